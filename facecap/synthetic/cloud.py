"""MVS-like point clouds sampled from a ground-truth mesh, for tests and benchmarks.

:func:`mvs_like_cloud` samples the surface uniformly at a given density (points per mm²),
adds Gaussian noise along every direction, cuts spatially coherent holes (geodesic-ish
patches: balls around random surface points, grown until the requested fraction is gone)
and replaces a fraction of the points by outliers scattered off the surface (2-15 mm, the
way bad PatchMatch depths land in front of or behind the skin). Normals are the true ones,
jittered; outliers get random normals.
"""

from __future__ import annotations

import numpy as np
import trimesh


def mvs_like_cloud(vertices: np.ndarray, faces: np.ndarray, density: float = 0.7,
                   noise_mm: float = 0.5, holes: float = 0.2, outliers: float = 0.05,
                   hole_radius_mm: tuple[float, float] = (6.0, 18.0), normal_jitter_deg: float = 10.0,
                   seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``(points (N, 3), normals (N, 3))`` sampled from the mesh as described above."""
    rng = np.random.default_rng(seed)
    mesh = trimesh.Trimesh(np.asarray(vertices, float), np.asarray(faces, np.int64),
                           process=False)
    count = max(int(mesh.area * density), 100)
    pts, fid = trimesh.sample.sample_surface(mesh, count, seed=int(rng.integers(2 ** 31)))
    nrm = mesh.face_normals[fid]
    keep = np.ones(len(pts), bool)
    target = holes * len(pts)
    while (~keep).sum() < target:
        c = pts[rng.integers(len(pts))]
        r = rng.uniform(*hole_radius_mm)
        keep &= np.linalg.norm(pts - c, axis=1) > r
    pts, nrm = pts[keep], nrm[keep]
    pts = pts + rng.normal(0.0, noise_mm, pts.shape)
    jitter = rng.normal(0.0, np.radians(normal_jitter_deg) / np.sqrt(2), nrm.shape)
    nrm = nrm + jitter - np.sum(jitter * nrm, 1, keepdims=True) * nrm
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    k = int(round(outliers * len(pts)))
    if k:
        idx = rng.choice(len(pts), k, replace=False)
        d = rng.normal(size=(k, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        pts[idx] = pts[idx] + d * rng.uniform(2.0, 15.0, (k, 1))
        rn = rng.normal(size=(k, 3))
        nrm[idx] = rn / np.linalg.norm(rn, axis=1, keepdims=True)
    return pts, nrm
