"""Peak memory on a long video: 60 s at 120 fps in 1080p (7,200 frames) through the keyframe
stage, directly and through the service, and on to the poses; or (``--face``) a 4K, 60 s,
60 fps capture of a face through the whole pipeline.

    python benchmarks/bench_memory.py [--seconds 60] [--fps 120] [--width 1920] [--height 1080]
        [--out out/bench_memory] [--poses]
    python benchmarks/bench_memory.py --face [--seconds 60] [--fps 60] [--width 3840]
        [--height 2160] [--out out/bench_memory_4k] [--until STAGE] [--pba-width N|full]

The orbit video is generated on the fly and streamed into the encoder one frame at a time: an
orbit seen from the camera, i.e. a textured disk that stays in the middle of the picture while
the textured background slides past (the parallax of a camera circling the head), with no
face. Each measured step runs in a fresh process whose peak resident memory (VmHWM) is polled
while it runs, and so are its descendants', so that the embedded Prefect server of the CLI (a
process of its own) is reported separately when it is found; ru_maxrss from ``wait4`` when it
exits is given too (the largest of the process, the children it reaped, and this script when
it started the step: Linux carries a peak across exec, so the videos are made in a child
process and this script stays small):

- ``decode``: every frame decoded at full resolution (the floor: one frame and the decoder);
- ``keyframes stage``: ``facecap_core.keyframes.main`` (tracking at 640 px);
- ``reconstruct --until keyframes``: the same through the CLI and the capture flow;
- ``--poses``: ``reconstruct --until poses`` (keyframes at ``sfm_width``; slow on 2 cores).

``--face``: rendering 3,600 4K frames is far too slow on 2 cores, so ``facecap synth``
renders a 6 s, 30 fps, 1280×720 ear-to-ear sweep (ICT identity 3, seed 0; 180 frames), and
the capture is built from it, streamed: the sweep slowed to last ``--seconds`` (each output
frame a cross-fade of the two nearest rendered ones) and upscaled (bicubic) to the target
size. Then, with a fresh store
(``FACECAP_STORE`` in OUT), ``facecap reconstruct --until S`` runs once per stage S, each in a
fresh process; the earlier stages come from the store, so each row is one stage's cost (plus
the CLI's start and its cache look-ups). The last step scores the mesh against the synthetic
ground truth. ``--pba-width`` sets ``poses.pba.max_width`` (``full``: no bound, the
behaviour before the bound); its rows go to their own store and report.

Bar: ≤ 4 GB. Prints the table and writes OUT/report.md (OUT/report-pba-W.md with
``--pba-width W``).
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from facecap.tasks.graph import STEPS

ROOT = Path(__file__).resolve().parents[1]
BAR_GB = 4.0
STAGES = STEPS  # what --until can stop after
SYNTH = ["--subject", "ict:3", "--width", "1280", "--height", "720", "--fps", "30",
         "--seconds", "6", "--seed", "0"]
"""The rendered sweep the --face capture is built from (``facecap synth`` options)."""


def make_video(path: Path | str, seconds: float, fps: int, width: int, height: int) -> Path:
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
            _encode(container, stream, image, i)
        _encode(container, stream, None, None)
    return path


def _encode(container, stream, image: np.ndarray | None, pts: int | None) -> None:
    """One RGB frame into the stream (``None``: flush the encoder)."""
    import av

    frame = None
    if image is not None:
        frame = av.VideoFrame.from_ndarray(image, format="rgb24")
        frame.pts = pts
    for packet in stream.encode(frame):
        container.mux(packet)


def _peak_kb(pid: int) -> tuple[int, str] | None:
    """A live process's peak resident memory (VmHWM, kB) and its command line."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
    except OSError:
        return None
    for line in status.splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]), cmdline
    return None


def _descendants(pid: int) -> list[int]:
    import psutil

    try:
        return [p.pid for p in psutil.Process(pid).children(recursive=True)]
    except psutil.Error:
        return []


def is_server(cmdline: str) -> bool:
    """Whether a command line is Prefect's embedded API server (uvicorn in a subprocess)."""
    return "uvicorn" in cmdline or ("prefect" in cmdline and "server" in cmdline)


def measure(command: list[str], env: dict | None = None, log: Path | None = None,
            poll_s: float = 0.5) -> dict:
    """Run a command in a fresh process; its wall and CPU seconds (its reaped children
    included), its peak RSS from wait4 (MB: the largest of the process and the children it
    reaped), its own peak (VmHWM, polled) and that of the embedded Prefect server among its
    descendants, when one is found."""
    import tempfile

    start = time.perf_counter()
    out = open(log, "w+") if log else tempfile.TemporaryFile("w+")
    with out:
        proc = subprocess.Popen(command, cwd=ROOT, env=env, stdout=out,
                                stderr=subprocess.STDOUT, text=True)
        own, peaks = 0, {}
        while True:
            pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
            if pid:
                break
            sample = _peak_kb(proc.pid)
            if sample:
                own = max(own, sample[0])
            for child in _descendants(proc.pid):
                sample = _peak_kb(child)
                if sample:
                    peaks[child] = (max(sample[0], peaks.get(child, (0, ""))[0]), sample[1])
            time.sleep(poll_s)
        proc.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        output = out.read()
    server = [kb for kb, cmd in peaks.values() if is_server(cmd)]
    return {"code": proc.returncode, "wall_s": round(time.perf_counter() - start, 1),
            "cpu_s": round(usage.ru_utime + usage.ru_stime, 1),
            "peak_rss_mb": round(usage.ru_maxrss / 1024, 1),
            # A process that ended before the first sample: its ru_maxrss (an upper bound).
            "own_peak_mb": round((own or usage.ru_maxrss) / 1024, 1),
            "server_peak_mb": round(max(server) / 1024, 1) if server else None,
            "tail": output[-2000:]}


def make_face_video(source: Path | str, path: Path | str, seconds: float, fps: int,
                    width: int, height: int) -> Path:
    """``source`` slowed to last ``seconds`` at ``fps`` and upscaled (bicubic) to
    width×height. Output frame i sits at source position x = i (n_src - 1) / (n_out - 1) and
    is the cross-fade of source frames floor(x) and floor(x) + 1 (a stand-in for the motion
    between them: repeated frames would make a stop-and-go sweep). Streamed: two source
    frames and one output frame in memory."""
    import av
    import cv2

    from facecap_core.video import iter_frames, stored_frame_count

    n_src = stored_frame_count(source)
    n_out = int(round(seconds * fps))
    frames = iter_frames(source)
    pair = [next(frames).image, next(frames).image]
    first = 0  # source index of pair[0]
    with av.open(str(path), "w", format="mp4") as container:
        stream = container.add_stream("libx264", rate=fps)
        stream.width, stream.height, stream.pix_fmt = width, height, "yuv420p"
        stream.options = {"preset": "ultrafast", "crf": "20"}
        for i in range(n_out):
            x = i * (n_src - 1) / max(1, n_out - 1)
            j = min(int(x), n_src - 2)
            while first < j:
                pair = [pair[1], next(frames).image]
                first += 1
            blend = cv2.addWeighted(pair[0], 1 - (x - j), pair[1], x - j, 0)
            big = cv2.resize(blend, (width, height), interpolation=cv2.INTER_CUBIC)
            _encode(container, stream, big, i)
        _encode(container, stream, None, None)
    return Path(path)


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


def _timed(label: str, function: str, *args) -> None:
    """``function(*args)`` of this module in a child process: Linux carries a process's peak
    RSS across exec into the ru_maxrss of what it starts next, so this process stays small
    (the video generators hold frames and encoders)."""
    print(f"{label} ...", flush=True)
    start = time.perf_counter()
    code = (f"import sys; sys.path[:0] = [{str(ROOT)!r}, {str(ROOT / 'benchmarks')!r}]; "
            f"import bench_memory; bench_memory.{function}(*{args!r})")
    subprocess.run([sys.executable, "-c", code], cwd=ROOT, check=True)
    print(f"  {time.perf_counter() - start:.0f} s wall", flush=True)


def face_steps(args, out: Path, py: list[str], env: dict) -> tuple[Path, list, str]:
    """The --face capture (synthesized and built if missing) and its measured steps."""
    synth = out / "synth"
    if not (synth / "video.mp4").is_file():
        print("facecap synth " + " ".join(SYNTH), flush=True)
        subprocess.run(py + ["-m", "facecap", "synth", "--out", str(synth), "--quiet", *SYNTH],
                       cwd=ROOT, env=env, check=True)
    video = out / f"face_{args.width}x{args.height}_{args.fps}fps_{args.seconds:g}s.mp4"
    if not video.is_file():
        part = video.with_name(video.stem + ".part.mp4")
        _timed(f"building {video.name}", "make_face_video", str(synth / "video.mp4"),
               str(part), args.seconds, args.fps, args.width, args.height)
        part.rename(video)
    tag = "" if args.pba_width is None else f"-pba-{args.pba_width}"
    store, result = out / f"store{tag}", out / f"result{tag}"
    shutil.rmtree(store, ignore_errors=True)  # a fresh store: every stage computed once
    env["FACECAP_STORE"] = str(store)
    config = []
    if args.pba_width is not None:
        width = "null" if args.pba_width == "full" else int(args.pba_width)
        (out / f"config{tag}.yaml").write_text(f"poses: {{pba: {{max_width: {width}}}}}\n")
        config = ["--config", str(out / f"config{tag}.yaml")]
    steps = [("decode (full resolution)", py + ["-c", DECODE, str(video)])]
    for stage in STAGES[:STAGES.index(args.until) + 1]:
        scan = (["--scan", str(synth / "gt" / "mesh.ply"), "--scan-landmarks",
                 str(synth / "gt" / "landmarks.json")] if stage == "evaluation" else [])
        steps.append((f"reconstruct --until {stage}",
                      py + ["-m", "facecap", "reconstruct", str(video), "--out", str(result),
                            "--until", stage, *config, *scan]))
    return video, steps, tag


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--face", action="store_true",
                        help="a capture of a face (4K, 60 s, 60 fps) through every stage")
    parser.add_argument("--seconds", type=float, default=60)
    parser.add_argument("--fps", type=int, default=None, help="120; --face: 60")
    parser.add_argument("--width", type=int, default=None, help="1920; --face: 3840")
    parser.add_argument("--height", type=int, default=None, help="1080; --face: 2160")
    parser.add_argument("--out", type=Path, default=None,
                        help="out/bench_memory; --face: out/bench_memory_4k")
    parser.add_argument("--poses", action="store_true", help="also run up to the poses")
    parser.add_argument("--until", choices=STAGES, default="evaluation",
                        help="--face: the last stage to run")
    parser.add_argument("--pba-width", default=None,
                        help="--face: poses.pba.max_width (pixels, or 'full' for no bound)")
    args = parser.parse_args()
    face = {"fps": 60, "width": 3840, "height": 2160, "out": ROOT / "out" / "bench_memory_4k"}
    orbit = {"fps": 120, "width": 1920, "height": 1080, "out": ROOT / "out" / "bench_memory"}
    for key, value in (face if args.face else orbit).items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    (out / "logs").mkdir(exist_ok=True)
    py = [sys.executable]
    env = {**os.environ, "PYTHONPATH": str(ROOT), "FACECAP_HOME": os.environ.get(
        "FACECAP_HOME", str(Path.home() / ".cache" / "facecap"))}
    tag = ""
    if args.face:
        video, steps, tag = face_steps(args, out, py, env)
    else:
        video = out / f"orbit_{args.width}x{args.height}_{args.fps}fps_{args.seconds:g}s.mp4"
        if not video.is_file():
            _timed(f"generating {video}", "make_video", str(video), args.seconds, args.fps,
                   args.width, args.height)
        steps = [("decode (full resolution)", py + ["-c", DECODE, str(video)]),
                 ("keyframes stage", py + ["-c", KEYFRAMES, str(video), str(out / "keyframes")]),
                 ("reconstruct --until keyframes",
                  py + ["-m", "facecap", "reconstruct", str(video), "--out",
                        str(out / "result"), "--store", str(out / "store"), "--until",
                        "keyframes"])]
        if args.poses:
            config = out / "poses.yaml"
            config.write_text("poses: {method: geometric}\n")
            steps.append(("reconstruct --until poses",
                          py + ["-m", "facecap", "reconstruct", str(video), "--out",
                                str(out / "result"), "--store", str(out / "store"), "--until",
                                "poses", "--config", str(config)]))
    rows = []
    for name, command in steps:
        print(f"{name} ...", flush=True)
        log = out / "logs" / f"{name.replace(' ', '_').replace('-', '')}{tag}.log"
        result = measure(command, env, log)
        rows.append((name, result))
        last = [line for line in result["tail"].splitlines() if line.strip()][-1:]
        print(f"  exit {result['code']}, {result['wall_s']} s wall, {result['cpu_s']} s CPU, "
              f"peak RSS {result['peak_rss_mb']} MB (own {result['own_peak_mb']} MB, server "
              f"{result['server_peak_mb']} MB)  {last[0] if last else ''}", flush=True)
        if result["code"] != 0:
            print(result["tail"], flush=True)
            break
    peak_gb = max(r["peak_rss_mb"] for _, r in rows) / 1024
    both_gb = max(r["own_peak_mb"] + (r["server_peak_mb"] or 0) for _, r in rows) / 1024
    command = "python benchmarks/bench_memory.py" + (" --poses" if args.poses else "") + (
        f" --face --until {args.until}" if args.face else "") + (
        f" --pba-width {args.pba_width}" if args.pba_width is not None else "")
    what = ("a face, built from `facecap synth " + " ".join(SYNTH) + "` (upscaled, retimed)"
            if args.face else "an orbit without a face")
    def server(r):
        return "–" if r["server_peak_mb"] is None else r["server_peak_mb"]

    lines = [
        "# Peak memory on a long video\n",
        f"`{video.name}`: {args.seconds:g} s, {args.fps} fps, {args.width}x{args.height} "
        f"({int(round(args.seconds * args.fps))} frames, {video.stat().st_size / 1e6:.0f} MB), "
        f"{what}. Each step in a fresh process. own: its peak RSS (VmHWM, polled); server: "
        "that of the embedded Prefect server, a child process of the CLI; peak RSS: ru_maxrss "
        "from wait4, the largest of the process, the children it reaped and the RSS of this "
        "script when it started the step (Linux carries it across exec).\n",
        "| step | exit | wall s | CPU s | peak RSS MB | own MB | server MB |",
        "|---|---|---|---|---|---|---|",
        *(f"| {name} | {r['code']} | {r['wall_s']} | {r['cpu_s']} | {r['peak_rss_mb']} | "
          f"{r['own_peak_mb']} | {server(r)} |" for name, r in rows),
        f"\nLargest peak: {peak_gb:.2f} GB; process + server {both_gb:.2f} GB (bar "
        f"{BAR_GB:g} GB: {'met' if both_gb <= BAR_GB and all(r['code'] == 0 for _, r in rows) else 'NOT met'}).",
        f"\nCommand: `{command}`",
    ]
    (out / f"report{tag}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
