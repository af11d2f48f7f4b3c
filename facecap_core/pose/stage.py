"""The pose stage: keyframes in, calibrated cameras out.

1. pycolmap SfM on the keyframes (SIFT, sequential matching, incremental mapping).
2. Our geometric refinement: the keyframe tracker's LK tracks triangulated into the model and
   a bundle adjustment with the principal point free (``geometric.py``).
3. Photometric bundle adjustment from that start (``pba.py``), hosting the sparse points at
   their depths, when ``config.method == "pba"``; the sparse points are then re-triangulated
   with the final cameras.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from facecap_core.config import PoseConfig
from facecap_core.errors import InputError
from facecap_core.pose.colmap_sfm import Poses, run_sfm
from facecap_core.pose.geometric import refine_with_tracks, triangulate
from facecap_core.pose.io import write_outputs


def track_hosts(observations: np.ndarray, n_points: int) -> np.ndarray:
    """For each point, the middle view of its track (its PBA host keyframe)."""
    hosts = np.full(n_points, -1, np.int64)
    obs = np.asarray(observations)
    order = np.lexsort((obs[:, 1], obs[:, 0]))
    points = obs[order, 0].astype(np.int64)
    starts = np.flatnonzero(np.r_[True, points[1:] != points[:-1]])
    ends = np.r_[starts[1:], len(points)]
    hosts[points[starts]] = obs[order[(starts + ends) // 2], 1].astype(np.int64)
    return hosts


def photometric_refinement(poses: Poses, grey_keyframes: list[np.ndarray], config: PoseConfig,
                           progress: bool = False) -> Poses:
    """PBA of ``poses`` over the keyframes (grey, full resolution, in poses' order); the
    sparse points are re-triangulated from their observations with the refined cameras."""
    from facecap_core.pose.pba import photometric_bundle_adjustment

    result = photometric_bundle_adjustment(
        grey_keyframes, poses.intrinsics, poses.R, poses.t, poses.points, config.pba,
        progress=progress, sparse_hosts=track_hosts(poses.observations, len(poses.points)),
        centre_prior=True)
    points, rows = triangulate(poses.observations, result.R, result.t, result.intrinsics,
                               min_views=2, min_angle_deg=1.0)
    return Poses(result.intrinsics, list(poses.frame_indices), result.R, result.t, points,
                 poses.seconds + result.seconds, rows)


def estimate_poses(video: str | Path, keyframes, work_dir: str | Path,
                   config: PoseConfig | None = None, progress: bool = False) -> dict[str, Poses]:
    """The cameras of ``keyframes`` after each step: {"sfm", "geometric", "pba"} (the last
    two as configured). Raises InputError unless SfM registers every keyframe."""
    from facecap_core.video import read_frames

    config = config or PoseConfig()
    work = Path(work_dir)
    images = read_frames(video, keyframes.indices, width=config.sfm_width)
    sfm = run_sfm(images, work / "sfm", keyframes.video_size, overlap=config.match_overlap,
                  threads=config.threads)
    missing = len(keyframes.indices) - len(sfm.frame_indices)
    if missing:
        raise InputError(f"{missing} of {len(keyframes.indices)} keyframes could not be "
                         "registered (too little overlap or texture between them); record a "
                         "slower, steadier sweep of a well-lit face")
    steps = {"sfm": sfm}
    current = sfm
    if config.use_tracks:
        current = refine_with_tracks(sfm, keyframes.observations, keyframes.indices,
                                     work / "geometric")
        steps["geometric"] = current
    if config.method == "pba":
        start = time.perf_counter()
        greys = read_frames(video, keyframes.indices, grey=True)
        grey_list = [greys[i] for i in current.frame_indices]
        refined = photometric_refinement(current, grey_list, config, progress)
        refined.seconds = current.seconds + time.perf_counter() - start
        current = steps["pba"] = refined
    return steps


def main(video: str | Path, keyframes_json: str | Path, out_dir: str | Path,
         config: PoseConfig | None = None, progress: bool = False) -> Path:
    """Cameras of the keyframes in ``keyframes_json``; writes ``out_dir/cameras.json``,
    ``points.ply``, ``sparse.npz`` and ``colmap/`` and returns the cameras.json path."""
    from facecap_core.keyframes import load_keyframes

    config = config or PoseConfig()
    keyframes = load_keyframes(keyframes_json)
    out = Path(out_dir)
    start, cpu = time.perf_counter(), time.process_time()
    # COLMAP's scratch (keyframe PNGs, database: ~100 MB at 720p) stays out of the artifact,
    # which every later stage downloads.
    with tempfile.TemporaryDirectory(prefix="facecap-poses-") as work:
        steps = estimate_poses(video, keyframes, work, config, progress)
    final = list(steps.values())[-1]
    return write_outputs(final, out, method=list(steps)[-1],
                         wall_seconds=round(time.perf_counter() - start, 2),
                         cpu_seconds=round(time.process_time() - cpu, 2))
