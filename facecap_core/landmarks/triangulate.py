"""Robust multi-view triangulation of 2D landmark tracks with known cameras.

Each point is solved on its own (Agrawal et al. 2020, eq. 3: minimal reprojection error):

1. **Hypotheses**: the linear (DLT) triangulation of every pair of views that observe the
   point with enough parallax; each hypothesis is scored over all views by a truncated
   squared reprojection error (MSAC), and the best one names the inlier views.
2. **Refinement**: Gauss–Newton on the reprojection error of the inlier views with Huber
   weights, starting from the DLT of all inliers; the inlier set is then re-decided from the
   refined point and the refinement repeated once.
3. Points seen by fewer than ``min_views`` inlier views come back as NaN.

All points are handled at once with batched numpy (views × points arrays). Observations
are undistorted once; errors are measured in pixels of the undistorted image (the same as
the distorted image's up to the lens's local magnification, a fraction of a percent here).
Missing observations are NaN.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np

from facecap_core.camera import Intrinsics, camera_center, project, undistort


def box_size(box) -> float:
    """Size of a face box (the square root of its area): what reprojection errors and
    thresholds are measured against."""
    left, top, right, bottom = box
    return float(np.sqrt(max(right - left, 1) * max(bottom - top, 1)))


@dataclass
class Triangulation:
    """Result of :func:`triangulate` for P points observed in V views."""

    points: np.ndarray  # (P, 3), NaN where the point could not be triangulated
    inliers: np.ndarray  # (V, P) bool: the observation was used
    errors: np.ndarray  # (V, P) reprojection error in px (NaN where not observed)
    covariance: np.ndarray  # (P, 3, 3) of each point for 1 px of image noise per inlier

    def spread(self, noise_px: float = 1.0) -> np.ndarray:
        """(P,) standard deviation along each point's least certain direction (world
        units) for ``noise_px`` of image noise: large when the inlier views barely differ."""
        eig = np.linalg.eigvalsh(np.nan_to_num(self.covariance, nan=np.inf, posinf=1e30))
        return noise_px * np.sqrt(np.maximum(eig[:, -1], 0.0))

    @property
    def views(self) -> np.ndarray:
        """(P,) number of inlier views per point."""
        return self.inliers.sum(0)


def normalised(uv: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """Undistorted normalised image coordinates (..., 2) of distorted pixels (..., 2)."""
    uv = np.asarray(uv, float)
    xy_d = np.stack([(uv[..., 0] - intr.cx) / intr.fx, (uv[..., 1] - intr.cy) / intr.fy], -1)
    return undistort(xy_d, intr.k1, intr.k2)


def dlt(xy: np.ndarray, R: np.ndarray, t: np.ndarray, weights: np.ndarray | None = None
        ) -> np.ndarray:
    """Linear triangulation of P points from V views; ``xy`` (V, P, 2) normalised
    coordinates (NaN: missing), ``R`` (V, 3, 3), ``t`` (V, 3); returns (P, 3), NaN where
    fewer than two views observe a point. ``weights`` (V, P) scale each view's rows."""
    xy = np.asarray(xy, float)
    P3 = np.concatenate([np.asarray(R, float), np.asarray(t, float)[:, :, None]], axis=2)
    seen = np.all(np.isfinite(xy), axis=-1)
    w = seen.astype(float) if weights is None else np.where(seen, weights, 0.0)
    x = np.nan_to_num(xy)
    # Rows x * P[2] - P[0] and y * P[2] - P[1] per view: (P, 2V, 4).
    rows_x = x[..., 0, None] * P3[:, None, 2, :] - P3[:, None, 0, :]
    rows_y = x[..., 1, None] * P3[:, None, 2, :] - P3[:, None, 1, :]
    A = np.concatenate([rows_x * w[..., None], rows_y * w[..., None]], axis=0)
    A = np.transpose(A, (1, 0, 2))
    _, _, vt = np.linalg.svd(A)
    X = vt[:, -1, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        out = X[:, :3] / X[:, 3:4]
    out[seen.sum(0) < 2] = np.nan
    return out


def _camera_xyz(X: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Camera-frame coordinates (V, P, 3) of points X (P, 3)."""
    return np.einsum("vij,pj->vpi", R, X) + t[:, None, :]


def _residuals(X, xy, R, t, focal):
    pc = _camera_xyz(X, R, t)
    z = pc[..., 2]
    proj = pc[..., :2] / np.where(np.abs(z) > 1e-12, z, 1e-12)[..., None]
    return (proj - xy) * focal, pc


def _huber_weights(err: np.ndarray, k: np.ndarray) -> np.ndarray:
    return np.where(err <= k, 1.0, k / np.maximum(err, 1e-12))


def refine(X: np.ndarray, xy: np.ndarray, R: np.ndarray, t: np.ndarray, focal: float,
           use: np.ndarray, huber_px: np.ndarray, iterations: int = 10) -> np.ndarray:
    """Gauss–Newton with Huber weights on the pixel reprojection error of the ``use``
    observations (V, P); ``huber_px`` (V, P) or scalar. Points without two used views are
    left as they are."""
    X = np.array(X, float)
    R, t = np.asarray(R, float), np.asarray(t, float)
    huber_px = np.broadcast_to(np.asarray(huber_px, float), use.shape)
    ok = (use.sum(0) >= 2) & np.all(np.isfinite(X), axis=1)
    xy0 = np.nan_to_num(xy)
    for _ in range(iterations):
        r, pc = _residuals(np.nan_to_num(X), xy0, R, t, focal)
        err = np.linalg.norm(r, axis=-1)
        w = np.where(use, _huber_weights(err, huber_px), 0.0)
        z = np.where(np.abs(pc[..., 2]) > 1e-12, pc[..., 2], 1e-12)
        # d(proj)/dX = f / z * (R[row] - proj * R[2]) for rows x, y: (V, P, 2, 3).
        proj = pc[..., :2] / z[..., None]
        J = (focal / z)[..., None, None] * (R[:, None, :2, :] - proj[..., :, None]
                                            * R[:, None, None, 2, :])
        H = np.einsum("vp,vpki,vpkj->pij", w, J, J) + 1e-9 * np.eye(3)
        g = np.einsum("vp,vpki,vpk->pi", w, J, r)
        step = -np.linalg.solve(H[ok], g[ok][..., None])[..., 0]
        X[ok] += step
        if np.all(np.linalg.norm(step, axis=1) < 1e-9 * (1 + np.linalg.norm(X[ok], axis=1))):
            break
    return X


def reprojection_errors(X: np.ndarray, uv: np.ndarray, R: np.ndarray, t: np.ndarray,
                        intr: Intrinsics) -> np.ndarray:
    """(V, P) distance in distorted pixels between the observations ``uv`` (V, P, 2) and the
    projections of ``X`` (P, 3); NaN where unobserved or behind the camera."""
    out = np.full(uv.shape[:2], np.nan)
    good = np.all(np.isfinite(X), axis=1)
    for v in range(len(R)):
        proj, z = project(np.nan_to_num(X), R[v], t[v], intr)
        e = np.linalg.norm(proj - uv[v], axis=1)
        out[v] = np.where(good & (z > 0), e, np.nan)
    return out


def _pair_hypotheses(xy, R, t, centres, min_parallax_deg):
    """DLT of every view pair with parallax, per point: (H, P, 3) and validity (H, P)."""
    V, P = xy.shape[:2]
    seen = np.all(np.isfinite(xy), axis=-1)
    hyps, valid = [], []
    for a, b in combinations(range(V), 2):
        both = seen[a] & seen[b]
        if not both.any():
            continue
        X = dlt(xy[[a, b]], R[[a, b]], t[[a, b]])
        ra, rb = X - centres[a], X - centres[b]
        cosang = np.einsum("pi,pi->p", ra, rb) / np.maximum(
            np.linalg.norm(ra, axis=1) * np.linalg.norm(rb, axis=1), 1e-300)
        parallax = np.degrees(np.arccos(np.clip(cosang, -1, 1)))
        za = (X @ R[a][2]) + t[a][2]
        zb = (X @ R[b][2]) + t[b][2]
        hyps.append(X)
        valid.append(both & np.all(np.isfinite(X), axis=1) & (za > 0) & (zb > 0)
                     & (parallax >= min_parallax_deg))
    if not hyps:
        return np.zeros((0, P, 3)), np.zeros((0, P), bool)
    return np.stack(hyps), np.stack(valid)


def triangulate(uv: np.ndarray, R: np.ndarray, t: np.ndarray, intr: Intrinsics,
                threshold_px: np.ndarray | float, huber_px: np.ndarray | float,
                min_views: int = 2, min_parallax_deg: float = 2.0) -> Triangulation:
    """Robust triangulation of P points observed in V views.

    ``uv`` (V, P, 2) distorted pixels (NaN: missing), ``R`` (V, 3, 3), ``t`` (V, 3)
    world-to-camera poses; ``threshold_px`` and ``huber_px`` per view (V,) or scalar: the
    inlier threshold and the Huber threshold of the refinement, in pixels.
    """
    uv = np.asarray(uv, float)
    R, t = np.asarray(R, float), np.asarray(t, float)
    V, P = uv.shape[:2]
    thr = np.broadcast_to(np.asarray(threshold_px, float).reshape(-1, 1)
                          if np.ndim(threshold_px) else threshold_px, (V, P))
    hub = np.broadcast_to(np.asarray(huber_px, float).reshape(-1, 1)
                          if np.ndim(huber_px) else huber_px, (V, P))
    xy = normalised(uv, intr)
    seen = np.all(np.isfinite(xy), axis=-1)
    focal = 0.5 * (intr.fx + intr.fy)
    centres = np.stack([camera_center(R[v], t[v]) for v in range(V)]) if V else np.zeros((0, 3))

    # 1. Pair hypotheses scored by MSAC over all views.
    hyps, valid = _pair_hypotheses(xy, R, t, centres, min_parallax_deg)
    X = np.full((P, 3), np.nan)
    inl = np.zeros((V, P), bool)
    if len(hyps):
        cost = np.full(valid.shape, np.inf)
        for h in range(len(hyps)):
            r, pc = _residuals(np.nan_to_num(hyps[h]), np.nan_to_num(xy), R, t, focal)
            e2 = np.sum(r * r, axis=-1)
            e2 = np.where(pc[..., 2] > 0, e2, np.inf)
            c = np.where(seen, np.minimum(e2, thr ** 2), 0.0).sum(0)
            cost[h] = np.where(valid[h], c, np.inf)
        best = np.argmin(cost, axis=0)
        found = np.isfinite(cost[best, np.arange(P)])
        X[found] = hyps[best[found], np.flatnonzero(found)]
    # 2. Inliers of the best hypothesis, DLT on them, robust refinement, inliers again.
    for _ in range(2):
        r, pc = _residuals(np.nan_to_num(X), np.nan_to_num(xy), R, t, focal)
        err = np.linalg.norm(r, axis=-1)
        inl = seen & (err < thr) & (pc[..., 2] > 0) & np.all(np.isfinite(X), axis=1)[None]
        start = dlt(np.where(inl[..., None], xy, np.nan), R, t)
        start = np.where(np.all(np.isfinite(start), axis=1)[:, None], start, X)
        X = refine(start, xy, R, t, focal, inl, hub)
    r, pc = _residuals(np.nan_to_num(X), np.nan_to_num(xy), R, t, focal)
    err = np.linalg.norm(r, axis=-1)
    inl = seen & (err < thr) & (pc[..., 2] > 0) & np.all(np.isfinite(X), axis=1)[None]
    X[inl.sum(0) < min_views] = np.nan
    inl[:, ~np.all(np.isfinite(X), axis=1)] = False
    return Triangulation(X, inl, reprojection_errors(X, uv, R, t, intr),
                         _covariance(X, R, t, focal, inl))


def _covariance(X, R, t, focal, use):
    """(P, 3, 3) inverse Gauss–Newton matrix of the ``use`` observations (1 px noise);
    infinite where a point is not determined."""
    pc = _camera_xyz(np.nan_to_num(X), R, t)
    z = np.where(np.abs(pc[..., 2]) > 1e-12, pc[..., 2], 1e-12)
    proj = pc[..., :2] / z[..., None]
    J = (focal / z)[..., None, None] * (R[:, None, :2, :] - proj[..., :, None]
                                        * R[:, None, None, 2, :])
    H = np.einsum("vp,vpki,vpkj->pij", use.astype(float), J, J)
    cov = np.full(H.shape, np.inf)
    ok = (use.sum(0) >= 2) & (np.abs(np.linalg.det(H)) > 1e-300)
    cov[ok] = np.linalg.inv(H[ok])
    return cov
