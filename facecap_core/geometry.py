"""Similarity transforms between point sets, shared by the method (coarse fit, fitting,
poses) and its scoring (evaluation).

``umeyama`` is the (weighted) least-squares similarity; ``robust_similarity`` reweights it
by the residuals so that a few wrong points (a mislocated landmark) do not steer it.
"""

from __future__ import annotations

import numpy as np

__all__ = ["umeyama", "robust_similarity"]


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True,
            weights: np.ndarray | None = None) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity (or rigid) transform with ``dst ≈ s * R @ src + t``,
    minimising ``sum w |.|²`` (equal weights by default).

    Umeyama (1991): ``R`` is always a proper rotation (det +1) — a reflection that would fit
    better is replaced by the best rotation. Returns ``(s, R, t)``; ``s`` is 1.0 when
    ``with_scale`` is False.
    """
    src = np.asarray(src, float)
    dst = np.asarray(dst, float)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ValueError(f"umeyama needs two (N>=3, 3) arrays of equal shape; got {src.shape} "
                         f"and {dst.shape}")
    w = np.full(len(src), 1.0) if weights is None else np.asarray(weights, float)
    w = w / w.sum()
    mu_s, mu_d = w @ src, w @ dst
    xs, xd = src - mu_s, dst - mu_d
    cov = (xd * w[:, None]).T @ xs
    U, D, Vt = np.linalg.svd(cov)
    S = np.ones(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2] = -1.0  # flip the weakest axis: the best proper rotation, not a reflection
    R = (U * S) @ Vt
    var_s = float(np.sum(w * np.sum(xs * xs, axis=1)))
    s = float(np.sum(D * S) / var_s) if with_scale and var_s > 0 else 1.0
    return s, R, mu_d - s * R @ mu_s


def robust_similarity(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None,
                      iterations: int = 5, cauchy_mm: float = 3.0, with_scale: bool = True
                      ) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """Similarity from ``src`` (template, mm) to ``dst`` reweighted by a Cauchy function of
    the residuals in template millimetres; returns ``s, R, t`` and the final weights."""
    base = np.ones(len(src)) if weights is None else np.asarray(weights, float)
    w = base.copy()
    s, R, t = umeyama(src, dst, with_scale, w)
    for _ in range(iterations):
        r = np.linalg.norm(s * src @ R.T + t - dst, axis=1) / s
        w = base / (1.0 + (r / cauchy_mm) ** 2)
        s, R, t = umeyama(src, dst, with_scale, w)
    return s, R, t, w
