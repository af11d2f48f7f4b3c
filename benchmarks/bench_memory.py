"""Peak memory on a long video: 60 s at 120 fps in 1080p (7,200 frames) through the keyframe
stage, directly and through the service, and on to the poses.

    python benchmarks/bench_memory.py [--seconds 60] [--fps 120] [--width 1920] [--height 1080]
        [--out out/bench_memory] [--poses]

The video is generated on the fly and streamed into the encoder one frame at a time: an orbit
seen from the camera, i.e. a textured disk that stays in the middle of the picture while the
textured background slides past (the parallax of a camera circling the head), with no face.
Each measured step runs in a fresh process whose peak resident memory (ru_maxrss) is read
when it exits:

- ``decode``: every frame decoded at full resolution (the floor: one frame and the decoder);
- ``keyframes stage``: ``facecap_core.keyframes.main`` (tracking at 640 px);
- ``reconstruct --until keyframes``: the same through the CLI and the capture flow (the
  embedded Prefect server is a process of its own, reported separately when it can be found);
- ``--poses``: ``reconstruct --until poses`` (keyframes at ``sfm_width``; slow on 2 cores).

Bar: ≤ 4 GB. Prints the table and writes OUT/report.md.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
BAR_GB = 4.0


def make_video(path: Path, seconds: float, fps: int, width: int, height: int) -> Path:
    """The orbit video, frame by frame into libx264 (memory: one frame and the encoder)."""
    import av
    import cv2

    rng = np.random.default_rng(0)
    frames = int(round(seconds * fps))
    slide = 2.0 * width / frames  # the background slides two picture widths in all

    def texture(h: int, w: int, cell: int) -> np.ndarray:
        small = rng.integers(0, 255, (h // cell + 2, w // cell + 2, 3), np.uint8)
        return cv2.resize(small, ((w // cell + 2) * cell, (h // cell + 2) * cell),
                          interpolation=cv2.INTER_CUBIC)[:h, :w]

    background = texture(height, width * 3 + 8, 12)
    radius = height // 3
    disk = texture(2 * radius, 2 * radius * 4, 8)  # the disk's surface turns 3 diameters
    yy, xx = np.mgrid[-radius:radius, -radius:radius]
    inside = (xx ** 2 + yy ** 2) < radius ** 2
    cy, cx = height // 2, width // 2
    with av.open(str(path), "w", format="mp4") as container:
        stream = container.add_stream("libx264", rate=fps)
        stream.width, stream.height, stream.pix_fmt = width, height, "yuv420p"
        stream.options = {"preset": "ultrafast", "crf": "23"}
        for i in range(frames):
            x = int(i * slide)
            image = background[:, x:x + width].copy()
            turn = int(i * 6 * radius / frames)
            patch = image[cy - radius:cy + radius, cx - radius:cx + radius]
            patch[inside] = disk[:, turn:turn + 2 * radius][inside]
            frame = av.VideoFrame.from_ndarray(image, format="rgb24")
            frame.pts = i
            for packet in stream.encode(frame):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    return path


def measure(command: list[str], env: dict | None = None) -> dict:
    """Run a command in a fresh process; its wall and CPU seconds and peak RSS (MB)."""
    start = time.perf_counter()
    proc = subprocess.Popen(command, cwd=ROOT, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    output = proc.stdout.read()
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    return {"code": proc.returncode, "wall_s": round(time.perf_counter() - start, 1),
            "cpu_s": round(usage.ru_utime + usage.ru_stime, 1),
            "peak_rss_mb": round(usage.ru_maxrss / 1024, 1), "tail": output[-2000:]}


DECODE = """
import sys
from facecap_core.video import iter_frames
n = sum(1 for _ in iter_frames(sys.argv[1]))
print(f"decoded {n} frames")
"""

KEYFRAMES = """
import json, sys
from facecap_core import keyframes
path = keyframes.main(sys.argv[1], sys.argv[2])
doc = json.loads(open(path).read())
print(f"{len(doc['frame_indices'])} keyframes of {doc['frames_read']} frames")
"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=60)
    parser.add_argument("--fps", type=int, default=120)
    parser.add_argument("--width", type=int, default=1920)
    parser.add_argument("--height", type=int, default=1080)
    parser.add_argument("--out", type=Path, default=ROOT / "out" / "bench_memory")
    parser.add_argument("--poses", action="store_true", help="also run up to the poses")
    args = parser.parse_args()
    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    video = out / f"orbit_{args.width}x{args.height}_{args.fps}fps_{args.seconds:g}s.mp4"
    if not video.is_file():
        print(f"generating {video} ...", flush=True)
        start, cpu = time.perf_counter(), time.process_time()
        make_video(video, args.seconds, args.fps, args.width, args.height)
        print(f"  {time.perf_counter() - start:.0f} s wall, {time.process_time() - cpu:.0f} s "
              f"CPU, {video.stat().st_size / 1e6:.0f} MB", flush=True)
    py = [sys.executable]
    env = {**os.environ, "PYTHONPATH": str(ROOT), "FACECAP_HOME": os.environ.get(
        "FACECAP_HOME", str(Path.home() / ".cache" / "facecap"))}
    steps = [("decode (full resolution)", py + ["-c", DECODE, str(video)]),
             ("keyframes stage", py + ["-c", KEYFRAMES, str(video), str(out / "keyframes")]),
             ("reconstruct --until keyframes",
              py + ["-m", "flows.cli", "reconstruct", str(video), "--out", str(out / "result"),
                    "--store", str(out / "store"), "--until", "keyframes"])]
    if args.poses:
        config = out / "poses.yaml"
        config.write_text("poses: {method: geometric}\n")
        steps.append(("reconstruct --until poses",
                      py + ["-m", "flows.cli", "reconstruct", str(video), "--out",
                            str(out / "result"), "--store", str(out / "store"), "--until",
                            "poses", "--config", str(config)]))
    rows = []
    for name, command in steps:
        print(f"{name} ...", flush=True)
        result = measure(command, env)
        rows.append((name, result))
        last = [line for line in result["tail"].splitlines() if line.strip()][-1:]
        print(f"  exit {result['code']}, {result['wall_s']} s wall, {result['cpu_s']} s CPU, "
              f"peak RSS {result['peak_rss_mb']} MB  {last[0] if last else ''}", flush=True)
    peak_gb = max(r["peak_rss_mb"] for _, r in rows) / 1024
    lines = [
        f"# Peak memory on a long video\n",
        f"`{video.name}`: {args.seconds:g} s, {args.fps} fps, {args.width}x{args.height} "
        f"({int(round(args.seconds * args.fps))} frames, {video.stat().st_size / 1e6:.0f} MB). "
        f"Each step in a fresh process; peak RSS is the process's ru_maxrss (the embedded "
        "Prefect server of the CLI runs in a process of its own, not counted).\n",
        "| step | exit | wall s | CPU s | peak RSS MB |", "|---|---|---|---|---|",
        *(f"| {name} | {r['code']} | {r['wall_s']} | {r['cpu_s']} | {r['peak_rss_mb']} |"
          for name, r in rows),
        f"\nLargest peak: {peak_gb:.2f} GB (bar {BAR_GB:g} GB: "
        f"{'met' if peak_gb <= BAR_GB else 'NOT met'}).",
        f"\nCommand: `python benchmarks/bench_memory.py{' --poses' if args.poses else ''}`",
    ]
    (out / "report.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
