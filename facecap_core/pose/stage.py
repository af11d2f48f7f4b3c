"""The pose stage: keyframes in, calibrated cameras out.

1. pycolmap SfM on the keyframes (SIFT, sequential matching, incremental mapping).
2. Our geometric refinement: the keyframe tracker's LK tracks triangulated into the model and
   a bundle adjustment with the principal point free (``geometric.py``).
3. Photometric bundle adjustment from that start (``pba/``), hosting the sparse points at
   their depths, when ``config.method == "pba"``, on keyframes decoded at most
   ``config.pba.max_width`` wide; the sparse points are then re-triangulated with the final
   cameras.
"""

from __future__ import annotations

import logging
import tempfile
import time
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field

from facecap_core.camera import CAMERAS_JSON
from facecap_core.config import StrictModel
from facecap_core.errors import FacecapError, InputError
from facecap_core.keyframes import KEYFRAMES_JSON, Keyframes, load_keyframes
from facecap_core.photos import list_photos
from facecap_core.pose.cameras_json import Cameras
from facecap_core.pose.checks import (
    NOMINAL_HFOV_DEG,
    CameraSolveError,
    focal_problem,
    frame_numbers,
    solve_figures,
    solve_problem,
)
from facecap_core.pose.colmap_sfm import Poses, run_sfm
from facecap_core.pose.geometric import refine_with_tracks, triangulate
from facecap_core.pose.io import write_outputs
from facecap_core.pose.pba import PBAConfig, photometric_bundle_adjustment
from facecap_core.stage import Folders, Stage, capture_in
from facecap_core.video import read_frames

MIN_YAW_SPAN_DEG = 40.0
"""Fewest degrees round the head a capture's views must span (see
``LandmarkConfig.min_yaw_span_deg``)."""


class PoseConfig(StrictModel):
    """Camera poses of the keyframes (``facecap_core/pose/stage.py``): pycolmap SfM, our
    geometric refinement with the LK tracks, then photometric bundle adjustment."""

    sfm_width: int = Field(1280, ge=320, le=8192)
    """Keyframes are given to SIFT/SfM at most this wide (pixels)."""
    match_overlap: int = Field(10, ge=1, le=100)
    """Sequential matching pairs each keyframe with this many following ones."""
    use_tracks: bool = True
    """Add the keyframe tracker's LK tracks to the SfM model and re-adjust it with the
    principal point free (otherwise the SfM result is the geometric solution)."""
    method: Literal["geometric", "pba"] = "pba"
    """Final refinement: ``pba`` (photometric bundle adjustment) or ``geometric`` only."""
    pba: PBAConfig = Field(default_factory=lambda: PBAConfig())
    """Photometric bundle adjustment settings."""
    min_registered: int = Field(5, ge=3, le=1000)
    """Fewest registered keyframes to go on with (unregistered ones are left out)."""
    min_registered_fraction: float = Field(0.5, ge=0, le=1)
    """Fewest registered keyframes as a fraction of all: below it the capture is refused, as
    the views that did register are then as likely a lucky subset as the face."""
    threads: int = Field(1, ge=1, le=256)
    """Threads for SfM's matching and mapping and for the geometric refinement's bundle
    adjustment. One makes the stage reproducible (a rerun gives the same cameras, so nightly
    re-evaluations compare like with like); with more, COLMAP's threaded matching moves the
    focal length by up to 0.2 % from run to run, and Ceres's threaded Schur complement the
    cameras in their last digits."""
    extraction_threads: int = Field(2, ge=1, le=256)
    """Threads for SfM's SIFT extraction (one image each): an image's features do not
    depend on them (the same keypoints from 1 and 2 threads), so they cost no
    reproducibility; two halve the extraction, a third of SfM's time at 720p. The row lists it
    as key-neutral: a changed value reuses the stored cameras."""


POINTS = "points.ply"
SPARSE = "sparse.npz"
COLMAP_MODEL = ("colmap/cameras.txt", "colmap/images.txt", "colmap/points3D.txt",
                "colmap/rigs.txt", "colmap/frames.txt")
"""The COLMAP text model of the keyframes (the pose stage's own units), as pycolmap writes
it."""

log = logging.getLogger(__name__)


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
                           progress: bool = False, keyframes=None) -> Poses:
    """PBA of ``poses`` over the keyframes (grey, in poses' order, at full resolution or
    already at most ``config.pba.max_width`` wide); the sparse points are re-triangulated
    from their observations with the refined cameras (full-resolution intrinsics).
    ``keyframes``: the video's keyframes, whose times let PBA model motion blur and the
    rolling shutter (None, or photos: neither is modelled). A principal point the geometric
    refinement held at the image centre stays there (the tracks would pull it away again)."""

    pba_config = config.pba
    if poses.principal_point_held:
        pba_config = pba_config.model_copy(update={"hold_principal_point": True})
    times = interval = None
    if keyframes is not None and keyframes.ordered and len(keyframes.indices) > 1:
        at = dict(zip(keyframes.indices, keyframes.times))
        times = [at[i] for i in poses.frame_indices]
        interval = float(np.median(np.diff(keyframes.times) / np.diff(keyframes.indices)))
    result = photometric_bundle_adjustment(
        grey_keyframes, poses.intrinsics, poses.R, poses.t, poses.points, pba_config,
        progress=progress, sparse_hosts=track_hosts(poses.observations, len(poses.points)),
        centre_prior=True, times=times, frame_interval_s=interval,
        tracks=(poses.points, poses.observations))
    if result.exposure_fraction is not None:
        log.info("motion blur modelled with an exposure of %.3g of a frame",
                 result.exposure_fraction)
    points, rows = triangulate(poses.observations, result.R, result.t, result.intrinsics,
                               min_views=2, min_angle_deg=1.0)
    return Poses(result.intrinsics, list(poses.frame_indices), result.R, result.t, points,
                 poses.seconds + result.seconds, rows,
                 principal_point_held=poses.principal_point_held)


def sweep_order(poses: Poses) -> np.ndarray:
    """The views of ``poses`` in sweep order: by azimuth around the point their optical
    axes pass closest to (the head), about the mean camera "up", starting after the widest
    gap between neighbouring views. Photos come in any order; PBA's neighbourhoods and the
    depth maps' evenly spaced references need the order of a sweep."""
    R = np.asarray(poses.R)
    centres = np.array([-Rk.T @ tk for Rk, tk in zip(R, poses.t)])
    axes = R[:, 2, :]  # optical axes in the world
    # The point nearest every optical axis (least squares): sum (I - a a^T)(x - c) = 0.
    proj = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]
    target = np.linalg.lstsq(proj.sum(0), np.einsum("kij,kj->i", proj, centres), rcond=None)[0]
    up = -R[:, 1, :].mean(0)  # image y points down
    up /= np.linalg.norm(up)
    e1 = np.cross(up, axes.mean(0))
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    d = centres - target
    azimuth = np.arctan2(d @ e2, d @ e1)
    order = np.argsort(azimuth)
    gaps = np.diff(np.r_[azimuth[order], azimuth[order[0]] + 2 * np.pi])
    return np.roll(order, -(int(np.argmax(gaps)) + 1))


def reorder(poses: Poses, order: np.ndarray) -> Poses:
    """``poses`` with its views in ``order`` (observations renumbered)."""
    order = np.asarray(order, np.int64)
    position = np.empty(len(order), np.int64)
    position[order] = np.arange(len(order))
    obs = np.asarray(poses.observations, float).copy()
    if len(obs):
        obs[:, 1] = position[obs[:, 1].astype(np.int64)]
    return Poses(poses.intrinsics, [poses.frame_indices[k] for k in order],
                 [poses.R[k] for k in order], [poses.t[k] for k in order], poses.points,
                 poses.seconds, obs, principal_point_held=poses.principal_point_held)


def view_span_deg(poses: Poses) -> float:
    """The widest angle between two views' optical axes (degrees): how far the camera went
    round the subject."""
    axes = np.asarray(poses.R)[:, 2, :]
    if len(axes) < 2:
        return 0.0
    return float(np.degrees(np.arccos(np.clip((axes @ axes.T).min(), -1, 1))))


def registered_enough(poses: Poses, total: int, config: PoseConfig) -> None:
    """Refuse a capture of which SfM registered too few keyframes to go on with, saying
    whether the camera hardly moved round the head or the views did not match."""
    registered = len(poses.frame_indices)
    needed = max(config.min_registered, int(np.ceil(config.min_registered_fraction * total)))
    if registered >= needed:
        return
    span = view_span_deg(poses) if registered else 0.0
    if registered >= 2 and span < MIN_YAW_SPAN_DEG:
        raise InputError(
            f"only {registered} of {total} views could be registered, and those span "
            f"{span:.0f}° round the head: the camera hardly moved around the subject (a face "
            f"needs at least {MIN_YAW_SPAN_DEG:.0f}°, a full capture about 180°); record "
            "again, moving the camera from one ear round the face to the other")
    raise InputError(f"only {registered} of {total} keyframes could be registered (need "
                     f"{needed}): too little overlap or texture between the views; record "
                     "a slower, steadier sweep of a well-lit face")


def what_to_try(keyframes: Keyframes, numbers) -> str:
    """The advice of a failed camera solve, for the kind of capture."""
    if keyframes.ordered:
        return ("record a slower, steadier sweep of a well-lit face from one ear round to the "
                "other, with the phone's main (1×) camera")
    if numbers is not None:
        return ("if the numbered photos were not taken in sweep order, rename them in that "
                "order or give them names without numbers; or give the video itself (its "
                "tracking follows the views along the sweep), or photos that keep the camera's "
                "EXIF focal length")
    return ("name the photos in sweep order (frame_001.jpg, frame_002.jpg, …: they are then "
            "matched along it) or give the video itself")


def structure_from_motion(images: dict[int, np.ndarray], work: Path, keyframes: Keyframes,
                          config: PoseConfig, numbers=None, names=None
                          ) -> tuple[Poses, list | None]:
    """SfM's cameras of ``images``, checked (:func:`~facecap_core.pose.checks.solve_problem`),
    and the photo numbers the later checks hold them to. Cameras that fail a check are
    solved again once with what may fix them: photos whose file names may give their order
    (``numbers``) matched along it, a focal length outside a phone's started from a phone's
    nominal one. Numbered photos whose first solve fails only the order, and whose solve
    along the numbers does no better, were not taken in that order (photos come in any
    order): the first solve is kept and their numbers are not held to. Raises
    CameraSolveError when no solve passes, InputError when too few views register."""

    def solve(ordered: bool, focal_px: float | None, folder: str) -> Poses:
        poses = run_sfm(images, work / folder, keyframes.video_size,
                        overlap=config.match_overlap, threads=config.threads, ordered=ordered,
                        focal_px=focal_px, extraction_threads=config.extraction_threads)
        registered_enough(poses, len(keyframes.indices), config)
        return poses

    poses = solve(keyframes.ordered, keyframes.focal_px, "sfm")
    problem = solve_problem(poses, keyframes, numbers, names)
    if problem is None:
        return poses, numbers
    retries = []
    if not keyframes.ordered and numbers is not None:
        retries.append(("matching along the file names' order", True, keyframes.focal_px))
    if focal_problem(poses.intrinsics):
        nominal = (keyframes.video_size[0] / 2) / np.tan(np.radians(NOMINAL_HFOV_DEG) / 2)
        retries.append(("a phone's nominal focal length to start from", keyframes.ordered,
                        nominal))
    for how, ordered, focal_px in retries:
        log.warning("the camera solve failed (%s); structure from motion again with %s",
                    problem, how)
        try:
            again = solve(ordered, focal_px, "sfm-again")
        except FacecapError as exc:
            log.warning("... which failed too: %s", exc)
            continue
        again_problem = solve_problem(again, keyframes, numbers, names)
        if again_problem is None:
            return again, numbers
        log.warning("... which failed too: %s", again_problem)
    if numbers is not None and solve_problem(poses, keyframes, None, names) is None:
        log.warning("the photos' numbers do not follow the sweep (%s): they are put in sweep "
                    "order from the solve", problem)
        return poses, None
    raise CameraSolveError(problem, what_to_try(keyframes, numbers))


def checked(refined: Poses, step: str, keyframes: Keyframes, numbers=None,
            names=None) -> Poses | None:
    """``refined`` (the cameras after the refinement ``step``) when they pass the camera
    solve's checks, else None (with a warning): the previous step's cameras, which passed,
    are then kept."""
    problem = solve_problem(refined, keyframes, numbers, names)
    if problem is None:
        return refined
    log.warning("%s left the cameras wrong (%s): the cameras before it are kept", step, problem)
    return None


def photo_order(video: str | Path, keyframes: Keyframes):
    """A photo folder's file names and, where they are a video's frames numbered at a
    constant step, their numbers (:func:`~facecap_core.pose.checks.frame_numbers`): the
    order of the sweep. None, None for a video."""
    if keyframes.ordered:
        return None, None
    names = [path.name for path in list_photos(video)]
    return names, frame_numbers(names)


def estimate_poses(video: str | Path, keyframes, work_dir: str | Path,
                   config: PoseConfig | None = None, progress: bool = False
                   ) -> tuple[dict[str, Poses], list | None]:
    """The cameras of ``keyframes`` after each step: {"sfm", "geometric", "pba"} (the last
    two as configured, and only when they pass the camera solve's checks: a refinement that
    leaves them wrong is dropped), and the photo numbers the checks held them to (None: a
    video, or photos whose names give no order). Keyframes SfM cannot register are left out
    (the cameras file lists them); too few registered raises InputError, a solve that fails
    the checks CameraSolveError. Photos are put in sweep order."""

    config = config or PoseConfig()
    work = Path(work_dir)
    names, numbers = photo_order(video, keyframes)
    images = read_frames(video, keyframes.indices, width=config.sfm_width)
    with ThreadPoolExecutor(1) as pool:
        # PBA's keyframes, decoded straight to its processing width (it holds every keyframe
        # at once) in a thread while SfM runs: its mapping, on one thread, leaves a core free.
        greys = (pool.submit(read_frames, video, keyframes.indices,
                             width=config.pba.max_width, grey=True)
                 if config.method == "pba" else None)
        return refined_steps(images, work, keyframes, config, numbers, names, greys,
                             progress)


def refined_steps(images, work: Path, keyframes: Keyframes, config: PoseConfig,
                  numbers, names, greys: Future | None, progress: bool
                  ) -> tuple[dict[str, Poses], list | None]:
    """:func:`estimate_poses` from SfM's keyframes ``images`` and PBA's being decoded
    (``greys``)."""
    sfm, numbers = structure_from_motion(images, work, keyframes, config, numbers, names)
    if not keyframes.ordered:
        sfm = reorder(sfm, sweep_order(sfm))
    steps = {"sfm": sfm}
    current = sfm
    if config.use_tracks and len(keyframes.observations):
        refined = checked(refine_with_tracks(sfm, keyframes.observations, keyframes.indices,
                                             work / "geometric", threads=config.threads),
                          "the bundle adjustment with the tracks", keyframes, numbers, names)
        if refined is not None:
            current = steps["geometric"] = refined
    if config.method == "pba":
        start = time.perf_counter()
        grey = greys.result()
        grey_list = [grey[i] for i in current.frame_indices]
        refined = photometric_refinement(current, grey_list, config, progress, keyframes)
        refined.seconds = current.seconds + time.perf_counter() - start
        refined = checked(refined, "photometric bundle adjustment", keyframes, numbers, names)
        if refined is not None:
            current = steps["pba"] = refined
    return steps, numbers


def main(video: str | Path, keyframes_json: str | Path, out_dir: str | Path,
         config: PoseConfig | None = None, progress: bool = False) -> Path:
    """Cameras of the keyframes in ``keyframes_json``; writes ``out_dir/cameras.json``,
    ``points.ply``, ``sparse.npz`` and ``colmap/`` and returns the cameras.json path."""

    config = config or PoseConfig()
    keyframes = load_keyframes(keyframes_json)
    out = Path(out_dir)
    start, cpu = time.perf_counter(), time.process_time()
    # COLMAP's scratch (keyframe PNGs, database: ~100 MB at 720p) stays out of the artifact,
    # which every later stage downloads.
    with tempfile.TemporaryDirectory(prefix="facecap-poses-") as work:
        steps, numbers = estimate_poses(video, keyframes, work, config, progress)
    final = list(steps.values())[-1]
    dropped = [{"frame_index": int(i), "reason": "not registered by structure from motion "
                "(too few features matched to the other views)"}
               for i in keyframes.indices if i not in set(final.frame_indices)]
    if dropped:
        log.warning("%d of %d keyframes could not be registered and are left out",
                    len(dropped), len(keyframes.indices))
    log.info("cameras of %d keyframes by %s in %.1f s", len(final.frame_indices),
             " + ".join(steps), time.perf_counter() - start)
    solve = solve_figures(final, keyframes, numbers)
    return write_outputs(final, out, method=list(steps)[-1], dropped=dropped, solve=solve,
                         wall_seconds=round(time.perf_counter() - start, 2),
                         cpu_seconds=round(time.process_time() - cpu, 2))


def figures(folder: str | Path) -> dict:
    """Headline figures of a pose artifact for the run report and the UI (none where its
    files are missing: an artifact seeded by a test or a tool)."""
    path = Path(folder) / CAMERAS_JSON
    if not path.is_file():
        return {}
    cams = Cameras.read(path)
    return {"keyframes": len(cams.keyframes), "focal_px": round(cams.intrinsics.fx, 2),
            "dropped_keyframes": [d.model_dump() for d in cams.dropped or []],
            "solve": cams.solve.model_dump(exclude_unset=True) if cams.solve else {}}


def run(inputs: Folders, out: Path, config: PoseConfig, params: dict) -> None:
    main(capture_in(inputs["video"]), inputs["keyframes"] / KEYFRAMES_JSON, out, config)


STAGE = Stage("poses", version="8", inputs=("video", "keyframes"),
              work_seconds=106.8,
              section="poses", run=run, outputs=(CAMERAS_JSON, SPARSE, *COLMAP_MODEL),
              optional_outputs=(POINTS,),
              exported=(CAMERAS_JSON, POINTS, *COLMAP_MODEL), figures=figures,
              key_neutral={"extraction_threads": "an image's SIFT features do not depend on "
                           "the threads that extract them: the same cameras from 1, 2 or 3"})
