"""Photometric bundle adjustment (PBA) of keyframe poses, intrinsics and radial distortion.

One module of ~650 lines on purpose: the residual, its derivatives, the numba accumulation
and the Schur-complement solve share one parameter layout and one set of kernels; split,
they would need an interface as wide as the algorithm.

The method of DSO (Engel et al.), run as a batch over all keyframes:

* **Points**: the initial reconstruction's sparse points, each hosted in the middle keyframe
  of its track at its depth (default), or in every keyframe the strongest-gradient pixel of
  each ``cell``×``cell`` block with an epipolar depth search; an 8-pixel pattern around each;
  one unknown per point, its inverse depth along the host ray.
* **Residuals**: each pattern pixel is cast along its host ray at the point's inverse depth,
  projected into nearby keyframes (the targets) and compared there:
  ``r = I_t(u_t) - b_t - exp(a_t - a_h) (I_h(u_h) - b_h)``, with a per-keyframe affine
  brightness (a, b) for exposure changes, a Huber weight and DSO's gradient-dependent weight.
* **Unknowns**: every keyframe's pose (6) and brightness (2), one shared camera: focal length,
  principal point and radial distortion k1, k2 (5), and all inverse depths.
* **Solver**: Levenberg–Marquardt with analytic Jacobians. Inverse depths are eliminated by
  the Schur complement (each is a 1×1 block), leaving a small dense system over the camera
  unknowns; coarse to fine over an image pyramid.
* **Gauge**: the first keyframe's pose and brightness are fixed, and the scale by a prior on
  the distance between the first two camera centres. Optionally the camera centres are held
  near the start by a prior, and the intrinsics fixed (see :class:`PBAConfig`).

Distortion is part of the model (rays are undistorted with the current k1, k2), so the
intrinsics' Jacobians pass through the undistortion by the implicit-function theorem.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numba as nb
import numpy as np

from facecap_core.camera import Intrinsics, rotation_matrix
from facecap_core.config import PBAConfig
from facecap_core.errors import FacecapError

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


@nb.njit(cache=True)
def _accumulate(host, uv, rho, target_start, targets, images, grad_x, grad_y, host_values,
                host_weights, R_rel, t_rel, affine, intr, huber, max_residual, with_cameras,
                H, b, Hpp, bpp, Hcp_store, idx_store, stats):
    """Residuals, weights and Jacobians of every point; Schur-reduced normal equations.

    Camera unknowns are [intrinsics (5), keyframes 1..K-1 (8 each)]; keyframe 0 is fixed.
    Per point, its camera columns (intrinsics, host, targets) are gathered locally, and
    H_cc - h_cp h_cp^T / h_pp is scattered into H when ``with_cameras``. Residuals larger
    than ``max_residual`` are dropped (occlusions, specularities).
    """
    f, cx, cy, k1, k2 = intr[0], intr[1], intr[2], intr[3], intr[4]
    max_local = Hcp_store.shape[1]
    cost = 0.0
    count = 0
    dxd = np.zeros((2, N_INTR))
    dxn = np.zeros((2, N_INTR))
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
        for q in range(8):
            uh = uv[p, 0] + PATTERN[q, 0]
            vh = uv[p, 1] + PATTERN[q, 1]
            Ih = host_values[p, q]
            xd = (uh - cx) / f
            yd = (vh - cy) / f
            xn, yn, rn2, g00, g01, g11 = _undistort(xd, yd, k1, k2)
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
            Xh0 = xn / rho[p]
            Xh1 = yn / rho[p]
            Xh2 = 1.0 / rho[p]
            for k in range(t0, t1):
                tg = targets[k]
                slot = 1 + k - t0
                Rr = R_rel[h, tg]
                tr = t_rel[h, tg]
                X0 = Rr[0, 0] * Xh0 + Rr[0, 1] * Xh1 + Rr[0, 2] * Xh2 + tr[0]
                X1 = Rr[1, 0] * Xh0 + Rr[1, 1] * Xh1 + Rr[1, 2] * Xh2 + tr[1]
                X2 = Rr[2, 0] * Xh0 + Rr[2, 1] * Xh1 + Rr[2, 2] * Xh2 + tr[2]
                if X2 <= 1e-9:
                    continue
                yx = X0 / X2
                yy = X1 / X2
                s2 = yx * yx + yy * yy
                fac = 1 + k1 * s2 + k2 * s2 * s2
                dfac = 2 * k1 + 4 * k2 * s2
                It = _bilinear(images[tg], f * yx * fac + cx, f * yy * fac + cy)
                if np.isnan(It):
                    # Leaving the image costs as much as an outlier, so that no step can
                    # lower the cost by pushing residuals out of view.
                    cost += 2 * huber * max_residual - huber * huber
                    count += 1
                    continue
                gx = _bilinear(grad_x[tg], f * yx * fac + cx, f * yy * fac + cy)
                gy = _bilinear(grad_y[tg], f * yx * fac + cx, f * yy * fac + cy)
                ea = np.exp(affine[tg, 0] - ah)
                r = It - affine[tg, 1] - ea * (Ih - bh)
                ar = abs(r)
                gw = host_weights[p, q]
                if ar > max_residual:
                    cost += gw * (2 * huber * max_residual - huber * huber)  # truncated
                    count += 1
                    continue
                if ar < huber:
                    w = gw
                    cost += gw * r * r
                else:
                    w = gw * huber / ar
                    cost += gw * (2 * huber * ar - huber * huber)
                count += 1
                # g^T du/dX_t, with du/dy = f (fac I + dfac y y^T) and y = X_t[:2] / X_t[2]
                a0 = f * (gx * (fac + dfac * yx * yx) + gy * dfac * yx * yy)
                a1 = f * (gx * dfac * yx * yy + gy * (fac + dfac * yy * yy))
                dX0 = a0 / X2
                dX1 = a1 / X2
                dX2 = -(a0 * X0 + a1 * X1) / (X2 * X2)
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
                    for c1 in range(n_loc):
                        if J[c1] == 0.0:
                            continue
                        wj = w * J[c1]
                        bc[c1] += wj * r
                        hcp[c1] += wj * jp
                        for c2 in range(c1, n_loc):
                            Hcc[c1, c2] += wj * J[c2]
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
    K = len(R)
    R_rel = np.empty((K, K, 3, 3))
    t_rel = np.empty((K, K, 3))
    for h in range(K):
        for k in range(K):
            R_rel[h, k] = R[k] @ R[h].T
            t_rel[h, k] = t[k] - R_rel[h, k] @ t[h]
    return R_rel, t_rel


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
    from facecap_core.video import processing_size

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
    from facecap_core.camera import project

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


def photometric_bundle_adjustment(images: list[np.ndarray], intrinsics: Intrinsics,
                                  R: list[np.ndarray], t: list[np.ndarray],
                                  sparse_points: np.ndarray, config: PBAConfig | None = None,
                                  progress: bool = False,
                                  sparse_hosts: np.ndarray | None = None,
                                  centre_prior: bool = False) -> PBAResult:
    """Refine keyframe poses, intrinsics and distortion photometrically.

    ``images``: the keyframes (grey or RGB) in video order, at the intrinsics' resolution or
    any other of the same aspect ratio; those wider than ``config.max_width`` are adjusted at
    that width, and the returned intrinsics are at the resolution of ``intrinsics``;
    ``R``, ``t``: their initial world-to-camera poses; ``sparse_points``: 3D points of the
    initial reconstruction. With ``sparse_hosts`` (a host keyframe per sparse point, -1 for
    none) and ``config.points_from_sparse``, the points are those sparse points, hosted there
    at their initial depths; otherwise strong-gradient pixels get their initial inverse depth
    by a search along the epipolar lines within the sparse points' depth range. With
    ``centre_prior`` the camera centres are held near their initial positions with a
    standard deviation of ``config.centre_prior_pct`` of the mean camera distance from their
    centroid: the photometric cost pins rotations and intrinsics well but lets the chain of
    centres bend, where a geometric solution with long tracks is already good.
    """
    config = config or PBAConfig()
    start = time.perf_counter()
    greys = [_processing_grey(im, config.max_width) for im in images]
    K = len(greys)
    full = intrinsics
    intrinsics = _at_size(full, greys[0].shape[1], greys[0].shape[0])
    levels = config.pyramid_levels
    pyr = [_pyramid(g, levels) for g in greys]
    R = [np.asarray(r, float) for r in R]
    t = [np.asarray(x, float) for x in t]
    affine = np.zeros((K, 2))
    intr = np.array([intrinsics.fx, intrinsics.cx, intrinsics.cy, intrinsics.k1, intrinsics.k2])
    baseline_ref = np.linalg.norm(R[1].T @ t[1] - R[0].T @ t[0])
    log: list[str] = []
    centres0 = np.array([-r.T @ x for r, x in zip(R, t)])
    spread = np.linalg.norm(centres0 - centres0.mean(0), axis=1).mean()
    # One standard deviation of a centre costs as much as one residual at the Huber threshold.
    w_centre = (config.huber ** 2 / (config.centre_prior_pct / 100 * spread) ** 2
                if centre_prior and config.centre_prior_pct > 0 else 0.0)

    def prior_cost(R_, t_):
        if w_centre == 0:
            return 0.0
        c = np.array([-r.T @ x for r, x in zip(R_, t_)])
        return w_centre * float(np.sum((c - centres0) ** 2))

    if config.points_from_sparse and sparse_hosts is not None:
        host, uv0, rho = _points_from_sparse(sparse_points, sparse_hosts, R, t, intrinsics,
                                             greys[0].shape)
        log.append(f"{len(host)} points from the initial reconstruction")
    else:
        host, uv0, rho = _points_by_search(greys, pyr, R, t, intr, sparse_points, config, log)
    if len(host) == 0:
        raise FacecapError("photometric bundle adjustment found no usable points: the "
                           "keyframes have no texture")
    tgt = [[k for k in range(max(0, h - config.neighbours), min(K, h + config.neighbours + 1))
            if k != h] for h in host]
    target_start = np.concatenate([[0], np.cumsum([len(x) for x in tgt])]).astype(np.int64)
    targets = np.fromiter((k for x in tgt for k in x), np.int64)
    n_cam = N_INTR + N_FRAME * (K - 1)
    max_local = N_INTR + N_FRAME * (2 * config.neighbours + 1)

    rms_first = None
    for level in reversed(range(levels)):
        s = 2.0 ** level
        imgs, gxs, gys = nb.typed.List(), nb.typed.List(), nb.typed.List()
        for k in range(K):
            img = pyr[k][level]
            gx, gy = _gradients(img)
            imgs.append(img)
            gxs.append(gx)
            gys.append(gy)
        uv_l = uv0 / s
        host_values = np.empty((len(host), 8))
        host_weights = np.empty((len(host), 8))
        c2 = config.gradient_weight ** 2
        for k in range(K):
            sel = host == k
            for q, d in enumerate(PATTERN):
                host_values[sel, q] = _sample(pyr[k][level], uv_l[sel] + d)
                # DSO's weight from the host's gradient: fixed while the poses move, so the
                # cost cannot fall by sliding residuals onto strong edges.
                g2 = _sample(gxs[k], uv_l[sel] + d) ** 2 + _sample(gys[k], uv_l[sel] + d) ** 2
                host_weights[sel, q] = c2 / (c2 + g2)

        def evaluate(R_, t_, aff_, intr_, rho_, with_cameras):
            R_rel, t_rel = _relative(R_, t_)
            H = np.zeros((n_cam, n_cam))
            b = np.zeros(n_cam)
            Hpp, bpp = np.zeros(len(host)), np.zeros(len(host))
            Hcp = np.zeros((len(host), max_local))
            idx = np.full((len(host), max_local), -1, np.int64)
            stats = np.zeros(2)
            _accumulate(host, uv_l, rho_, target_start, targets, imgs, gxs, gys, host_values,
                        host_weights, R_rel, t_rel, aff_, _level_intrinsics(intr_, s),
                        config.huber, config.max_residual, with_cameras,
                        H, b, Hpp, bpp, Hcp, idx, stats)
            return H, b, Hpp, bpp, Hcp, idx, stats[0], int(stats[1])

        lam = config.initial_lambda
        for it in range(config.iterations):
            cams = it >= config.depth_only_iterations
            H, b, Hpp, bpp, Hcp, idx, cost, count = evaluate(R, t, affine, intr, rho, cams)
            cost_prior = prior_cost(R, t)
            if rms_first is None:
                rms_first = np.sqrt(cost / max(count, 1))
            if cams:
                # Scale gauge: keep the first baseline's length (its centre moves by -R_1^T v_1).
                c0, c1 = -R[0].T @ t[0], -R[1].T @ t[1]
                n = (c1 - c0) / np.linalg.norm(c1 - c0)
                a = -R[1] @ n
                sl = slice(N_INTR, N_INTR + 3)
                H[sl, sl] += config.scale_prior * np.outer(a, a)
                b[sl] += config.scale_prior * a * (np.linalg.norm(c1 - c0) - baseline_ref)
                if w_centre > 0:
                    # Centre c = -R^T t moves by -R^T v under the increment (v, w).
                    for k in range(1, K):
                        sl = slice(N_INTR + N_FRAME * (k - 1), N_INTR + N_FRAME * (k - 1) + 3)
                        c = -R[k].T @ t[k]
                        H[sl, sl] += w_centre * np.eye(3)
                        b[sl] += -w_centre * R[k] @ (c - centres0[k])
                if not config.refine_intrinsics or level > config.intrinsics_level:
                    H[:N_INTR, :N_INTR] += 1e12 * np.eye(N_INTR)
                dc = -np.linalg.solve(H + lam * np.diag(np.diag(H) + 1e-9), b)
                dcl = np.where(idx >= 0, dc[np.maximum(idx, 0)], 0.0)
                drho = -(bpp + np.sum(Hcp * dcl, 1)) / (Hpp * (1 + lam) + 1e-12)
                R2, t2, aff2 = _update_frames(R, t, affine, dc[N_INTR:])
                intr2 = _full_intrinsics(_level_intrinsics(intr, s) + dc[:N_INTR], s)
            else:
                drho = -bpp / (Hpp * (1 + lam) + 1e-12)
                R2, t2, aff2, intr2 = R, t, affine, intr
            rho2 = np.clip(rho + drho, rho * 0.5, rho * 2.0)
            cost2, count2 = evaluate(R2, t2, aff2, intr2, rho2, False)[6:]
            accept = cost2 + prior_cost(R2, t2) <= cost + cost_prior
            if accept:
                R, t, affine, intr, rho = R2, t2, aff2, intr2, rho2
                lam = max(lam / 4, 1e-7)
            else:
                lam *= 4
            log.append(f"level {level} it {it:2d} {'joint' if cams else 'depth'}: rms "
                       f"{np.sqrt(cost / max(count, 1)):.3f} -> "
                       f"{np.sqrt(cost2 / max(count2, 1)):.3f}, {count2} residuals, "
                       f"{'accepted' if accept else 'rejected'}, f {intr[0]:.2f}, "
                       f"lambda {lam:.1e}, |drho|/rho {np.median(np.abs(drho) / rho):.1e}")
            if progress:
                print(log[-1])
    cost, count = evaluate(R, t, affine, intr, rho, False)[6:]
    out = Intrinsics(intrinsics.width, intrinsics.height, float(intr[0]), float(intr[0]),
                     float(intr[1]), float(intr[2]), float(intr[3]), float(intr[4]))
    if (out.width, out.height) != (full.width, full.height):
        out = out.scaled(full.width, full.height)
    return PBAResult(out, R, t, affine, len(host), count, float(rms_first),
                     float(np.sqrt(cost / max(count, 1))),
                     time.perf_counter() - start, log)
