"""Ground-truth-derived inputs for judging the MVS stage alone (benchmarks and tests).

A synthetic capture gives exact cameras and the true mesh; the stage's other input, the
coarse mesh, is made from the true mesh by smoothing it and pushing it off by a smooth
low-frequency offset of a few mm — as far off as a landmark-fitted 3DMM is.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from facecap.synthetic import load_gt_cameras
from facecap_core.mvs.images import MVSView, prepare_view
from facecap_core.render import RaycastScene, vertex_normals
from facecap_core.video import read_frames


def coarse_from_gt(vertices: np.ndarray, faces: np.ndarray, smooth_iterations: int = 10,
                   offset_mm: float = 2.5, wavelength_mm: float = 120.0,
                   seed: int = 0) -> np.ndarray:
    """Vertices of a coarse version of a mesh: Laplacian-smoothed, then moved along the
    normals by a smooth random field whose largest magnitude is ``offset_mm``."""
    mesh = trimesh.Trimesh(np.asarray(vertices, float), np.asarray(faces), process=False)
    if smooth_iterations:
        trimesh.smoothing.filter_laplacian(mesh, lamb=0.5, iterations=smooth_iterations)
    v = np.asarray(mesh.vertices, float)
    rng = np.random.default_rng(seed)
    field = np.zeros(len(v))
    for _ in range(4):
        k = rng.normal(size=3)
        k *= 2 * np.pi / (wavelength_mm * rng.uniform(0.8, 1.5) * np.linalg.norm(k))
        field += np.sin(v @ k + rng.uniform(0, 2 * np.pi))
    field += rng.uniform(-1, 1)  # a constant part too: the fit can be off as a whole
    field *= offset_mm / np.abs(field).max()
    return v + field[:, None] * vertex_normals(v, np.asarray(faces))


def gt_depth(view: MVSView, vertices: np.ndarray, faces: np.ndarray,
             scene: RaycastScene | None = None):
    """True depth (H, W) of the view's pinhole camera (inf where the mesh is missed) and the
    world points hit (H, W, 3)."""
    if scene is None:
        scene = RaycastScene()
        scene.add(vertices, faces)
    hits = scene.cast_camera(view.intr, view.R, view.t)
    return hits.depth, hits.points


def even_keyframes(n_frames: int, count: int) -> list[int]:
    """``count`` frame indices evenly spread over a sweep (stand-in for keyframe selection)."""
    return sorted(set(np.linspace(0, n_frames - 1, min(count, n_frames)).round().astype(int)))


def load_views(capture_folder: str | Path, indices: list[int], width: int) -> list[MVSView]:
    """MVS views of some frames of a synthetic capture, with its ground-truth cameras."""

    folder = Path(capture_folder)
    intr, frames = load_gt_cameras(folder / "gt" / "cameras.json")
    images = read_frames(folder / "video.mp4", indices, width=width)
    return [prepare_view(i, images[i], intr, frames[i]["R"], frames[i]["t"], width)
            for i in indices]
