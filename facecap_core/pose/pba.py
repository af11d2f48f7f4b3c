"""Photometric bundle adjustment (PBA) of keyframe poses, intrinsics and radial distortion.

One module on purpose: the residuals, their derivatives, the numba accumulation and the
Schur-complement solve share one parameter layout and one set of kernels; split, they would
need an interface as wide as the algorithm. Inside it: the numba kernels (photometric
residuals, track residuals, the epipolar depth search), a :class:`_Problem` (what the solve
is over: points, targets, tracks, priors, timing), a :class:`_Level` of the image pyramid
(its images, the normal equations at a :class:`_State`, the models' choice, the
Levenberg-Marquardt iterations) and :func:`photometric_bundle_adjustment`, which runs the
levels coarse to fine.

The method of DSO (Engel et al.), run as a batch over all keyframes:

* **Points**: the initial reconstruction's sparse points, each hosted in the middle keyframe
  of its track at its depth (default), or in every keyframe the strongest-gradient pixel of
  each ``cell``×``cell`` block with an epipolar depth search; an 8-pixel pattern around each;
  one unknown per point, its inverse depth along the host ray.
* **Residuals**: each pattern pixel is cast along its host ray at the point's inverse depth,
  projected into nearby keyframes (the targets) and compared there:
  ``r = I_t(u_t) - b_t - exp(a_t - a_h) (I_h(u_h) - b_h)``, with a per-keyframe affine
  brightness (a, b) for exposure changes, DSO's gradient-dependent weight and a robust loss
  scaled to the residuals' own spread (whole patterns dropped as outliers). Each side is
  sampled along the other keyframe's motion-blur streak, and optionally each row at its own
  time (rolling shutter).
* **Tracked points** (optional, the default in the pose stage): the initial reconstruction's
  points (3 unknowns each) and their reprojection errors against their observations, in the
  same solve.
* **Unknowns**: every keyframe's pose (6) and brightness (2), one shared camera: focal length,
  principal point and radial distortion k1, k2 (5), all inverse depths and tracked points.
* **Solver**: Levenberg–Marquardt with analytic Jacobians. Inverse depths (1×1 blocks) and
  tracked points (3×3 blocks) are eliminated by the Schur complement, leaving a small dense
  system over the camera unknowns; coarse to fine over an image pyramid.
* **Gauge**: the first keyframe's pose and brightness are fixed, and the scale by a prior on
  the distance between the first two camera centres. Optionally the camera centres are held
  near the start by a prior; without tracked points the intrinsics are held (see
  :class:`PBAConfig`).

Distortion is part of the model (rays are undistorted with the current k1, k2), so the
intrinsics' Jacobians pass through the undistortion by the implicit-function theorem.
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numba as nb
import numpy as np
from pydantic import Field

from facecap_core.camera import Intrinsics, project, rotation_matrix
from facecap_core.config import KEY_NEUTRAL, StrictModel
from facecap_core.errors import FacecapError
from facecap_core.video import processing_size


class PBAConfig(StrictModel):
    """Photometric bundle adjustment (``facecap_core/pose/pba.py``)."""

    cell: int = Field(12, ge=4, le=64)
    """One point per cell×cell block of each keyframe (its strongest gradient)."""
    min_gradient: float = Field(8.0, ge=0)
    """Weakest gradient (grey levels per pixel) a point may have."""
    search_level: int = Field(1, ge=0, le=5)
    """Pyramid level of the initial depth search along the epipolar lines."""
    search_samples: int = Field(96, ge=8, le=1024)
    """Inverse-depth samples of that search (log-spaced over the sparse points' range)."""
    min_search_quality: float = Field(1.5, ge=1)
    """A point is kept when its second-best match costs this many times its best."""
    neighbours: int = Field(6, ge=1, le=15)
    """Each point is compared in this many keyframes before and after its host."""
    pyramid_levels: int = Field(2, ge=1, le=6)
    """Coarse-to-fine levels (each half the size of the previous)."""
    iterations: int = Field(8, ge=1, le=200)
    """Levenberg–Marquardt iterations per pyramid level."""
    depth_only_iterations: int = Field(2, ge=0, le=200)
    """The first iterations of each level move only the inverse depths."""
    huber: float = Field(1.5, gt=0)
    """Huber threshold of the photometric residual, in units of the residuals' robust
    standard deviation (1.4826 x their median magnitude at the level's starting cameras)."""
    gradient_weight: float = Field(50.0, gt=0)
    """DSO's gradient weight c²/(c² + |∇I|²): strong edges count less (sub-pixel noise)."""
    max_residual: float = Field(3.0, gt=0)
    """A point's pattern in one target is an outlier (occluded, a highlight) when its root
    mean square residual exceeds this many robust standard deviations; it then costs a
    constant."""
    initial_lambda: float = Field(1e-3, gt=0)
    """Initial Levenberg–Marquardt damping."""
    refine_intrinsics: bool = True
    """Refine focal length, principal point and k1, k2 with the poses, when the tracked points
    are in the solve (``track_weight``): photometric residuals over neighbouring keyframes
    alone leave the principal point free against a tilt of every camera."""
    principal_point_prior_pct: float = Field(1.0, ge=0)
    """With the intrinsics refined, the principal point is held near the image centre with
    this standard deviation (% of the image's width for x, of its height for y; the spread
    of facecap's sensor model), weighed against the tracks by their noise: the data move it
    as far as they pin it (a tilt of every camera and a shift of the principal point
    reproject almost alike). 0: free."""
    hold_principal_point: bool = Field(False, json_schema_extra={KEY_NEUTRAL: False})
    """The principal point stays where the start (the geometric refinement) put it; focal
    length and distortion are still refined. Instead of the prior above."""
    scale_prior: float = Field(1e8, gt=0)
    """Weight of the prior that fixes the length of the first baseline (the scale gauge)."""
    points_from_sparse: bool = True
    """Use the initial reconstruction's points (at their depths) instead of an epipolar
    search for strong-gradient pixels."""
    centre_prior_pct: float = Field(0.0, ge=0)
    """Camera centres are held near the start's with this standard deviation (% of the mean
    camera distance from their centroid; 0: free, the gauge is then the first keyframe and
    the first baseline's length)."""
    intrinsics_level: int = Field(0, ge=0, le=5)
    """Intrinsics are held fixed at pyramid levels coarser than this one (coarse levels bias
    the focal length)."""
    motion_blur: bool = True
    """Model each keyframe's motion blur: the streak the camera's motion (a constant velocity
    through the neighbouring keyframes) draws over the exposure. Each residual compares the
    host and the target each blurred by the other's streak. Videos only (photos have no
    times)."""
    exposure_fraction: float | None = Field(None, ge=0, le=1)
    """Exposure as a fraction of the frame interval; None: the one of
    ``exposure_candidates`` whose blur model fits the starting cameras best."""
    exposure_candidates: tuple[float, ...] = Field((0.0, 0.25, 0.5, 0.75), min_length=1)
    """Exposures (fractions of the frame interval) tried when ``exposure_fraction`` is None."""
    track_weight: float = Field(30.0, ge=0)
    """The tracked points' reprojection errors join the photometric residuals in one solve:
    one pixel of reprojection error costs as much as this many grey levels of photometric
    residual (0: photometric only)."""
    track_huber_px: float = Field(1.0, gt=0)
    """Huber threshold of the reprojection errors (pixels)."""
    rolling_shutter: bool = False
    """Model a rolling shutter: each image row exposed at its own time, the camera moving at
    a constant velocity (through the neighbouring keyframes) over the readout; with the
    readout chosen from the tracks, their adjustment under it is PBA's start. Videos only.
    Off by default: SfM and the geometric solution model no rolling shutter, and from their
    start it did not help on the benchmark's rolling-shutter capture (docs/poses.md)."""
    readout_s: float | None = Field(None, ge=0, le=0.1)
    """Readout time from the first row to the last (seconds; 0: global shutter); None: the
    one of ``readout_candidates`` whose model fits the keyframes best."""
    readout_candidates: tuple[float, ...] = Field((0.0, 0.01, 0.02, 0.03, 0.04), min_length=1)
    """Readouts (seconds) tried when ``readout_s`` is None (phones: about 10-35 ms)."""
    blur_samples: int = Field(9, ge=1, le=64)
    """Most samples along one streak (one per pixel of its length)."""
    max_width: int | None = Field(1920, ge=160, le=8192)
    """Keyframes wider than this (pixels) are adjusted at this width (area filter, aspect kept;
    the intrinsics scaled to it and the result's scaled back; poses are metric and do not
    change with it). PBA holds every keyframe with its pyramid and gradients, about 14 bytes
    a pixel: at 3840×2160 that is 116 MB a keyframe, 5 GB for 45 keyframes; at 1920×1080,
    29 MB. None: full resolution. 720p and 1080p captures are not affected."""


PATTERN = np.array([(0, -2), (-1, -1), (1, -1), (-2, 0), (0, 0), (2, 0), (-1, 1), (0, 2)],
                   np.float64)  # DSO's 8-pixel pattern (dx, dy)
N_FRAME = 8  # pose (v, w) + brightness (a, b) per keyframe
N_INTR = 5  # f, cx, cy, k1, k2


@dataclass
class PBAResult:
    intrinsics: Intrinsics
    R: list[np.ndarray]
    t: list[np.ndarray]
    affine: np.ndarray  # (K, 2) brightness a, b per keyframe
    points: int
    residuals: int
    rms_before: float
    rms_after: float
    seconds: float
    log: list[str]
    exposure_fraction: float | None = None  # the exposure the blur model used (of a frame)
    readout_s: float | None = None  # the rolling shutter's readout the model used


# -- numba kernels ---------------------------------------------------------------------------


@nb.njit(cache=True, inline="always")
def _bilinear(img, x, y):
    h, w = img.shape
    x0 = int(np.floor(x))
    y0 = int(np.floor(y))
    if x0 < 0 or y0 < 0 or x0 + 1 >= w or y0 + 1 >= h:
        return np.nan
    ax = x - x0
    ay = y - y0
    return ((1 - ay) * ((1 - ax) * img[y0, x0] + ax * img[y0, x0 + 1])
            + ay * ((1 - ax) * img[y0 + 1, x0] + ax * img[y0 + 1, x0 + 1]))


@nb.njit(cache=True)
def _undistort(xd, yd, k1, k2):
    """Normalised undistorted coordinates, r^2, and the Jacobian G of the distortion there."""
    rd = np.sqrt(xd * xd + yd * yd)
    r = rd
    for _ in range(20):
        r2 = r * r
        f = r * (1 + k1 * r2 + k2 * r2 * r2) - rd
        df = 1 + 3 * k1 * r2 + 5 * k2 * r2 * r2
        r = r - f / df
    s = r / rd if rd > 1e-12 else 1.0
    x = xd * s
    y = yd * s
    r2 = x * x + y * y
    fac = 1 + k1 * r2 + k2 * r2 * r2
    dfac = 2 * k1 + 4 * k2 * r2  # d fac / d r, divided by r
    return x, y, r2, fac + x * x * dfac, x * y * dfac, fac + y * y * dfac


@nb.njit(cache=True, inline="always")
def _distortion_terms(X0, X1, X2, k1, k2):
    """For a camera point: its normalised coordinates y, |y|², the radial factor and its
    derivative over |y|² (doubled): what the projection and its Jacobian share."""
    yx = X0 / X2
    yy = X1 / X2
    s2 = yx * yx + yy * yy
    return yx, yy, s2, 1 + k1 * s2 + k2 * s2 * s2, 2 * k1 + 4 * k2 * s2


@nb.njit(cache=True, inline="always")
def _pixel(X0, X1, X2, f, cx, cy, k1, k2):
    yx, yy, _, fac, _ = _distortion_terms(X0, X1, X2, k1, k2)
    return f * yx * fac + cx, f * yy * fac + cy


@nb.njit(cache=True, inline="always")
def _point_gradient(gx, gy, X0, X1, X2, f, yx, yy, fac, dfac):
    """g^T du/dX for the camera point X: the derivative of a pixel-space quantity with
    gradient (gx, gy) along u, with du/dy = f (fac I + dfac y y^T) and y = X[:2] / X[2]."""
    a0 = f * (gx * (fac + dfac * yx * yx) + gy * dfac * yx * yy)
    a1 = f * (gx * dfac * yx * yy + gy * (fac + dfac * yy * yy))
    return a0 / X2, a1 / X2, -(a0 * X0 + a1 * X1) / (X2 * X2)


@nb.njit(cache=True, inline="always")
def _blur(X0, X1, X2, m, f, cx, cy, k1, k2):
    """The image streak (pixels) of the camera point X over one exposure: ``m`` holds the
    angular and linear displacement over half the exposure (w, v), X moves by w x X + v."""
    d0 = m[1] * X2 - m[2] * X1 + m[3]
    d1 = m[2] * X0 - m[0] * X2 + m[4]
    d2 = m[0] * X1 - m[1] * X0 + m[5]
    ua, va = _pixel(X0 + d0, X1 + d1, X2 + d2, f, cx, cy, k1, k2)
    ub, vb = _pixel(X0 - d0, X1 - d1, X2 - d2, f, cx, cy, k1, k2)
    return ua - ub, va - vb


@nb.njit(cache=True, inline="always")
def _moved(X0, X1, X2, m, tau):
    """A camera point after the camera moved for ``tau`` seconds at velocity ``m`` (w, v)."""
    return (X0 + tau * (m[1] * X2 - m[2] * X1 + m[3]),
            X1 + tau * (m[2] * X0 - m[0] * X2 + m[4]),
            X2 + tau * (m[0] * X1 - m[1] * X0 + m[5]))


@nb.njit(cache=True, inline="always")
def _streak(img, x, y, dx, dy, n):
    """Mean of ``img`` over ``n`` samples of the segment centred on (x, y) with extent
    (dx, dy): an image seen through a box blur along that segment."""
    if n == 1:
        return _bilinear(img, x, y)
    acc = 0.0
    for i in range(n):
        s = i / (n - 1) - 0.5
        v = _bilinear(img, x + s * dx, y + s * dy)
        if np.isnan(v):
            return np.nan
        acc += v
    return acc / n


@nb.njit(cache=True, inline="always")
def _samples(dx, dy, most):
    """Samples of a streak: one per pixel of its length, at least one, at most ``most``."""
    return min(most, 1 + int(np.ceil(np.sqrt(dx * dx + dy * dy))))


@nb.njit(cache=True, nogil=True)
def _accumulate(host, uv, rho, target_start, targets, images, grad_x, grad_y, host_weights,
                motion, max_samples, velocity, readout, rows, R_rel, t_rel, affine, intr,
                huber, max_residual, with_cameras, jacobians, H, b, Hpp, bpp, Hcp_store,
                idx_store, stats, res_out):
    """Residuals, weights and Jacobians of every point; Schur-reduced normal equations.

    Camera unknowns are [intrinsics (5), keyframes 1..K-1 (8 each)]; keyframe 0 is fixed.
    Per point, its camera columns (intrinsics, host, targets) are gathered locally, and
    H_cc - h_cp h_cp^T / h_pp is scattered into H when ``with_cameras``; without
    ``jacobians`` only the cost (and ``res_out``) is computed. A point's residuals
    in one target are dropped together when their root mean square exceeds ``max_residual``
    (the point occluded there, or a highlight): each then costs a constant. ``res_out``, when
    not empty, receives every residual's magnitude (the robust scale).

    Motion blur (``motion``: per keyframe the camera's displacement over half its exposure,
    (w, v), zero for none): each keyframe saw the scene averaged along its own streak, so
    the host is sampled along the target's streak (mapped into the host) and the target
    along the host's (mapped into the target). Both sides are then the scene blurred by
    both streaks, equal at the true poses whatever the blur (a box blur along a segment
    commutes with the locally affine warp). The Jacobian treats the host's side as fixed.

    Rolling shutter (``readout``: seconds from the first of ``rows`` image rows to the last;
    0 for a global shutter): row y was exposed ``readout (y / rows - 1/2)`` after the frame's
    middle, by the camera moved by its ``velocity`` (per keyframe (w, v) per second, a
    constant velocity) for that long. A host pixel's ray is cast from its row's camera; the
    point is found in the target's row that sees it (two fixed-point steps).
    """
    # Long on purpose: a numba kernel: one pass over points, targets and pattern pixels that keeps
    # each residual's Jacobian in registers and scatters it once; its pixel model is the inlined
    # helpers above.
    f, cx, cy, k1, k2 = intr[0], intr[1], intr[2], intr[3], intr[4]
    max_local = Hcp_store.shape[1]
    cost = 0.0
    count = 0
    dxd = np.zeros((2, N_INTR))
    dxn = np.zeros((2, N_INTR))
    # A residual's camera columns: the intrinsics and the host's (fixed), then its target's.
    nonzero = np.arange(N_INTR + 2 * N_FRAME)
    for p in range(host.shape[0]):
        h = host[p]
        ah = affine[h, 0]
        bh = affine[h, 1]
        t0 = target_start[p]
        t1 = target_start[p + 1]
        n_frames = 1 + t1 - t0
        n_loc = N_INTR + N_FRAME * n_frames
        Hcc = np.zeros((n_loc, n_loc))
        hcp = np.zeros(n_loc)
        bc = np.zeros(n_loc)
        J = np.zeros(n_loc)
        hpp = 0.0
        bp = 0.0
        # Per target: the host's streak mapped into it and its own mapped into the host,
        # through the warp's Jacobian at the point (pattern pixels at the point's depth).
        streaks = np.zeros((t1 - t0, 4))
        xc, yc, _, _, _, _ = _undistort((uv[p, 0] - cx) / f, (uv[p, 1] - cy) / f, k1, k2)
        xx, yx_, _, _, _, _ = _undistort((uv[p, 0] + 1 - cx) / f, (uv[p, 1] - cy) / f, k1, k2)
        xy_, yy_, _, _, _, _ = _undistort((uv[p, 0] - cx) / f, (uv[p, 1] + 1 - cy) / f, k1, k2)
        hb0, hb1 = _blur(xc / rho[p], yc / rho[p], 1.0 / rho[p], motion[h], f, cx, cy, k1, k2)
        for k in range(t0, t1):
            tg = targets[k]
            Rr = R_rel[h, tg]
            tr = t_rel[h, tg]
            pts = np.empty((3, 2))
            Xc = np.empty(3)
            ok = True
            for j in range(3):
                ax, ay = (xc, yc) if j == 0 else ((xx, yx_) if j == 1 else (xy_, yy_))
                Y0 = (Rr[0, 0] * ax + Rr[0, 1] * ay + Rr[0, 2]) / rho[p] + tr[0]
                Y1 = (Rr[1, 0] * ax + Rr[1, 1] * ay + Rr[1, 2]) / rho[p] + tr[1]
                Y2 = (Rr[2, 0] * ax + Rr[2, 1] * ay + Rr[2, 2]) / rho[p] + tr[2]
                if Y2 <= 1e-9:
                    ok = False
                    break
                if j == 0:
                    Xc[0], Xc[1], Xc[2] = Y0, Y1, Y2
                pts[j, 0], pts[j, 1] = _pixel(Y0, Y1, Y2, f, cx, cy, k1, k2)
            if not ok:
                continue
            a00 = pts[1, 0] - pts[0, 0]
            a10 = pts[1, 1] - pts[0, 1]
            a01 = pts[2, 0] - pts[0, 0]
            a11 = pts[2, 1] - pts[0, 1]
            tb0, tb1 = _blur(Xc[0], Xc[1], Xc[2], motion[tg], f, cx, cy, k1, k2)
            det = a00 * a11 - a01 * a10
            streaks[k - t0, 0] = a00 * hb0 + a01 * hb1
            streaks[k - t0, 1] = a10 * hb0 + a11 * hb1
            if abs(det) > 1e-9:
                streaks[k - t0, 2] = (a11 * tb0 - a01 * tb1) / det
                streaks[k - t0, 3] = (-a10 * tb0 + a00 * tb1) / det
        # The samples of every (pattern pixel, target): host and target values, the target's
        # gradient; NaN where either leaves its image. A target whose residuals are too large
        # together is an outlier for the whole pattern.
        nt_ = t1 - t0
        cache = np.full((nt_, 8, 4), np.nan)
        pair_ok = np.zeros(nt_, np.bool_)
        host_X = np.empty((8, 3))  # the pattern's points in the host's mid-frame camera
        target_X = np.full((nt_, 8, 3), np.nan)  # and in each target's, at their rows' times
        host_ray = np.empty((8, 6))  # each pattern pixel's undistortion (for the Jacobians)
        for q in range(8):
            uh = uv[p, 0] + PATTERN[q, 0]
            vh = uv[p, 1] + PATTERN[q, 1]
            xn, yn, rn2, g00, g01, g11 = _undistort((uh - cx) / f, (vh - cy) / f, k1, k2)
            host_ray[q, 0], host_ray[q, 1], host_ray[q, 2] = xn, yn, rn2
            host_ray[q, 3], host_ray[q, 4], host_ray[q, 5] = g00, g01, g11
            Y0, Y1, Y2 = xn / rho[p], yn / rho[p], 1.0 / rho[p]
            if readout != 0.0:
                Y0, Y1, Y2 = _moved(Y0, Y1, Y2, velocity[h], -readout * (vh / rows - 0.5))
            host_X[q, 0], host_X[q, 1], host_X[q, 2] = Y0, Y1, Y2
            for k in range(t0, t1):
                tg = targets[k]
                Rr = R_rel[h, tg]
                tr = t_rel[h, tg]
                Z0 = Rr[0, 0] * Y0 + Rr[0, 1] * Y1 + Rr[0, 2] * Y2 + tr[0]
                Z1 = Rr[1, 0] * Y0 + Rr[1, 1] * Y1 + Rr[1, 2] * Y2 + tr[1]
                Z2 = Rr[2, 0] * Y0 + Rr[2, 1] * Y1 + Rr[2, 2] * Y2 + tr[2]
                X0, X1, X2 = Z0, Z1, Z2
                if readout != 0.0 and Z2 > 1e-9:
                    for _ in range(2):
                        _, vt = _pixel(X0, X1, X2, f, cx, cy, k1, k2)
                        X0, X1, X2 = _moved(Z0, Z1, Z2, velocity[tg],
                                            readout * (vt / rows - 0.5))
                        if X2 <= 1e-9:
                            break
                if X2 <= 1e-9:
                    continue
                target_X[k - t0, q, 0], target_X[k - t0, q, 1] = X0, X1
                target_X[k - t0, q, 2] = X2
                ut, vt = _pixel(X0, X1, X2, f, cx, cy, k1, k2)
                sx, sy = streaks[k - t0, 0], streaks[k - t0, 1]
                nt = _samples(sx, sy, max_samples)
                It = _streak(images[tg], ut, vt, sx, sy, nt)
                nh = _samples(streaks[k - t0, 2], streaks[k - t0, 3], max_samples)
                Ih = _streak(images[h], uh, vh, streaks[k - t0, 2], streaks[k - t0, 3], nh)
                if np.isnan(It) or np.isnan(Ih):
                    continue
                cache[k - t0, q, 0] = It
                cache[k - t0, q, 1] = Ih
                if jacobians:
                    cache[k - t0, q, 2] = _streak(grad_x[tg], ut, vt, sx, sy, nt)
                    cache[k - t0, q, 3] = _streak(grad_y[tg], ut, vt, sx, sy, nt)
        for k in range(t0, t1):
            tg = targets[k]
            ea = np.exp(affine[tg, 0] - ah)
            ss = 0.0
            inside = True
            for q in range(8):
                if np.isnan(cache[k - t0, q, 0]):
                    inside = False
                    break
                r = cache[k - t0, q, 0] - affine[tg, 1] - ea * (cache[k - t0, q, 1] - bh)
                ss += r * r
                if res_out.shape[0] > 0 and stats[2] < res_out.shape[0]:
                    res_out[int(stats[2])] = abs(r)
                    stats[2] += 1
            pair_ok[k - t0] = inside and ss <= 8 * max_residual * max_residual
        for q in range(8):
            uh = uv[p, 0] + PATTERN[q, 0]
            vh = uv[p, 1] + PATTERN[q, 1]
            xd = (uh - cx) / f
            yd = (vh - cy) / f
            xn, yn, rn2 = host_ray[q, 0], host_ray[q, 1], host_ray[q, 2]
            g00, g01, g11 = host_ray[q, 3], host_ray[q, 4], host_ray[q, 5]
            # x_d = g(x_n; k) = (u - c) / f  =>  dx_n/dθ = G^-1 (dx_d/dθ - ∂g/∂θ)
            det = g00 * g11 - g01 * g01
            dxd[0, 0] = -xd / f
            dxd[1, 0] = -yd / f
            dxd[0, 1] = -1.0 / f
            dxd[1, 1] = 0.0
            dxd[0, 2] = 0.0
            dxd[1, 2] = -1.0 / f
            dxd[0, 3] = -xn * rn2
            dxd[1, 3] = -yn * rn2
            dxd[0, 4] = -xn * rn2 * rn2
            dxd[1, 4] = -yn * rn2 * rn2
            for c in range(N_INTR):
                dxn[0, c] = (g11 * dxd[0, c] - g01 * dxd[1, c]) / det
                dxn[1, c] = (-g01 * dxd[0, c] + g00 * dxd[1, c]) / det
            # The Jacobians take the rolling shutter's motion as fixed (it is a velocity times
            # a fraction of the readout: ~1 % of the points' own change).
            Xh0, Xh1, Xh2 = host_X[q, 0], host_X[q, 1], host_X[q, 2]
            for k in range(t0, t1):
                tg = targets[k]
                slot = 1 + k - t0
                Rr = R_rel[h, tg]
                X0, X1, X2 = target_X[k - t0, q, 0], target_X[k - t0, q, 1], target_X[k - t0, q, 2]
                if not X2 > 1e-9:
                    continue
                gw = host_weights[p, q]
                if not pair_ok[k - t0]:
                    # Leaving the image costs as much as an outlier, so that no step can
                    # lower the cost by pushing residuals out of view.
                    cost += gw * (2 * huber * max_residual - huber * huber)
                    count += 1
                    continue
                It = cache[k - t0, q, 0]
                Ih = cache[k - t0, q, 1]
                gx = cache[k - t0, q, 2]
                gy = cache[k - t0, q, 3]
                ea = np.exp(affine[tg, 0] - ah)
                r = It - affine[tg, 1] - ea * (Ih - bh)
                ar = abs(r)
                if ar < huber:
                    w = gw
                    cost += gw * r * r
                else:
                    w = gw * huber / ar
                    cost += gw * (2 * huber * ar - huber * huber)
                count += 1
                if not jacobians:
                    continue
                yx, yy, s2, fac, dfac = _distortion_terms(X0, X1, X2, k1, k2)
                dX0, dX1, dX2 = _point_gradient(gx, gy, X0, X1, X2, f, yx, yy, fac, dfac)
                for c in range(n_loc):
                    J[c] = 0.0
                # target keyframe: dX_t = v + w x X_t
                bt = N_INTR + N_FRAME * slot
                J[bt + 0] = dX0
                J[bt + 1] = dX1
                J[bt + 2] = dX2
                J[bt + 3] = X1 * dX2 - X2 * dX1
                J[bt + 4] = X2 * dX0 - X0 * dX2
                J[bt + 5] = X0 * dX1 - X1 * dX0
                J[bt + 6] = -ea * (Ih - bh)
                J[bt + 7] = -1.0
                # host keyframe: dX_t = -R_th (v + w x X_h)
                e0 = dX0 * Rr[0, 0] + dX1 * Rr[1, 0] + dX2 * Rr[2, 0]
                e1 = dX0 * Rr[0, 1] + dX1 * Rr[1, 1] + dX2 * Rr[2, 1]
                e2 = dX0 * Rr[0, 2] + dX1 * Rr[1, 2] + dX2 * Rr[2, 2]
                bh_ = N_INTR
                J[bh_ + 0] = -e0
                J[bh_ + 1] = -e1
                J[bh_ + 2] = -e2
                J[bh_ + 3] = -(Xh1 * e2 - Xh2 * e1)
                J[bh_ + 4] = -(Xh2 * e0 - Xh0 * e2)
                J[bh_ + 5] = -(Xh0 * e1 - Xh1 * e0)
                J[bh_ + 6] = ea * (Ih - bh)
                J[bh_ + 7] = ea
                # intrinsics: through the host ray, and directly in the target projection
                for c in range(N_INTR):
                    J[c] = (e0 * dxn[0, c] + e1 * dxn[1, c]) / rho[p]
                J[0] += (gx * yx + gy * yy) * fac
                J[1] += gx
                J[2] += gy
                J[3] += f * (gx * yx + gy * yy) * s2
                J[4] += f * (gx * yx + gy * yy) * s2 * s2
                # inverse depth: dX_h / drho = -X_h / rho
                jp = -(e0 * Xh0 + e1 * Xh1 + e2 * Xh2) / rho[p]
                hpp += w * jp * jp
                bp += w * jp * r
                if with_cameras:
                    # Only the intrinsics', the host's and this target's columns can be
                    # non-zero: the products of those alone (in the same order) are the sums.
                    for i in range(N_FRAME):
                        nonzero[N_INTR + N_FRAME + i] = bt + i
                    for i1 in range(N_INTR + 2 * N_FRAME):
                        c1 = nonzero[i1]
                        if J[c1] == 0.0:
                            continue
                        wj = w * J[c1]
                        bc[c1] += wj * r
                        hcp[c1] += wj * jp
                        for i2 in range(i1, N_INTR + 2 * N_FRAME):
                            Hcc[c1, nonzero[i2]] += wj * J[nonzero[i2]]
        Hpp[p] = hpp
        bpp[p] = bp
        for c in range(max_local):
            idx_store[p, c] = -1
        if not with_cameras or hpp <= 0:
            continue
        inv = 1.0 / hpp
        for c1 in range(n_loc):
            s1 = (c1 - N_INTR) // N_FRAME
            if c1 < N_INTR:
                g1 = c1
            else:
                fr = h if s1 == 0 else targets[t0 + s1 - 1]
                g1 = -1 if fr == 0 else N_INTR + N_FRAME * (fr - 1) + (c1 - N_INTR) % N_FRAME
            idx_store[p, c1] = g1
            Hcp_store[p, c1] = hcp[c1]
        for c1 in range(n_loc):
            g1 = idx_store[p, c1]
            if g1 < 0:
                continue
            b[g1] += bc[c1] - hcp[c1] * inv * bp
            for c2 in range(c1, n_loc):
                g2 = idx_store[p, c2]
                if g2 < 0:
                    continue
                v = Hcc[c1, c2] - hcp[c1] * inv * hcp[c2]
                H[g1, g2] += v
                if g1 != g2:
                    H[g2, g1] += v
    stats[0] = cost
    stats[1] = count


ACCUMULATE_CHUNKS = 2
"""The photometric normal equations are summed over this many fixed runs of points, each
on its own thread (the kernel releases the GIL), and added in this order: the same sums,
so the same cameras, on one core or many; two use both cores of the machine the pipeline
is sized for (PBA runs alone in the pipeline)."""


def _accumulate_in_chunks(host, uv, rho, target_start, targets, images, grad_x, grad_y,
                          host_weights, motion, max_samples, velocity, readout, rows, R_rel,
                          t_rel, affine, intr, huber, max_residual, with_cameras, H, b, Hpp,
                          bpp, Hcp_store, idx_store, stats, res_out,
                          chunks: int = ACCUMULATE_CHUNKS, jacobians: bool = True):
    """:func:`_accumulate` over ``chunks`` runs of points at once: per-point outputs are
    written in place (the runs are disjoint), the camera system and the cost summed in
    order, the residual magnitudes gathered at the front of ``res_out`` (stats[2] of them)."""
    cuts = np.linspace(0, len(host), chunks + 1).astype(np.int64)
    runs = []
    for a, z in zip(cuts[:-1], cuts[1:]):
        out = res_out[8 * target_start[a]:8 * target_start[z]] if len(res_out) else res_out
        runs.append((a, z, np.zeros_like(H), np.zeros_like(b), np.zeros(3), out))

    def run(part):
        a, z, H_, b_, stats_, out = part
        _accumulate(host[a:z], uv[a:z], rho[a:z], target_start[a:z + 1], targets, images,
                    grad_x, grad_y, host_weights[a:z], motion, max_samples, velocity, readout,
                    rows, R_rel, t_rel, affine, intr, huber, max_residual, with_cameras,
                    jacobians, H_,
                    b_, Hpp[a:z], bpp[a:z], Hcp_store[a:z], idx_store[a:z], stats_, out)

    if chunks == 1:
        run(runs[0])
    else:
        with ThreadPoolExecutor(chunks) as pool:
            list(pool.map(run, runs))
    stats[0] = stats[1] = 0.0
    written = int(stats[2])
    for _, _, H_, b_, stats_, out in runs:
        H += H_
        b += b_
        stats[0] += stats_[0]
        stats[1] += stats_[1]
        n = int(stats_[2])
        if n:  # each run's magnitudes start its own slice, at or after the gathered ones
            res_out[written:written + n] = out[:n].copy()
            written += n
    stats[2] = written


@nb.njit(cache=True)
def _accumulate_tracks(X, obs_start, obs_frame, obs_xy, R, t, intr, weight, huber_px,
                       velocity, readout, rows, with_cameras, H, b, Hpp, bpp, Hpc, stats):
    """Reprojection residuals of the tracked points (world points X, 3 unknowns each, their
    observations in CSR order) added to the same normal equations as the photometric ones,
    the points eliminated by their own 3x3 Schur blocks. ``weight`` is the cost of one pixel
    in squared grey levels; Huber beyond ``huber_px``. Keyframe 0 is fixed (the gauge).
    ``Hpc`` keeps each observation's 3x6 pose block and each point's 3x5 intrinsics block
    (stored after the observations) for the back-substitution. With a rolling shutter
    (``readout`` > 0) each observation is of the camera moved for its row's time offset.
    """
    # Long on purpose: a numba kernel, one pass over the observations as in _accumulate.
    f, cx, cy, k1, k2 = intr[0], intr[1], intr[2], intr[3], intr[4]
    n_obs_total = obs_frame.shape[0]
    cost = 0.0
    e = np.empty(2)
    J = np.empty(N_INTR + 6)  # one residual's columns: intrinsics, then its keyframe's pose
    jp = np.empty(3)
    cols = np.empty(N_INTR + 6, np.int64)
    for c in range(N_INTR):
        cols[c] = c
    for p in range(X.shape[0]):
        o0 = obs_start[p]
        o1 = obs_start[p + 1]
        n = o1 - o0
        # local unknowns: intrinsics (5), then 6 pose unknowns per observation
        n_loc = N_INTR + 6 * n
        m = n_loc if with_cameras else 0  # a long track's camera block is large: only if used
        Hcc = np.zeros((m, m))
        Wc = np.zeros((3, m))
        bc = np.zeros(m)
        Hp = np.zeros((3, 3))
        bp = np.zeros(3)
        for o in range(o0, o1):
            k = obs_frame[o]
            Rk = R[k]
            Xc0 = Rk[0, 0] * X[p, 0] + Rk[0, 1] * X[p, 1] + Rk[0, 2] * X[p, 2] + t[k, 0]
            Xc1 = Rk[1, 0] * X[p, 0] + Rk[1, 1] * X[p, 1] + Rk[1, 2] * X[p, 2] + t[k, 1]
            Xc2 = Rk[2, 0] * X[p, 0] + Rk[2, 1] * X[p, 1] + Rk[2, 2] * X[p, 2] + t[k, 2]
            if readout != 0.0:
                Xc0, Xc1, Xc2 = _moved(Xc0, Xc1, Xc2, velocity[k],
                                       readout * (obs_xy[o, 1] / rows - 0.5))
            if Xc2 <= 1e-9:
                continue
            yx, yy, s2, fac, dfac = _distortion_terms(Xc0, Xc1, Xc2, k1, k2)
            e[0] = f * yx * fac + cx - obs_xy[o, 0]
            e[1] = f * yy * fac + cy - obs_xy[o, 1]
            norm = np.sqrt(e[0] * e[0] + e[1] * e[1])
            w = weight if norm <= huber_px else weight * huber_px / norm
            cost += (weight * norm * norm if norm <= huber_px
                     else weight * (2 * huber_px * norm - huber_px * huber_px))
            stats[1] += 1
            slot = N_INTR + 6 * (o - o0)
            for c in range(6):
                cols[N_INTR + c] = slot + c
            for row in range(2):
                gx = 1.0 if row == 0 else 0.0
                gy = 1.0 - gx
                dX0, dX1, dX2 = _point_gradient(gx, gy, Xc0, Xc1, Xc2, f, yx, yy, fac, dfac)
                y = yx if row == 0 else yy
                J[0] = y * fac
                J[1] = gx
                J[2] = gy
                J[3] = f * y * s2
                J[4] = f * y * s2 * s2
                J[5] = dX0
                J[6] = dX1
                J[7] = dX2
                J[8] = Xc1 * dX2 - Xc2 * dX1
                J[9] = Xc2 * dX0 - Xc0 * dX2
                J[10] = Xc0 * dX1 - Xc1 * dX0
                for c in range(3):
                    jp[c] = dX0 * Rk[0, c] + dX1 * Rk[1, c] + dX2 * Rk[2, c]
                r = e[row]
                for c1 in range(3):
                    bp[c1] += w * jp[c1] * r
                    for c2 in range(3):
                        Hp[c1, c2] += w * jp[c1] * jp[c2]
                if not with_cameras:
                    continue
                for i1 in range(N_INTR + 6):
                    c1 = cols[i1]
                    bc[c1] += w * J[i1] * r
                    for c in range(3):
                        Wc[c, c1] += w * J[i1] * jp[c]
                    for i2 in range(N_INTR + 6):
                        Hcc[c1, cols[i2]] += w * J[i1] * J[i2]
        Hpp[p] = Hp
        bpp[p] = bp
        if not with_cameras:
            continue
        det = np.linalg.det(Hp)
        if abs(det) < 1e-18:
            continue
        inv = np.linalg.inv(Hp)
        # global columns of the local unknowns (-1: keyframe 0, fixed)
        glob = np.empty(n_loc, np.int64)
        for c in range(N_INTR):
            glob[c] = c
        for o in range(o0, o1):
            k = obs_frame[o]
            for c in range(6):
                glob[N_INTR + 6 * (o - o0) + c] = -1 if k == 0 else N_INTR + N_FRAME * (k - 1) + c
            for c in range(3):
                for c2 in range(6):
                    Hpc[o, c, c2] = Wc[c, N_INTR + 6 * (o - o0) + c2]
        for c in range(3):
            for c2 in range(N_INTR):
                Hpc[n_obs_total + p, c, c2] = Wc[c, c2]
        IW = inv @ Wc
        for c1 in range(n_loc):
            g1 = glob[c1]
            if g1 < 0:
                continue
            b[g1] += bc[c1] - (Wc[0, c1] * (inv[0, 0] * bp[0] + inv[0, 1] * bp[1] + inv[0, 2] * bp[2])
                               + Wc[1, c1] * (inv[1, 0] * bp[0] + inv[1, 1] * bp[1] + inv[1, 2] * bp[2])
                               + Wc[2, c1] * (inv[2, 0] * bp[0] + inv[2, 1] * bp[1] + inv[2, 2] * bp[2]))
            for c2 in range(n_loc):
                g2 = glob[c2]
                if g2 < 0:
                    continue
                H[g1, g2] += Hcc[c1, c2] - (Wc[0, c1] * IW[0, c2] + Wc[1, c1] * IW[1, c2]
                                            + Wc[2, c1] * IW[2, c2])
    stats[0] += cost


@nb.njit(cache=True)
def _search_depth(host, uv, host_values, rho_lo, rho_hi, samples, neighbours, images, R_rel,
                  t_rel, intr, out_rho, out_quality):
    """Per point, the inverse depth in [rho_lo, rho_hi] (log-spaced samples) whose pattern
    matches best (SSD, mean-normalised) in the neighbouring keyframes; quality is the ratio of
    the second-best separated minimum to the best (higher = less ambiguous)."""
    f, cx, cy, k1, k2 = intr[0], intr[1], intr[2], intr[3], intr[4]
    K = len(images)
    costs = np.empty(samples)
    for p in range(host.shape[0]):
        h = host[p]
        mh = 0.0
        for q in range(8):
            mh += host_values[p, q]
        mh /= 8
        for i in range(samples):
            costs[i] = 0.0
        used = 0
        for dn in range(-neighbours, neighbours + 1):
            tg = h + dn
            if dn == 0 or tg < 0 or tg >= K:
                continue
            used += 1
            Rr = R_rel[h, tg]
            tr = t_rel[h, tg]
            for i in range(samples):
                rho = rho_lo * (rho_hi / rho_lo) ** (i / (samples - 1))
                vals = np.empty(8)
                ok = True
                for q in range(8):
                    xn, yn, _, _, _, _ = _undistort((uv[p, 0] + PATTERN[q, 0] - cx) / f,
                                                    (uv[p, 1] + PATTERN[q, 1] - cy) / f, k1, k2)
                    X0 = Rr[0, 0] * xn + Rr[0, 1] * yn + Rr[0, 2] + tr[0] * rho
                    X1 = Rr[1, 0] * xn + Rr[1, 1] * yn + Rr[1, 2] + tr[1] * rho
                    X2 = Rr[2, 0] * xn + Rr[2, 1] * yn + Rr[2, 2] + tr[2] * rho
                    if X2 <= 1e-9:
                        ok = False
                        break
                    yx = X0 / X2
                    yy = X1 / X2
                    s2 = yx * yx + yy * yy
                    fac = 1 + k1 * s2 + k2 * s2 * s2
                    v = _bilinear(images[tg], f * yx * fac + cx, f * yy * fac + cy)
                    if np.isnan(v):
                        ok = False
                        break
                    vals[q] = v
                if not ok:
                    costs[i] += 1e6
                    continue
                mt = vals.mean()
                c = 0.0
                for q in range(8):
                    d = (vals[q] - mt) - (host_values[p, q] - mh)
                    c += d * d
                costs[i] += c
        best = np.argmin(costs)
        out_rho[p] = rho_lo * (rho_hi / rho_lo) ** (best / (samples - 1))
        second = np.inf
        for i in range(samples):
            if abs(i - best) > 2 and costs[i] < second:
                second = costs[i]
        out_quality[p] = second / (costs[best] + 1e-6) if used > 0 else 0.0


# -- set-up ----------------------------------------------------------------------------------


def _pyramid(img: np.ndarray, levels: int) -> list[np.ndarray]:
    out = [img]
    for _ in range(levels - 1):
        out.append(cv2.pyrDown(out[-1]))
    return out


def _gradients(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    return gx, gy


def _select_points(img: np.ndarray, cell: int, min_grad: float, margin: int) -> np.ndarray:
    """The strongest-gradient pixel of each cell×cell block, if strong enough (N, 2)."""
    gx, gy = _gradients(img)
    mag = np.hypot(gx, gy)
    h, w = img.shape
    hc, wc = (h - 2 * margin) // cell, (w - 2 * margin) // cell
    block = mag[margin:margin + hc * cell, margin:margin + wc * cell]
    block = block.reshape(hc, cell, wc, cell).transpose(0, 2, 1, 3).reshape(hc, wc, -1)
    arg = block.argmax(-1)
    best = np.take_along_axis(block, arg[..., None], -1)[..., 0]
    yy, xx = np.divmod(arg, cell)
    ys = margin + np.arange(hc)[:, None] * cell + yy
    xs = margin + np.arange(wc)[None, :] * cell + xx
    keep = best > min_grad
    return np.stack([xs[keep], ys[keep]], 1).astype(np.float64)


class _Normal:
    """The normal equations of one evaluation: the Schur-reduced camera system, and what
    the back-substitution of the photometric inverse depths and the tracked points needs."""

    def __init__(self, n_cam: int, n_points: int, max_local: int, n_tracks: int,
                 n_obs: int):
        self.H = np.zeros((n_cam, n_cam))
        self.b = np.zeros(n_cam)
        self.Hpp, self.bpp = np.zeros(n_points), np.zeros(n_points)
        self.Hcp = np.zeros((n_points, max_local))
        self.idx = np.full((n_points, max_local), -1, np.int64)
        self.Hpp3, self.bpp3 = np.zeros((n_tracks, 3, 3)), np.zeros((n_tracks, 3))
        self.Hpc = np.zeros((n_obs + n_tracks, 3, 6))
        self.stats = np.zeros(3)


def _track_steps(e: _Normal, dc: np.ndarray, obs_start, obs_frame, lam: float) -> np.ndarray:
    """The tracked points' steps for the camera step ``dc`` (back-substitution)."""
    n = len(e.bpp3)
    if n == 0:
        return np.zeros((0, 3))
    n_obs = len(obs_frame)
    pose = np.zeros((n_obs, 6))
    moving = obs_frame > 0
    cols = N_INTR + N_FRAME * (obs_frame[moving] - 1)
    pose[moving] = dc[cols[:, None] + np.arange(6)]
    rhs = e.bpp3 + np.einsum("ncj,j->nc", e.Hpc[n_obs:, :, :N_INTR], dc[:N_INTR])
    per_obs = np.einsum("ocj,oj->oc", e.Hpc[:n_obs], pose)
    point = np.repeat(np.arange(n), np.diff(obs_start))
    np.add.at(rhs, point, per_obs)
    Hd = e.Hpp3 + lam * np.einsum("nii->ni", e.Hpp3)[:, :, None] * np.eye(3)[None]
    ok = np.abs(np.linalg.det(Hd)) > 1e-18
    step = np.zeros((n, 3))
    step[ok] = -np.linalg.solve(Hd[ok], rhs[ok][:, :, None])[:, :, 0]
    return step


def _track_noise_px(tracks: tuple[np.ndarray, np.ndarray], R, t, intrinsics: Intrinsics,
                    full: Intrinsics) -> float:
    """The tracked observations' noise at the start (robust standard deviation of their
    reprojection errors, pixels of ``intrinsics``; the start is a bundle adjustment's, so
    what is left is their noise)."""
    points, obs = np.asarray(tracks[0], float), np.asarray(tracks[1], float)
    scale = intrinsics.width / full.width
    errors = np.empty(len(obs))
    for k in np.unique(obs[:, 1]).astype(int):
        sel = obs[:, 1] == k
        uv, _ = project(points[obs[sel, 0].astype(int)], R[k], t[k], intrinsics)
        errors[sel] = np.linalg.norm(uv - ((obs[sel, 2:4] + 0.5) * scale - 0.5), axis=1)
    # The median length of a 2D Gaussian error is 1.1774 of its standard deviation.
    return float(np.median(errors) / 1.1774)


def _adjust_to_tracks(R, t, intr, X, obs_start, obs_frame, obs_xy, rows, velocity, readout,
                      huber_px, iterations, free_intrinsics=True, pp_prior=None):
    """Cameras, intrinsics (``free_intrinsics``) and points adjusted to the tracked points
    alone under a given rolling-shutter readout (Levenberg-Marquardt; the gauge: keyframe 0
    and the first baseline's length), and the reprojection cost left: how well that readout
    explains the tracks. ``pp_prior``: (centre, weight per pixel² of x and y) of the principal
    point's prior. Returns (cost, R, t, intr, X)."""
    pp0, w_pp = pp_prior if pp_prior is not None else (np.zeros(2), np.zeros(2))

    def prior(intr_):
        return float(np.sum(w_pp * (intr_[1:3] - pp0) ** 2))

    K = len(R)
    n_cam = N_INTR + N_FRAME * (K - 1)
    R, t, intr, X = list(R), list(t), intr.copy(), X.copy()
    lam = 1e-3
    baseline = np.linalg.norm(R[1].T @ t[1] - R[0].T @ t[0])

    def run(R_, t_, intr_, X_, with_cameras):
        e = _Normal(n_cam, 0, 1, len(X_), len(obs_frame))
        _accumulate_tracks(X_, obs_start, obs_frame, obs_xy, np.asarray(R_), np.asarray(t_),
                           intr_, 1.0, huber_px, velocity(R_, t_), readout, rows,
                           with_cameras, e.H, e.b, e.Hpp3, e.bpp3, e.Hpc, e.stats)
        return e

    e = run(R, t, intr, X, True)
    for _ in range(iterations):
        H, b = e.H.copy(), e.b.copy()
        _hold_baseline(H, b, R, t, baseline, 1e8)
        if not free_intrinsics:
            H[:N_INTR, :N_INTR] += 1e12 * np.eye(N_INTR)
        else:
            H[1:3, 1:3] += np.diag(w_pp)
            b[1:3] += w_pp * (intr[1:3] - pp0)
        dc = -np.linalg.solve(H + lam * np.diag(np.diag(H)) + 1e-9 * np.eye(n_cam), b)
        R2, t2, _ = _update_frames(R, t, np.zeros((K, 2)), dc[N_INTR:])
        intr2 = intr + dc[:N_INTR]
        X2 = X + _track_steps(e, dc, obs_start, obs_frame, lam)
        e2 = run(R2, t2, intr2, X2, True)
        if e2.stats[0] + prior(intr2) < e.stats[0] + prior(intr):
            R, t, intr, X, e = R2, t2, intr2, X2, e2
            lam = max(lam / 4, 1e-7)
        else:
            lam *= 4
    return float(e.stats[0]) + prior(intr), R, t, intr, X


def _hold_baseline(H, b, R, t, length, weight):
    """Add the scale gauge to the camera system: a prior holding the first baseline at
    ``length`` (keyframe 1's centre moves by -R_1^T v_1 under its increment)."""
    c0, c1 = -R[0].T @ t[0], -R[1].T @ t[1]
    n = (c1 - c0) / np.linalg.norm(c1 - c0)
    a = -R[1] @ n
    sl = slice(N_INTR, N_INTR + 3)
    H[sl, sl] += weight * np.outer(a, a)
    b[sl] += weight * a * (np.linalg.norm(c1 - c0) - length)


def _update_frames(R, t, affine, delta):
    """Left-multiplied pose increments (v, w) and brightness increments for keyframes 1..K-1."""
    R, t, affine = [r.copy() for r in R], [x.copy() for x in t], affine.copy()
    for k in range(1, len(R)):
        d = delta[N_FRAME * (k - 1): N_FRAME * k]
        angle = np.linalg.norm(d[3:6])
        dR = np.eye(3) if angle < 1e-15 else rotation_matrix(d[3:6] / angle, angle)
        R[k] = dR @ R[k]
        t[k] = dR @ t[k] + d[:3]
        affine[k] += d[6:8]
    return R, t, affine


def _relative(R, t):
    """Every pair's relative pose: R_rel[h, k] = R_k R_hᵀ, t_rel[h, k] = t_k - R_rel[h, k] t_h."""
    R, t = np.asarray(R, float), np.asarray(t, float)
    R_rel = np.matmul(R[None], np.swapaxes(R, 1, 2)[:, None])
    t_rel = t[None] - np.matmul(R_rel, t[:, None, :, None])[..., 0]
    return R_rel, t_rel


def camera_motion(R: list[np.ndarray], t: list[np.ndarray], times: np.ndarray,
                  seconds: float) -> np.ndarray:
    """Per keyframe, the camera's displacement over ``seconds`` centred on its time, as
    (w, v) in its own frame (a point X of the camera frame moves by w x X + v), from the
    velocity of a constant-velocity model through its neighbouring keyframes (K, 6)."""
    K = len(R)
    out = np.zeros((K, 6))
    if K < 2 or seconds <= 0:
        return out
    for k in range(K):
        rates = []
        for j in (k - 1, k + 1):
            if not 0 <= j < K or times[j] == times[k]:
                continue
            # Camera k's frame to j's: X_j = R_kj X_k + t_kj = X_k + phi x X_k + t_kj (small).
            R_kj = R[j] @ R[k].T
            phi = cv2.Rodrigues(R_kj)[0][:, 0]
            t_kj = t[j] - R_kj @ t[k]
            rates.append(np.r_[phi, t_kj] / (times[j] - times[k]))
        if rates:
            out[k] = np.mean(rates, 0) * seconds
    return out


def _level_intrinsics(x: np.ndarray, s: float) -> np.ndarray:
    """(f, cx, cy, k1, k2) at a pyramid level ``s`` times smaller.

    cv2.pyrDown centres coarse pixel i on fine pixel s*i, so pixel coordinates simply scale
    by 1/s (not (u + 0.5)/s - 0.5, which would shift every sample by half a pixel less one
    coarse half pixel and bias the focal length at the coarse levels).
    """
    return np.array([x[0] / s, x[1] / s, x[2] / s, x[3], x[4]])


def _full_intrinsics(x: np.ndarray, s: float) -> np.ndarray:
    return np.array([x[0] * s, x[1] * s, x[2] * s, x[3], x[4]])


def _sample(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    if len(uv) == 0:
        return np.zeros(0, np.float32)
    m = uv.astype(np.float32)
    return cv2.remap(img, m[None, :, 0], m[None, :, 1], cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)[0]


def _processing_grey(image: np.ndarray, max_width: int | None) -> np.ndarray:
    """A keyframe as float32 grey, at most ``max_width`` wide (area filter, aspect kept)."""

    grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
    w, h = processing_size(grey.shape[1], grey.shape[0], max_width)
    if (w, h) != (grey.shape[1], grey.shape[0]):
        grey = cv2.resize(grey, (w, h), interpolation=cv2.INTER_AREA)
    return grey.astype(np.float32)


def _at_size(intrinsics: Intrinsics, width: int, height: int) -> Intrinsics:
    """``intrinsics`` for images ``width``×``height`` (the same camera at another resolution:
    pixel-centre convention, as an area-filter resize samples)."""
    if (width, height) == (intrinsics.width, intrinsics.height):
        return intrinsics
    if abs(width / height - intrinsics.width / intrinsics.height) > 0.01:
        raise FacecapError(f"keyframes are {width}x{height} but the camera is "
                           f"{intrinsics.width}x{intrinsics.height} (aspect ratios differ)")
    return intrinsics.scaled(width, height)


def _points_from_sparse(points, hosts, R, t, intrinsics: Intrinsics, shape):
    """The initial reconstruction's points, each hosted in its given keyframe at its depth
    (no search: the geometric solution already knows where they are)."""
    h_img, w_img = shape
    margin = 8
    host, uv, rho = [], [], []
    for k in range(len(R)):
        sel = np.flatnonzero(hosts == k)
        if len(sel) == 0:
            continue
        p, z = project(points[sel], R[k], t[k], intrinsics)
        p = np.round(p)  # pattern pixels on the host's pixel grid (no host interpolation)
        ok = ((z > 0) & (p[:, 0] >= margin) & (p[:, 0] < w_img - margin)
              & (p[:, 1] >= margin) & (p[:, 1] < h_img - margin))
        if not ok.any():
            continue
        # Depth along the host ray of the rounded pixel: the camera-frame z of the point.
        host.append(np.full(ok.sum(), k))
        uv.append(p[ok])
        rho.append(1.0 / z[ok])
    if not host:
        return np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0)
    return (np.concatenate(host).astype(np.int64), np.concatenate(uv).astype(np.float64),
            np.concatenate(rho))


def _points_by_search(greys, pyr, R, t, intr, sparse_points, config: PBAConfig, log):
    """Strong-gradient pixels with inverse depths from an epipolar search."""
    K = len(greys)
    uvs = [_select_points(greys[k], config.cell, config.min_gradient, margin=8) for k in range(K)]
    host = np.concatenate([np.full(len(u), k) for k, u in enumerate(uvs)]).astype(np.int64)
    uv0 = np.concatenate(uvs)
    depths = np.concatenate([(sparse_points @ R[k].T + t[k])[:, 2] for k in range(K)])
    depths = depths[depths > 0]
    if len(host) == 0 or len(depths) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0)
    rho_lo = 1.0 / (np.percentile(depths, 99) * 1.5)
    rho_hi = 1.0 / (np.percentile(depths, 1) * 0.7)
    ss = 2.0 ** config.search_level
    uv_s = uv0 / ss
    vals_s = np.empty((len(host), 8))
    for k in range(K):
        sel = host == k
        for q, d in enumerate(PATTERN):
            vals_s[sel, q] = _sample(pyr[k][config.search_level], uv_s[sel] + d)
    R_rel, t_rel = _relative(R, t)
    rho = np.empty(len(host))
    quality = np.empty(len(host))
    _search_depth(host, uv_s, vals_s, rho_lo, rho_hi, config.search_samples, 2,
                  nb.typed.List([pyr[k][config.search_level] for k in range(K)]), R_rel, t_rel,
                  _level_intrinsics(intr, ss), rho, quality)
    keep = quality >= config.min_search_quality
    log.append(f"{keep.sum()} of {len(keep)} points kept after the depth search")
    return host[keep], uv0[keep], rho[keep]


@dataclass
class _State:
    """The unknowns of the solve, and what the models fitted to them chose."""

    R: list[np.ndarray]
    t: list[np.ndarray]
    affine: np.ndarray  # (K, 2) brightness a, b per keyframe
    intr: np.ndarray  # f, cx, cy, k1, k2 at the processing resolution
    rho: np.ndarray  # the photometric points' inverse depths in their hosts
    X: np.ndarray  # the tracked points
    exposure_s: float
    readout_s: float
    centres0: np.ndarray  # where the centre prior holds the camera centres
    w_centre: float = 0.0  # the centre prior's weight at the current level


class _Problem:
    """What the solve is over, fixed while the cameras move: the keyframes' pyramids, the
    photometric points and the keyframes each is compared in (the parameter layout: the
    intrinsics, then pose and brightness per keyframe after the first), the tracked points'
    observations, the priors (principal point, camera centres, scale) and the video's timing
    (motion blur, rolling shutter)."""

    def __init__(self, images, intrinsics: Intrinsics, R, t, sparse_points, config: PBAConfig,
                 progress, sparse_hosts, centre_prior, times, frame_interval_s, tracks):
        self.config, self.progress, self.log = config, progress, []
        greys = [_processing_grey(im, config.max_width) for im in images]
        self.K = K = len(greys)
        self.shape = greys[0].shape
        self.full = intrinsics
        self.intrinsics = _at_size(intrinsics, greys[0].shape[1], greys[0].shape[0])
        self.pyr = [_pyramid(g, config.pyramid_levels) for g in greys]
        R = [np.asarray(r, float) for r in R]
        t = [np.asarray(x, float) for x in t]
        self.baseline_ref = np.linalg.norm(R[1].T @ t[1] - R[0].T @ t[0])
        centres0 = np.array([-r.T @ x for r, x in zip(R, t)])
        spread = np.linalg.norm(centres0 - centres0.mean(0), axis=1).mean()
        # One standard deviation of a centre costs as much as one residual at the Huber
        # threshold.
        self.w_centre_unit = (1 / (config.centre_prior_pct / 100 * spread) ** 2
                              if centre_prior and config.centre_prior_pct > 0 else 0.0)
        self._principal_point_prior(tracks, R, t)
        intr = np.array([self.intrinsics.fx, self.intrinsics.cx, self.intrinsics.cy,
                         self.intrinsics.k1, self.intrinsics.k2])
        if config.points_from_sparse and sparse_hosts is not None:
            self.host, self.uv0, rho = _points_from_sparse(sparse_points, sparse_hosts, R, t,
                                                           self.intrinsics, self.shape)
            self.log.append(f"{len(self.host)} points from the initial reconstruction")
        else:
            self.host, self.uv0, rho = _points_by_search(greys, self.pyr, R, t, intr,
                                                         sparse_points, config, self.log)
        if len(self.host) == 0:
            raise FacecapError("photometric bundle adjustment found no usable points: the "
                               "keyframes have no texture")
        tgt = [[k for k in range(max(0, h - config.neighbours),
                                 min(K, h + config.neighbours + 1)) if k != h]
               for h in self.host]
        self.target_start = np.concatenate([[0], np.cumsum([len(x) for x in tgt])]
                                           ).astype(np.int64)
        self.targets = np.fromiter((k for x in tgt for k in x), np.int64)
        self.n_cam = N_INTR + N_FRAME * (K - 1)
        self.max_local = N_INTR + N_FRAME * (2 * config.neighbours + 1)
        self.video = times is not None and bool(frame_interval_s)
        self.blur = config.motion_blur and self.video
        self.shutter = config.rolling_shutter and self.video
        self.key_times = np.asarray(times if times is not None else np.zeros(K), float)
        self.frame_interval_s = frame_interval_s
        X = self._tracks(tracks)
        # Without the tracks the intrinsics stay put: the photometric residuals over
        # neighbouring keyframes leave the principal point free against a tilt of every
        # camera.
        self.free_intrinsics = config.refine_intrinsics and len(X) > 0
        self.start = _State(
            R, t, np.zeros((K, 2)), intr, rho, X,
            exposure_s=((config.exposure_fraction or 0.0) * (frame_interval_s or 0.0)
                        if self.blur else 0.0),
            readout_s=(config.readout_s or 0.0) if self.shutter else 0.0, centres0=centres0)

    def _principal_point_prior(self, tracks, R, t) -> None:
        """The principal point's prior: a deviation of one standard deviation (processing
        pixels) costs as much as one tracked observation off by the tracks' noise, so that
        it weighs as a prior should against the data whatever their noise (exact tracks:
        nothing)."""
        config, intrinsics = self.config, self.intrinsics
        self.pp0 = np.array([(intrinsics.width - 1) / 2, (intrinsics.height - 1) / 2])
        pp_sigma = config.principal_point_prior_pct / 100 * np.array([intrinsics.width,
                                                                      intrinsics.height])
        self.w_pp = np.zeros(2)
        if config.hold_principal_point:
            self.pp0 = np.array([intrinsics.cx, intrinsics.cy])
            self.w_pp = np.full(2, 1e12)
            self.log.append("principal point held at the start's")
        elif config.principal_point_prior_pct > 0 and tracks is not None and len(tracks[0]):
            noise = _track_noise_px(tracks, R, t, intrinsics, self.full)
            self.w_pp = config.track_weight ** 2 * noise ** 2 / pp_sigma ** 2
            self.log.append(f"principal point prior: ±{config.principal_point_prior_pct:g} % "
                            f"of the image, the tracks' noise {noise:.2f} px")

    def _tracks(self, tracks) -> np.ndarray:
        """The tracked points (the geometric solution's, with their observations) in the
        same solve: long tracks pin what the photometric residuals over neighbouring
        keyframes leave loose (the principal point against a tilt of every camera, the chain
        of centres). Sets their observations; returns the points."""
        if tracks is None or self.config.track_weight <= 0:
            self.obs_start = np.zeros(1, np.int64)
            self.obs_frame = np.zeros(0, np.int64)
            self.obs_xy = np.zeros((0, 2))
            self.track_w = 0.0
            return np.zeros((0, 3))
        X = np.asarray(tracks[0], float).copy()
        obs = np.asarray(tracks[1], float)
        obs = obs[np.argsort(obs[:, 0], kind="stable")]
        pid = obs[:, 0].astype(np.int64)
        self.obs_start = np.searchsorted(pid, np.arange(len(X) + 1)).astype(np.int64)
        self.obs_frame = obs[:, 1].astype(np.int64)
        scale_px = np.array([self.intrinsics.width / self.full.width,
                             self.intrinsics.height / self.full.height])
        self.obs_xy = (obs[:, 2:4] + 0.5) * scale_px - 0.5
        self.track_w = self.config.track_weight ** 2
        return X

    def velocity(self, R, t) -> np.ndarray:
        return camera_motion(R, t, self.key_times, 1.0) if self.video else np.zeros((self.K, 6))

    def prior_cost(self, st: _State, R, t, intr) -> float:
        cost = float(np.sum(self.w_pp * (intr[1:3] - self.pp0) ** 2))
        if st.w_centre == 0:
            return cost
        c = np.array([-r.T @ x for r, x in zip(R, t)])
        return cost + st.w_centre * float(np.sum((c - st.centres0) ** 2))

    def say(self, line: str) -> None:
        self.log.append(line)
        if self.progress:
            print(line)


class _Level:
    """One level of the image pyramid: its images, gradients and the points' pattern
    weights; the residuals and normal equations at a state, the robust scale, the models'
    choice (exposure, readout) and the Levenberg-Marquardt iterations."""

    def __init__(self, problem: _Problem, level: int):
        p = self.p = problem
        self.level, self.s = level, 2.0 ** level
        self.frozen_velocity = None
        self.huber = self.max_residual = 1e9
        self.imgs, self.gxs, self.gys = nb.typed.List(), nb.typed.List(), nb.typed.List()
        for k in range(p.K):
            img = p.pyr[k][level]
            gx, gy = _gradients(img)
            self.imgs.append(img)
            self.gxs.append(gx)
            self.gys.append(gy)
        self.uv = p.uv0 / self.s
        self.host_weights = np.empty((len(p.host), 8))
        c2 = p.config.gradient_weight ** 2
        for k in range(p.K):
            sel = p.host == k
            for q, d in enumerate(PATTERN):
                # DSO's weight from the host's gradient: fixed while the poses move, so the
                # cost cannot fall by sliding residuals onto strong edges.
                g2 = (_sample(self.gxs[k], self.uv[sel] + d) ** 2
                      + _sample(self.gys[k], self.uv[sel] + d) ** 2)
                self.host_weights[sel, q] = c2 / (c2 + g2)

    def evaluate(self, st: _State, R, t, affine, intr, rho, X, with_cameras: bool,
                 with_tracks: bool = True, residuals=None, jacobians: bool = True) -> _Normal:
        """The cost and normal equations at cameras ``R, t, affine, intr`` and points
        ``rho, X`` (the exposure and readout of ``st``); without ``jacobians`` only the
        cost: the photometric residuals' Jacobians are skipped (a step's test, a model's
        choice)."""
        p = self.p
        R_rel, t_rel = _relative(R, t)
        e = _Normal(p.n_cam, len(p.host), p.max_local, len(X), len(p.obs_frame))
        intr_l = _level_intrinsics(intr, self.s)
        vel = self.frozen_velocity if self.frozen_velocity is not None else p.velocity(R, t)
        rows = self.imgs[0].shape[0]
        _accumulate_in_chunks(p.host, self.uv, rho, p.target_start, p.targets, self.imgs,
                              self.gxs, self.gys, self.host_weights,
                              vel * (st.exposure_s / 2), p.config.blur_samples, vel,
                              st.readout_s, rows, R_rel, t_rel, affine, intr_l, self.huber,
                              self.max_residual, with_cameras,
                              e.H, e.b, e.Hpp, e.bpp, e.Hcp, e.idx, e.stats,
                              residuals if residuals is not None else np.zeros(0),
                              jacobians=jacobians)
        if with_tracks and len(X):
            _accumulate_tracks(X, p.obs_start, p.obs_frame, p.obs_xy / self.s, np.asarray(R),
                               np.asarray(t), intr_l, p.track_w * self.s * self.s,
                               p.config.track_huber_px / self.s, vel, st.readout_s, rows,
                               with_cameras, e.H, e.b, e.Hpp3, e.bpp3, e.Hpc, e.stats)
        e.cost, e.count = float(e.stats[0]), int(e.stats[1])
        return e

    def at(self, st: _State, with_cameras: bool = False, **kwargs) -> _Normal:
        """:meth:`evaluate` at the state."""
        return self.evaluate(st, st.R, st.t, st.affine, st.intr, st.rho, st.X, with_cameras,
                             **kwargs)

    def robust_scale(self, st: _State) -> float:
        """1.4826 x the median residual magnitude at the current cameras (grey levels): the
        residuals' standard deviation, whatever the outliers."""
        buf = np.empty(8 * len(self.p.targets))
        e = self.at(st, with_tracks=False, residuals=buf, jacobians=False)
        n = int(e.stats[2])
        # At least the noise of 8-bit quantisation (1/sqrt(12) grey levels): exact renders
        # would otherwise make every residual an outlier.
        return max(1.4826 * float(np.median(buf[:n])) if n else 1.0, 12 ** -0.5)

    def set_robust_loss(self, st: _State) -> float:
        """The robust loss in units of the residuals' own spread (noise, codec, blur differ
        from capture to capture): Huber, and the outlier bound of a pattern in one target.
        Returns the spread."""
        sigma = self.robust_scale(st)
        self.huber = self.p.config.huber * sigma
        self.max_residual = self.p.config.max_residual * sigma
        return sigma

    def choose(self, st: _State, candidates, field: str, scale: float | None, name: str,
               unit: str) -> float:
        """Sets ``st.<field>`` to the candidate (times ``scale``) whose model makes the
        residuals smallest."""
        costs = []
        for value in candidates:
            setattr(st, field, value if scale is None else value * scale)
            e = self.at(st, with_tracks=False, jacobians=False)
            costs.append(e.cost / max(e.count, 1))
        best = candidates[int(np.argmin(costs))]
        setattr(st, field, best if scale is None else best * scale)
        self.p.say(f"{name} " + ", ".join(f"{v:g}: rms {np.sqrt(c):.3f}"
                                          for v, c in zip(candidates, costs))
                   + f"; chose {best:g} {unit} at level {self.level}")
        return best

    def readout_from_tracks(self, st: _State) -> None:
        """The readout from the tracks, each candidate after its own adjustment of the
        cameras: the start absorbed the shutter's distortion into its cameras (a tilt, a
        principal point), so at the start every readout but 0 looks worse. The chosen
        readout's adjustment is the start: SfM and the geometric solution model no rolling
        shutter. The track cost's unit is one observation (track_w in the joint solve)."""
        p, config = self.p, self.p.config
        pp_prior = (p.pp0, p.w_pp / max(config.track_weight ** 2, 1e-12))
        adjusted = [_adjust_to_tracks(
            st.R, st.t, st.intr, st.X, p.obs_start, p.obs_frame, p.obs_xy, p.shape[0],
            p.velocity, value, config.track_huber_px, 15, p.free_intrinsics, pp_prior)
            for value in config.readout_candidates]
        costs = [a[0] for a in adjusted]
        best = int(np.argmin(costs))
        st.readout_s = config.readout_candidates[best]
        if st.readout_s > 0:
            st.R, st.t, st.intr, st.X = _adjust_to_tracks(
                *adjusted[best][1:], p.obs_start, p.obs_frame, p.obs_xy,
                p.shape[0], p.velocity, st.readout_s, config.track_huber_px, 35,
                p.free_intrinsics, pp_prior)[1:]
            st.centres0 = np.array([-r.T @ x for r, x in zip(st.R, st.t)])
        p.say("readout " + ", ".join(f"{v:g}: cost {c:.4g}"
                                     for v, c in zip(config.readout_candidates, costs))
              + f"; chose {st.readout_s:g} s from the tracks")

    def prepare(self, st: _State) -> None:
        """The level's robust loss; the exposure and the readout where they are not given.
        They are rarely known for a video: the candidates whose model makes the residuals
        smallest (an over- or under-estimate leaves the two sides of every residual
        differently blurred, or their rows at the wrong times). Again at each level:
        misaligned cameras favour a longer exposure (blurring both sides hides
        misalignment), the finer level starts from better ones."""
        p, config = self.p, self.p.config
        sigma = self.set_robust_loss(st)
        choose_readout = p.shutter and config.readout_s is None
        choose_exposure = p.blur and config.exposure_fraction is None
        if choose_readout and self.level == config.pyramid_levels - 1:
            if len(st.X):
                self.readout_from_tracks(st)
            else:
                self.choose(st, config.readout_candidates, "readout_s", None, "readout", "s")
        if choose_exposure:
            self.choose(st, config.exposure_candidates, "exposure_s", p.frame_interval_s,
                        "exposure", "of a frame")
        if choose_readout or choose_exposure:
            sigma = self.set_robust_loss(st)
        p.log.append(f"level {self.level}: residual scale {sigma:.2f} grey levels")
        if p.w_centre_unit:
            st.w_centre = self.huber ** 2 * p.w_centre_unit

    def normal_step(self, st: _State, e: _Normal, lam: float):
        """The Levenberg-Marquardt step of the cameras, intrinsics and points from the
        normal equations ``e`` with the gauge and the priors; returns the moved
        ``(R, t, affine, intr, rho step, X)``."""
        p, config, s = self.p, self.p.config, self.s
        H, b = e.H, e.b
        _hold_baseline(H, b, st.R, st.t, p.baseline_ref, config.scale_prior)
        if st.w_centre > 0:
            # Centre c = -R^T t moves by -R^T v under the increment (v, w).
            for k in range(1, p.K):
                sl = slice(N_INTR + N_FRAME * (k - 1), N_INTR + N_FRAME * (k - 1) + 3)
                c = -st.R[k].T @ st.t[k]
                H[sl, sl] += st.w_centre * np.eye(3)
                b[sl] += -st.w_centre * st.R[k] @ (c - st.centres0[k])
        if not p.free_intrinsics or self.level > config.intrinsics_level:
            H[:N_INTR, :N_INTR] += 1e12 * np.eye(N_INTR)
        else:
            # The prior in the level's pixels (cx_l = cx / s): cost w s² (cx_l - c0 / s)².
            H[1:3, 1:3] += np.diag(p.w_pp * s * s)
            b[1:3] += p.w_pp * s * (st.intr[1:3] - p.pp0)
        dc = -np.linalg.solve(H + lam * np.diag(np.diag(H) + 1e-9), b)
        dcl = np.where(e.idx >= 0, dc[np.maximum(e.idx, 0)], 0.0)
        drho = -(e.bpp + np.sum(e.Hcp * dcl, 1)) / (e.Hpp * (1 + lam) + 1e-12)
        R2, t2, aff2 = _update_frames(st.R, st.t, st.affine, dc[N_INTR:])
        intr2 = _full_intrinsics(_level_intrinsics(st.intr, s) + dc[:N_INTR], s)
        X2 = st.X + _track_steps(e, dc, p.obs_start, p.obs_frame, lam)
        return R2, t2, aff2, intr2, drho, X2

    def iterate(self, st: _State) -> float | None:
        """The level's Levenberg-Marquardt iterations (inverse depths alone for the first
        ``depth_only_iterations``, then jointly with the cameras); returns the rms of the
        first residuals (None without iterations)."""
        p, config = self.p, self.p.config
        lam, rms_first = config.initial_lambda, None
        for it in range(config.iterations):
            # The camera velocities (blur, rolling shutter) are those of the iteration's
            # start for its step and the step's test: the Jacobians hold them fixed.
            self.frozen_velocity = p.velocity(st.R, st.t)
            cams = it >= config.depth_only_iterations
            e = self.at(st, cams)
            cost, count = e.cost, e.count
            cost_prior = p.prior_cost(st, st.R, st.t, st.intr)
            if rms_first is None:
                rms_first = np.sqrt(cost / max(count, 1))
            if cams:
                R2, t2, aff2, intr2, drho, X2 = self.normal_step(st, e, lam)
            else:
                drho = -e.bpp / (e.Hpp * (1 + lam) + 1e-12)
                R2, t2, aff2, intr2, X2 = st.R, st.t, st.affine, st.intr, st.X
            rho2 = np.clip(st.rho + drho, st.rho * 0.5, st.rho * 2.0)
            e2 = self.evaluate(st, R2, t2, aff2, intr2, rho2, X2, False, jacobians=False)
            accept = e2.cost + p.prior_cost(st, R2, t2, intr2) <= cost + cost_prior
            if accept:
                st.R, st.t, st.affine, st.intr, st.rho, st.X = R2, t2, aff2, intr2, rho2, X2
                lam = max(lam / 4, 1e-7)
            else:
                lam *= 4
            p.say(f"level {self.level} it {it:2d} {'joint' if cams else 'depth'}: rms "
                  f"{np.sqrt(cost / max(count, 1)):.3f} -> "
                  f"{np.sqrt(e2.cost / max(e2.count, 1)):.3f}, {e2.count} residuals, "
                  f"{'accepted' if accept else 'rejected'}, f {st.intr[0]:.2f}, "
                  f"lambda {lam:.1e}, |drho|/rho {np.median(np.abs(drho) / st.rho):.1e}")
        return rms_first


def photometric_bundle_adjustment(images: list[np.ndarray], intrinsics: Intrinsics,
                                  R: list[np.ndarray], t: list[np.ndarray],
                                  sparse_points: np.ndarray, config: PBAConfig | None = None,
                                  progress: bool = False,
                                  sparse_hosts: np.ndarray | None = None,
                                  centre_prior: bool = False,
                                  times: list[float] | None = None,
                                  frame_interval_s: float | None = None,
                                  tracks: tuple[np.ndarray, np.ndarray] | None = None
                                  ) -> PBAResult:
    """Refine keyframe poses, intrinsics and distortion photometrically.

    ``images``: the keyframes (grey or RGB) in video order, at the intrinsics' resolution or
    any other of the same aspect ratio; those wider than ``config.max_width`` are adjusted at
    that width, and the returned intrinsics are at the resolution of ``intrinsics``;
    ``R``, ``t``: their initial world-to-camera poses; ``sparse_points``: 3D points of the
    initial reconstruction. With ``sparse_hosts`` (a host keyframe per sparse point, -1 for
    none) and ``config.points_from_sparse``, the photometric points are those sparse points,
    hosted there at their initial depths; otherwise strong-gradient pixels get their initial
    inverse depth by a search along the epipolar lines within the sparse points' depth range.
    With ``centre_prior`` and ``config.centre_prior_pct`` > 0 the camera centres are held
    near their initial positions (that % of the mean camera distance from their centroid).

    ``tracks``: world points and their observations (rows: point, keyframe, x, y in pixels of
    ``intrinsics``), whose reprojection errors join the photometric residuals in one solve
    (``config.track_weight``); only with them are the intrinsics refined.
    ``times`` (seconds, one per keyframe) and ``frame_interval_s`` (1 / fps) make it a video:
    motion blur (``config.motion_blur``) and the rolling shutter (``config.rolling_shutter``)
    are modelled from the camera's velocity through the neighbouring keyframes.
    """
    config = config or PBAConfig()
    start = time.perf_counter()
    problem = _Problem(images, intrinsics, R, t, sparse_points, config, progress,
                       sparse_hosts, centre_prior, times, frame_interval_s, tracks)
    st = problem.start
    rms_first = None
    for level in reversed(range(config.pyramid_levels)):
        finest = _Level(problem, level)
        finest.prepare(st)
        first = finest.iterate(st)
        rms_first = first if rms_first is None else rms_first
    finest.frozen_velocity = None
    e = finest.at(st, jacobians=False)
    full, processed = problem.full, problem.intrinsics
    out = Intrinsics(processed.width, processed.height, float(st.intr[0]), float(st.intr[0]),
                     float(st.intr[1]), float(st.intr[2]), float(st.intr[3]),
                     float(st.intr[4]))
    if (out.width, out.height) != (full.width, full.height):
        out = out.scaled(full.width, full.height)
    return PBAResult(out, st.R, st.t, st.affine, len(problem.host), e.count, float(rms_first),
                     float(np.sqrt(e.cost / max(e.count, 1))),
                     time.perf_counter() - start, problem.log,
                     st.exposure_s / frame_interval_s if problem.blur else None,
                     st.readout_s if problem.shutter else None)
