"""Writing poses: ``cameras.json`` (full-resolution pixels, OpenCV convention) and a COLMAP
text model that COLMAP's GUI opens."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import trimesh

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


def write_outputs(poses: Poses, sfm_dir: str | Path, out_dir: str | Path) -> Path:
    """``cameras.json``, ``points.ply`` and ``colmap/`` (cameras/images/points3D.txt)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_cameras_json(poses, out / "cameras.json", seconds=round(poses.seconds, 2))
    if len(poses.points):
        trimesh.PointCloud(poses.points).export(out / "points.ply")
    colmap = out / "colmap"
    colmap.mkdir(exist_ok=True)
    for name in ("cameras.txt", "images.txt", "points3D.txt"):
        shutil.copy(Path(sfm_dir) / "sparse" / name, colmap / name)
    return out / "cameras.json"
