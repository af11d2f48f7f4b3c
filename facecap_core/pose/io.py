"""Writing poses: ``cameras.json`` (full-resolution pixels, OpenCV convention) and a COLMAP
text model that COLMAP's GUI opens (written by pycolmap)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from facecap_core.lazy import LazyModule
from facecap_core.pose.cameras_json import (
    CONVENTION,
    CameraIntrinsics,
    Cameras,
    DroppedKeyframe,
    SolveFigures,
    keyframe_poses,
)
from facecap_core.pose.colmap_sfm import Poses

trimesh = LazyModule("trimesh")

# Imported where used: pycolmap only where a COLMAP model is written.


def write_cameras_json(poses: Poses, path: str | Path, **meta) -> Path:
    """``cameras.json`` of ``poses`` in the pose stage's units; ``meta``: the other fields
    of :class:`Cameras` the stage fills in (seconds, method, dropped, solve, ...)."""
    if meta.get("dropped") is not None:
        meta["dropped"] = [DroppedKeyframe(**d) for d in meta["dropped"]]
    if meta.get("solve") is not None:
        meta["solve"] = SolveFigures.model_validate(meta["solve"])
    cameras = Cameras(
        convention=CONVENTION,
        units="arbitrary (monocular); the metric scale comes with the landmark stage",
        intrinsics=CameraIntrinsics(**{k: float(v) if not isinstance(v, int) else v
                                       for k, v in poses.intrinsics.to_dict().items()}),
        keyframes=keyframe_poses(poses.frame_indices, poses.R, poses.t), **meta)
    return cameras.write(path)


def colmap_reconstruction(poses: Poses, names: list[str] | None = None):
    """A pycolmap Reconstruction of ``poses``: one RADIAL camera, image i+1 is keyframe i
    (named ``names[i]``), point n+1 is sparse point n, each image's 2D points in the order
    of their sparse points (COLMAP pixels: the image edge at 0, so +0.5 on ours)."""
    import pycolmap

    intr = poses.intrinsics
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera(
        model="RADIAL", width=intr.width, height=intr.height, camera_id=1,
        params=[0.5 * (intr.fx + intr.fy), intr.cx + 0.5, intr.cy + 0.5, intr.k1, intr.k2]))
    names = names or [f"frame_{i:06d}.png" for i in poses.frame_indices]
    obs = np.asarray(poses.observations, float).reshape(-1, 4)
    point = obs[:, 0].astype(np.int64)
    view = obs[:, 1].astype(np.int64)
    by_view = np.lexsort((point, view))
    slot = np.empty(len(obs), np.int64)  # index of each observation within its image
    for k, (R, t) in enumerate(zip(poses.R, poses.t)):
        rows = by_view[view[by_view] == k]
        slot[rows] = np.arange(len(rows))
        image = pycolmap.Image(name=names[k], keypoints=obs[rows, 2:4] + 0.5, camera_id=1,
                               image_id=k + 1)
        cam_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(np.asarray(R, float)),
                                          np.asarray(t, float))
        rec.add_image_with_trivial_frame(image, cam_from_world)
    by_point = np.lexsort((view, point))
    bounds = np.searchsorted(point[by_point], np.arange(len(poses.points) + 1))
    grey = np.full(3, 200, np.uint8)
    for n, X in enumerate(poses.points):
        rows = by_point[bounds[n]:bounds[n + 1]]
        track = pycolmap.Track([pycolmap.TrackElement(int(view[r]) + 1, int(slot[r]))
                                for r in rows])
        # Ids are given in order from 1, so point n is n + 1 as the docstring says.
        rec.add_point3D(np.asarray(X, float), track, grey)
    return rec


def write_colmap_text(poses: Poses, out_dir: str | Path, names: list[str] | None = None) -> Path:
    """The COLMAP text model of ``poses`` (:func:`colmap_reconstruction`) in ``out_dir``:
    cameras.txt, images.txt, points3D.txt, and the trivial rigs.txt and frames.txt that
    COLMAP 3.12 and later read (older ones ignore them)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    colmap_reconstruction(poses, names).write_text(out)
    return out


def write_outputs(poses: Poses, out_dir: str | Path, **meta) -> Path:
    """``cameras.json``, ``points.ply``, ``sparse.npz`` (points (N, 3) and visibility
    (keyframes, N) bool, in cameras.json keyframe order) and ``colmap/`` (the COLMAP text
    model: :func:`write_colmap_text`)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_cameras_json(poses, out / "cameras.json", seconds=round(poses.seconds, 2), **meta)
    if len(poses.points):
        trimesh.PointCloud(poses.points).export(out / "points.ply")
    np.savez_compressed(out / "sparse.npz", points=np.asarray(poses.points, float),
                        visibility=poses.visibility())
    write_colmap_text(poses, out / "colmap")
    return out / "cameras.json"
