"""Colour for the fitted mesh from the keyframes.

:func:`vertex_colours` gives every vertex the colour of its best view: among the keyframes
where the vertex is visible (a ray from the camera centre reaches it unoccluded — the
z-buffer by ray casting) and faces the camera (``cos >= min_cos``), the one with the highest
``cos(view angle) × sharpness`` (sharpness: the frame's variance of the Laplacian, relative
to the sharpest keyframe), sampled bilinearly. Vertices no view sees take the mean colour of
their coloured neighbours (diffused over the mesh), then grey.

A UV texture atlas needs a template with UVs; the default template has none, so per-vertex
colour is what facecap writes (see docs/fitting.md).
"""

from __future__ import annotations

import cv2
import numpy as np

from facecap_core.camera import camera_center, project
from facecap_core.keyframes import sharpness
from facecap_core.render import RaycastScene, vertex_normals

__all__ = ["vertex_colours"]


def _bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    img = image if image.ndim == 3 else np.repeat(image[..., None], 3, axis=2)
    if len(uv) == 0:  # cv2.remap refuses an empty map
        return np.zeros((0, 3), np.float32)
    mx = uv[:, 0].astype(np.float32).reshape(-1, 1)
    my = uv[:, 1].astype(np.float32).reshape(-1, 1)
    out = cv2.remap(img.astype(np.float32), mx, my, cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(-1, 3)


def _diffuse(colours: np.ndarray, known: np.ndarray, faces: np.ndarray, rounds: int = 50
             ) -> tuple[np.ndarray, np.ndarray]:
    """Fill unknown vertex colours with the mean of known neighbours, ring by ring."""
    c, k = colours.copy(), known.copy()
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = np.concatenate([e, e[:, ::-1]])
    for _ in range(rounds):
        if k.all():
            break
        src = k[e[:, 0]] & ~k[e[:, 1]]
        if not src.any():
            break
        acc = np.zeros_like(c)
        cnt = np.zeros(len(c))
        np.add.at(acc, e[src, 1], c[e[src, 0]])
        np.add.at(cnt, e[src, 1], 1.0)
        new = cnt > 0
        c[new] = acc[new] / cnt[new, None]
        k = k | new
    return c, k


def vertex_colours(vertices: np.ndarray, faces: np.ndarray, keyframes, min_cos: float = 0.25,
                   depth_tol_mm: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Per-vertex RGB (n, 3) uint8 and the keyframe index that coloured each vertex (-1:
    filled from neighbours or grey). ``keyframes`` are :class:`~facecap_core.fitting.Keyframe`
    (RGB uint8 images with cameras)."""
    v = np.asarray(vertices, float)
    f = np.asarray(faces, np.int64)
    n = len(v)
    normals = vertex_normals(v, f)
    scene = RaycastScene()
    scene.add(v, f)
    sharp = np.array([sharpness(kf.image) for kf in keyframes]) if len(keyframes) else np.zeros(0)
    sharp_rel = sharp / sharp.max() if len(sharp) and sharp.max() > 0 else np.ones(len(sharp))
    best = np.full(n, -np.inf)
    view = np.full(n, -1)
    colours = np.zeros((n, 3))
    for k, kf in enumerate(keyframes):
        c = camera_center(kf.R, kf.t)
        d = c - v
        dist = np.linalg.norm(d, axis=1)
        d /= dist[:, None]
        cos = np.einsum("ij,ij->i", normals, d)
        cand = cos >= min_cos
        if not cand.any():
            continue
        uv, z = project(v[cand], kf.R, kf.t, kf.intrinsics)
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & \
                 (uv[:, 0] <= kf.intrinsics.width - 1) & (uv[:, 1] <= kf.intrinsics.height - 1)
        ids = np.flatnonzero(cand)
        hit = scene.cast(np.broadcast_to(c, (len(ids), 3)), -d[ids])["t_hit"]
        vis = inside & (hit >= dist[ids] - depth_tol_mm)
        ids, uv = ids[vis], uv[vis]
        score = cos[ids] * sharp_rel[k]
        better = score > best[ids]
        ids, uv = ids[better], uv[better]
        best[ids] = score[better]
        view[ids] = k
        colours[ids] = _bilinear(kf.image, uv)
    known = view >= 0
    colours, known = _diffuse(colours, known, f)
    colours[~known] = 128.0
    return np.clip(np.round(colours), 0, 255).astype(np.uint8), view
