"""Geometric refinement of the SfM start: the keyframe tracker's long LK tracks as extra
observations, and a bundle adjustment that also frees the principal point (held at the
image centre where the tracks would put it further than a phone camera's).

SIFT matches between keyframes span a few keyframes at most (the face's appearance changes
quickly as the camera circles it), while LK tracks follow a feature through every frame of
the video and often cover 15–40 keyframes. Longer tracks tie the chain of cameras together
over wider angles, where the principal point and focal length stop trading off against the
cameras' rotations. Ceres (through pycolmap) does the adjustment.
"""

from __future__ import annotations

import logging
import shutil
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from facecap_core.camera import Intrinsics, camera_center, project, undistort
from facecap_core.native_logs import native_stderr_to_log
from facecap_core.pose.colmap_sfm import Poses
from facecap_core.pose.io import write_colmap_text

# Imported where used: pycolmap only where the geometric refinement runs.

log = logging.getLogger(__name__)

PRINCIPAL_POINT_MAX_PCT = 3.0
"""Furthest a phone camera's principal point lies from the image centre (% of the image's
width for x, of its height for y): three standard deviations of facecap's sensor model (1 %);
the real 240×320 phone sweep's own calibration puts it 0.4 % and 0.25 % off. The tracks put
it further when they carry a distortion the camera model lacks: a 30 ms rolling shutter on a
240×320 phone-like sweep moved it 4.5 % (14.5 px), turning every camera 3.4° with it. Beyond
this the principal point is held at the centre."""


def triangulate(observations: np.ndarray, R: list[np.ndarray], t: list[np.ndarray],
                intr: Intrinsics, min_views: int = 3, max_error_px: float = 2.0,
                min_angle_deg: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """Points of observation tracks by linear triangulation, checked.

    ``observations`` rows are (track id, view, x, y) in full-resolution pixels. A track is
    kept when it has ``min_views`` views, lies in front of all of them, reprojects within
    ``max_error_px`` in every view and its rays span ``min_angle_deg``. Returns the points
    (M, 3) and the kept observations renumbered (point number, view, x, y).
    """
    obs = np.asarray(observations, float)
    if len(obs) == 0:
        return np.zeros((0, 3)), np.zeros((0, 4))
    ids, inverse, counts = np.unique(obs[:, 0], return_inverse=True, return_counts=True)
    order = np.argsort(inverse, kind="stable")
    starts = np.concatenate([[0], np.cumsum(counts)])
    xy = undistort(np.column_stack([(obs[:, 2] - intr.cx) / intr.fx,
                                    (obs[:, 3] - intr.cy) / intr.fy]), intr.k1, intr.k2)
    P = np.stack([np.column_stack([r, x]) for r, x in zip(R, t)])  # (K, 3, 4)
    centres = np.array([camera_center(r, x) for r, x in zip(R, t)])
    points, rows = [], []
    for j in range(len(ids)):
        sel = order[starts[j]:starts[j + 1]]
        if len(sel) < min_views:
            continue
        views = obs[sel, 1].astype(np.int64)
        Pv = P[views]
        A = np.concatenate([xy[sel, 0, None] * Pv[:, 2] - Pv[:, 0],
                            xy[sel, 1, None] * Pv[:, 2] - Pv[:, 1]])
        X = np.linalg.svd(A)[2][-1]
        if abs(X[3]) < 1e-12:
            continue
        X = X[:3] / X[3]
        in_cameras = np.einsum("kij,j->ki", Pv[:, :, :3], X) + Pv[:, :, 3]
        if np.any(in_cameras[:, 2] <= 0):
            continue
        # Every view at once: the points are already in their cameras' frames.
        pixels = project(in_cameras, np.eye(3), np.zeros(3), intr)[0]
        if np.max(np.linalg.norm(pixels - obs[sel, 2:4], axis=1)) > max_error_px:
            continue
        rays = X - centres[views]
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        if np.degrees(np.arccos(np.clip((rays @ rays.T).min(), -1, 1))) < min_angle_deg:
            continue
        n = len(points)
        points.append(X)
        rows.append(np.column_stack([np.full(len(sel), n), obs[sel, 1:]]))
    if not points:
        return np.zeros((0, 3)), np.zeros((0, 4))
    return np.array(points), np.concatenate(rows)


def bundle_adjust(poses: Poses, work_dir: str | Path, refine_intrinsics: bool = True,
                  names: list[str] | None = None, hold_principal_point: bool = False,
                  threads: int = 1) -> Poses:
    """Ceres bundle adjustment (pycolmap) of poses, points and, if asked, focal length,
    principal point (unless ``hold_principal_point``) and k1, k2 over
    ``poses.observations``. On one of ``threads`` the result is the same on every run; on
    more (COLMAP's default is every core), Ceres's threads sum in the order they finish,
    which moves the cameras in their last digits from run to run."""
    import pycolmap


    start = time.perf_counter()
    work = Path(work_dir)
    shutil.rmtree(work, ignore_errors=True)
    write_colmap_text(poses, work, names)
    rec = pycolmap.Reconstruction(str(work))
    options = pycolmap.BundleAdjustmentOptions()
    options.refine_focal_length = refine_intrinsics
    options.refine_principal_point = refine_intrinsics and not hold_principal_point
    options.refine_extra_params = refine_intrinsics
    options.print_summary = False
    options.ceres.solver_options.num_threads = threads
    with native_stderr_to_log(log, prefix="colmap: "):
        pycolmap.bundle_adjustment(rec, options)
    return _from_reconstruction(rec, poses, time.perf_counter() - start)


def _from_reconstruction(rec, poses: Poses, seconds: float) -> Poses:
    """Poses, intrinsics and points read back from a model written by write_colmap_text."""
    cam = next(iter(rec.cameras.values()))
    f, cx, cy, k1, k2 = cam.params
    w, h = poses.intrinsics.width, poses.intrinsics.height
    intr = Intrinsics(w, h, f, f, cx - 0.5, cy - 0.5, k1, k2)
    R, t = [], []
    for k in range(len(poses.frame_indices)):
        pose = rec.images[k + 1].cam_from_world()
        R.append(np.asarray(pose.rotation.matrix()))
        t.append(np.asarray(pose.translation))
    points = np.array([rec.points3D[n + 1].xyz for n in range(len(poses.points))]).reshape(-1, 3)
    return Poses(intr, list(poses.frame_indices), R, t, points, poses.seconds + seconds,
                 poses.observations, principal_point_held=poses.principal_point_held)


def merge_observations(poses: Poses, tracks: np.ndarray) -> Poses:
    """``poses`` with extra tracks (rows track id, view, x, y) triangulated and appended."""
    points, rows = triangulate(tracks, poses.R, poses.t, poses.intrinsics)
    if len(points) == 0:
        return poses
    rows = rows.copy()
    rows[:, 0] += len(poses.points)
    return Poses(poses.intrinsics, list(poses.frame_indices), poses.R, poses.t,
                 np.concatenate([poses.points, points]), poses.seconds,
                 np.concatenate([poses.observations, rows]),
                 principal_point_held=poses.principal_point_held)


def refine_with_tracks(poses: Poses, keyframe_observations: np.ndarray, keyframe_indices,
                       work_dir: str | Path, threads: int = 1) -> Poses:
    """Our geometric solution: the SfM model plus the LK tracks, adjusted with the principal
    point free, or held at the image centre where it would end over
    ``PRINCIPAL_POINT_MAX_PCT`` from it. ``keyframe_observations`` rows are (keyframe
    number, track id, x, y) over ``keyframe_indices``; tracks in unregistered keyframes are
    dropped. ``threads``: the bundle adjustment's (:func:`bundle_adjust`)."""
    start = time.perf_counter()
    view_of = {int(i): v for v, i in enumerate(poses.frame_indices)}
    obs = np.asarray(keyframe_observations, float)
    view = np.array([view_of.get(int(keyframe_indices[int(k)]), -1) for k in obs[:, 0]])
    keep = view >= 0
    tracks = np.column_stack([obs[keep, 1], view[keep], obs[keep, 2:4]])
    merged = merge_observations(poses, tracks)
    refined = bundle_adjust(merged, work_dir, refine_intrinsics=True, threads=threads)
    offset = principal_point_offset_pct(refined.intrinsics)
    if offset.max() > PRINCIPAL_POINT_MAX_PCT:
        log.warning("the tracks put the principal point %.1f %% × %.1f %% of the image from its "
                    "centre, further than a phone camera's (a rolling shutter can): it is held "
                    "at the centre", *offset)
        cx, cy = merged.intrinsics.image_centre
        centred = replace(merged.intrinsics, cx=cx, cy=cy)
        refined = bundle_adjust(replace(merged, intrinsics=centred, principal_point_held=True),
                                work_dir, refine_intrinsics=True, hold_principal_point=True,
                                threads=threads)
    refined.seconds = poses.seconds + (time.perf_counter() - start)
    return refined


def principal_point_offset_pct(intr: Intrinsics) -> np.ndarray:
    """How far the principal point lies from the image centre: % of the width (x) and of
    the height (y)."""
    return 100 * np.abs(([intr.cx, intr.cy] - intr.image_centre) / [intr.width, intr.height])
