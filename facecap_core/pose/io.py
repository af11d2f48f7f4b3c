"""Writing poses: ``cameras.json`` (full-resolution pixels, OpenCV convention) and a COLMAP
text model that COLMAP's GUI opens."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from facecap_core.pose.colmap_sfm import Poses


def write_cameras_json(poses: Poses, path: str | Path, **meta) -> Path:
    path = Path(path)
    doc = {
        "convention": "world-to-camera x_cam = R x_world + t (OpenCV); pixel centres at "
                      "integer coordinates; distortion RADIAL (k1, k2) on normalised coordinates",
        "units": "arbitrary (monocular); the metric scale comes with the landmark stage",
        "intrinsics": {k: float(v) if not isinstance(v, int) else v
                       for k, v in poses.intrinsics.to_dict().items()},
        "keyframes": [{"frame_index": int(i), "R": np.asarray(R).tolist(),
                       "t": np.asarray(t).tolist()}
                      for i, R, t in zip(poses.frame_indices, poses.R, poses.t)],
        **meta,
    }
    path.write_text(json.dumps(doc, indent=1))
    return path


def _quaternion(R: np.ndarray) -> np.ndarray:
    """(w, x, y, z) of a rotation matrix, w >= 0."""

    x, y, z, w = Rotation.from_matrix(R).as_quat()
    q = np.array([w, x, y, z])
    return -q if w < 0 else q


def write_colmap_text(poses: Poses, out_dir: str | Path, names: list[str] | None = None) -> Path:
    """A COLMAP text model (cameras.txt, images.txt, points3D.txt) of ``poses``: one RADIAL
    camera, image i+1 is keyframe i, point n+1 is sparse point n (COLMAP pixels: the image
    edge at 0, so +0.5 on ours)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    intr = poses.intrinsics
    f = 0.5 * (intr.fx + intr.fy)
    (out / "cameras.txt").write_text(
        "# CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[] (f, cx, cy, k1, k2)\n"
        f"1 RADIAL {intr.width} {intr.height} "
        + " ".join(repr(float(v)) for v in (f, intr.cx + 0.5, intr.cy + 0.5, intr.k1, intr.k2))
        + "\n")
    names = names or [f"frame_{i:06d}.png" for i in poses.frame_indices]
    obs = np.asarray(poses.observations, float).reshape(-1, 4)
    point = obs[:, 0].astype(np.int64)
    view = obs[:, 1].astype(np.int64)
    order = np.lexsort((point, view))
    slot = np.empty(len(obs), np.int64)  # index of each observation within its image
    tracks: list[list[str]] = [[] for _ in range(len(poses.points))]
    lines = ["# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
             "# POINTS2D[] as (X, Y, POINT3D_ID)"]
    for k, (R, t) in enumerate(zip(poses.R, poses.t)):
        rows = order[view[order] == k]
        slot[rows] = np.arange(len(rows))
        q = _quaternion(np.asarray(R))
        lines.append(f"{k + 1} " + " ".join(repr(float(v)) for v in (*q, *np.asarray(t)))
                     + f" 1 {names[k]}")
        lines.append(" ".join(f"{obs[r, 2] + 0.5:.4f} {obs[r, 3] + 0.5:.4f} {point[r] + 1}"
                              for r in rows))
        for r in rows:
            tracks[point[r]].append(f"{k + 1} {slot[r]}")
    (out / "images.txt").write_text("\n".join(lines) + "\n")
    pts = ["# POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)"]
    for n, X in enumerate(poses.points):
        pts.append(f"{n + 1} " + " ".join(repr(float(v)) for v in X) + " 200 200 200 0 "
                   + " ".join(tracks[n]))
    (out / "points3D.txt").write_text("\n".join(pts) + "\n")
    return out


def write_outputs(poses: Poses, out_dir: str | Path, **meta) -> Path:
    """``cameras.json``, ``points.ply``, ``sparse.npz`` (points (N, 3) and visibility
    (keyframes, N) bool, in cameras.json keyframe order) and ``colmap/`` (cameras, images,
    points3D .txt)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_cameras_json(poses, out / "cameras.json", seconds=round(poses.seconds, 2), **meta)
    if len(poses.points):
        trimesh.PointCloud(poses.points).export(out / "points.ply")
    np.savez_compressed(out / "sparse.npz", points=np.asarray(poses.points, float),
                        visibility=poses.visibility())
    write_colmap_text(poses, out / "colmap")
    return out / "cameras.json"
