"""Time (and profile) one stage again on inputs already computed: the fit, or PBA.

    python benchmarks/bench_stage_speed.py fitting RUN STORE [--repeat 2] [--profile]
    python benchmarks/bench_stage_speed.py pba CAPTURE WORK [--repeat 2] [--profile]

``fitting``: RUN is a capture's output folder of `bench_pipeline.py` (its ``report.json``
names the fusion, coarse and frames artifacts in STORE); the fit is redone into a temporary
folder and its ``mesh.ply`` hashed, so that two versions of the code can be compared for
the same mesh. ``pba``: CAPTURE is a rendered capture (``video.mp4``, ``gt/``); its
keyframes and the pose stage's cameras before PBA (``estimate_poses`` with ``method:
geometric``) are computed once and kept in WORK, then PBA alone (the stage's
``photometric_refinement``) is timed and scored against the true cameras (the cameras' hash
printed likewise).
``--profile``: cProfile's 25 costliest functions (by own time) of the first repetition.
Run on a quiet machine; the first repetition includes numba's compilation where the
kernels' cache is cold.
"""

from __future__ import annotations

import argparse
import cProfile
import hashlib
import json
import pickle
import pstats
import tempfile
import time
from pathlib import Path

import numpy as np


def _timed(run, profile: bool):
    prof = cProfile.Profile() if profile else None
    start = time.perf_counter()
    if prof:
        prof.enable()
    result = run()
    seconds = time.perf_counter() - start
    if prof:
        prof.disable()
        pstats.Stats(prof).sort_stats("tottime").print_stats(25)
    return seconds, result


def fitting(run_dir: Path, store: Path, repeat: int, profile: bool) -> None:
    from facecap_core.fitting.stage import main

    stages = json.loads((run_dir / "report.json").read_text())["stages"]
    folder = {name: store / "artifacts" / stages[name]["key"]
              for name in ("fusion", "coarse", "frames")}
    for k in range(repeat):
        with tempfile.TemporaryDirectory() as out:
            seconds, mesh = _timed(lambda: main(folder["fusion"] / "cloud.ply", folder["coarse"],
                                                folder["frames"], out), profile and k == 0)
            digest = hashlib.sha256(Path(mesh).read_bytes()).hexdigest()[:16]
        print(f"fit {k + 1}: {seconds:.1f} s, mesh.ply sha256 {digest}", flush=True)


def pba(capture: Path, work: Path, repeat: int, profile: bool) -> None:
    from facecap.synthetic import load_gt_cameras
    from facecap_core.keyframes import KeyframeConfig, select_keyframes
    from facecap_core.pose.evaluate import pose_errors
    from facecap_core.pose.stage import PoseConfig, estimate_poses, photometric_refinement
    from facecap_core.video import read_frames

    video = capture / "video.mp4"
    work.mkdir(parents=True, exist_ok=True)
    start = work / f"{capture.name}_geometric.pkl"
    config = PoseConfig()
    if not start.is_file():
        keyframes = select_keyframes(video, KeyframeConfig())
        steps, _ = estimate_poses(video, keyframes, work / "poses",
                                  config.model_copy(update={"method": "geometric"}))
        geometric = list(steps.values())[-1]  # PBA's start, as in the stage
        start.write_bytes(pickle.dumps((keyframes, geometric)))
    keyframes, geometric = pickle.loads(start.read_bytes())
    greys = read_frames(video, geometric.frame_indices, width=config.pba.max_width, grey=True)
    grey_list = [greys[i] for i in geometric.frame_indices]
    intr_gt, gt = load_gt_cameras(capture / "gt" / "cameras.json")
    idx = geometric.frame_indices
    for k in range(repeat):
        seconds, poses = _timed(lambda: photometric_refinement(
            geometric, grey_list, config, keyframes=keyframes), profile and k == 0)
        err = pose_errors(poses.R, poses.t, poses.intrinsics, [gt[i]["R"] for i in idx],
                          [gt[i]["t"] for i in idx], intr_gt)
        digest = hashlib.sha256(np.array(poses.R).tobytes() + np.array(poses.t).tobytes()).hexdigest()[:16]
        print(f"pba {k + 1}: {seconds:.1f} s, rotation {err['rotation_deg']:.4f}°, centre "
              f"{err['centre_pct']:.4f} %, focal {err['focal_pct']:.4f} %, principal point "
              f"{err['principal_point_px']:.3f} px, cameras sha256 {digest}", flush=True)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("stage", choices=("fitting", "pba"))
    p.add_argument("source", type=Path, help="RUN (fitting) or CAPTURE (pba)")
    p.add_argument("place", type=Path, help="STORE (fitting) or WORK (pba)")
    p.add_argument("--repeat", type=int, default=2)
    p.add_argument("--profile", action="store_true")
    args = p.parse_args()
    (fitting if args.stage == "fitting" else pba)(args.source, args.place, args.repeat,
                                                  args.profile)


if __name__ == "__main__":
    main()
