"""The photometric residual kernel of PBA and its pixel model (numba).

:func:`accumulate` sums every point's residuals, robust weights and analytic Jacobians into
the Schur-reduced normal equations over the camera unknowns. The helpers before it are the
camera model it shares with the tracks' kernel and the depth search (bilinear sampling,
radial (un)distortion, projection, motion-blur streaks, rolling-shutter motion), then the
steps of one point: its pattern sampled in its targets, their outlier test, one residual's
Jacobian and the Schur complement's scatter, inlined into it: one compiled loop.
"""

from __future__ import annotations

import numba as nb
import numpy as np

PATTERN = np.array([(0, -2), (-1, -1), (1, -1), (-2, 0), (0, 0), (2, 0), (-1, 1), (0, 2)],
                   np.float64)  # DSO's 8-pixel pattern (dx, dy)
N_FRAME = 8  # pose (v, w) + brightness (a, b) per keyframe
N_INTR = 5  # f, cx, cy, k1, k2


@nb.njit(cache=True, inline="always")
def bilinear(img, x, y):
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
def undistort(xd, yd, k1, k2):
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
def distortion_terms(X0, X1, X2, k1, k2):
    """For a camera point: its normalised coordinates y, |y|², the radial factor and its
    derivative over |y|² (doubled): what the projection and its Jacobian share."""
    yx = X0 / X2
    yy = X1 / X2
    s2 = yx * yx + yy * yy
    return yx, yy, s2, 1 + k1 * s2 + k2 * s2 * s2, 2 * k1 + 4 * k2 * s2


@nb.njit(cache=True, inline="always")
def _pixel(X0, X1, X2, f, cx, cy, k1, k2):
    yx, yy, _, fac, _ = distortion_terms(X0, X1, X2, k1, k2)
    return f * yx * fac + cx, f * yy * fac + cy


@nb.njit(cache=True, inline="always")
def point_gradient(gx, gy, X0, X1, X2, f, yx, yy, fac, dfac):
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
def moved(X0, X1, X2, m, tau):
    """A camera point after the camera moved for ``tau`` seconds at velocity ``m`` (w, v)."""
    return (X0 + tau * (m[1] * X2 - m[2] * X1 + m[3]),
            X1 + tau * (m[2] * X0 - m[0] * X2 + m[4]),
            X2 + tau * (m[0] * X1 - m[1] * X0 + m[5]))


@nb.njit(cache=True, inline="always")
def _streak(img, x, y, dx, dy, n):
    """Mean of ``img`` over ``n`` samples of the segment centred on (x, y) with extent
    (dx, dy): an image seen through a box blur along that segment."""
    if n == 1:
        return bilinear(img, x, y)
    acc = 0.0
    for i in range(n):
        s = i / (n - 1) - 0.5
        v = bilinear(img, x + s * dx, y + s * dy)
        if np.isnan(v):
            return np.nan
        acc += v
    return acc / n


@nb.njit(cache=True, inline="always")
def _samples(dx, dy, most):
    """Samples of a streak: one per pixel of its length, at least one, at most ``most``."""
    return min(most, 1 + int(np.ceil(np.sqrt(dx * dx + dy * dy))))


@nb.njit(cache=True, inline="always")
def _streaks(u, v, rho, h, targets, R_rel, t_rel, motion, intr):
    """Per target of the point at host pixel (u, v) and inverse depth ``rho``: the host's
    streak mapped into the target and the target's own mapped into the host, through the
    warp's Jacobian at the point (pattern pixels at the point's depth) (targets, 4)."""
    f, cx, cy, k1, k2 = intr[0], intr[1], intr[2], intr[3], intr[4]
    streaks = np.zeros((targets.shape[0], 4))
    xc, yc, _, _, _, _ = undistort((u - cx) / f, (v - cy) / f, k1, k2)
    xx, yx_, _, _, _, _ = undistort((u + 1 - cx) / f, (v - cy) / f, k1, k2)
    xy_, yy_, _, _, _, _ = undistort((u - cx) / f, (v + 1 - cy) / f, k1, k2)
    hb0, hb1 = _blur(xc / rho, yc / rho, 1.0 / rho, motion[h], f, cx, cy, k1, k2)
    for i in range(targets.shape[0]):
        tg = targets[i]
        Rr = R_rel[h, tg]
        tr = t_rel[h, tg]
        pts = np.empty((3, 2))
        Xc = np.empty(3)
        ok = True
        for j in range(3):
            ax, ay = (xc, yc) if j == 0 else ((xx, yx_) if j == 1 else (xy_, yy_))
            Y0 = (Rr[0, 0] * ax + Rr[0, 1] * ay + Rr[0, 2]) / rho + tr[0]
            Y1 = (Rr[1, 0] * ax + Rr[1, 1] * ay + Rr[1, 2]) / rho + tr[1]
            Y2 = (Rr[2, 0] * ax + Rr[2, 1] * ay + Rr[2, 2]) / rho + tr[2]
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
        streaks[i, 0] = a00 * hb0 + a01 * hb1
        streaks[i, 1] = a10 * hb0 + a11 * hb1
        if abs(det) > 1e-9:
            streaks[i, 2] = (a11 * tb0 - a01 * tb1) / det
            streaks[i, 3] = (-a10 * tb0 + a00 * tb1) / det
    return streaks


@nb.njit(cache=True, inline="always")
def _sample_pattern(u, v, rho, h, targets, motion, images, grad_x, grad_y, max_samples,
                    velocity, readout, rows, R_rel, t_rel, intr, jacobians):
    """The pattern of the point at host pixel (u, v) and inverse depth ``rho`` sampled in
    every target, each side along the other's streak (:func:`_streaks`): (target, pixel,
    [target's value, host's value, target's gradient x, y]), NaN where either side leaves its
    image; the pattern's points in the host's mid-frame camera (8, 3) and in each target's
    camera at their rows' times (targets, 8, 3; NaN behind it); each pattern pixel's
    undistortion (8, 6: x_n, y_n, r², the distortion's Jacobian G) for the Jacobians."""
    f, cx, cy, k1, k2 = intr[0], intr[1], intr[2], intr[3], intr[4]
    streaks = _streaks(u, v, rho, h, targets, R_rel, t_rel, motion, intr)
    cache = np.full((targets.shape[0], 8, 4), np.nan)
    host_X = np.empty((8, 3))
    target_X = np.full((targets.shape[0], 8, 3), np.nan)
    host_ray = np.empty((8, 6))
    for q in range(8):
        uh = u + PATTERN[q, 0]
        vh = v + PATTERN[q, 1]
        xn, yn, rn2, g00, g01, g11 = undistort((uh - cx) / f, (vh - cy) / f, k1, k2)
        host_ray[q, 0], host_ray[q, 1], host_ray[q, 2] = xn, yn, rn2
        host_ray[q, 3], host_ray[q, 4], host_ray[q, 5] = g00, g01, g11
        Y0, Y1, Y2 = xn / rho, yn / rho, 1.0 / rho
        if readout != 0.0:
            Y0, Y1, Y2 = moved(Y0, Y1, Y2, velocity[h], -readout * (vh / rows - 0.5))
        host_X[q, 0], host_X[q, 1], host_X[q, 2] = Y0, Y1, Y2
        for i in range(targets.shape[0]):
            tg = targets[i]
            Rr = R_rel[h, tg]
            tr = t_rel[h, tg]
            Z0 = Rr[0, 0] * Y0 + Rr[0, 1] * Y1 + Rr[0, 2] * Y2 + tr[0]
            Z1 = Rr[1, 0] * Y0 + Rr[1, 1] * Y1 + Rr[1, 2] * Y2 + tr[1]
            Z2 = Rr[2, 0] * Y0 + Rr[2, 1] * Y1 + Rr[2, 2] * Y2 + tr[2]
            X0, X1, X2 = Z0, Z1, Z2
            if readout != 0.0 and Z2 > 1e-9:
                for _ in range(2):
                    _, vt = _pixel(X0, X1, X2, f, cx, cy, k1, k2)
                    X0, X1, X2 = moved(Z0, Z1, Z2, velocity[tg], readout * (vt / rows - 0.5))
                    if X2 <= 1e-9:
                        break
            if X2 <= 1e-9:
                continue
            target_X[i, q, 0], target_X[i, q, 1], target_X[i, q, 2] = X0, X1, X2
            ut, vt = _pixel(X0, X1, X2, f, cx, cy, k1, k2)
            sx, sy = streaks[i, 0], streaks[i, 1]
            nt = _samples(sx, sy, max_samples)
            It = _streak(images[tg], ut, vt, sx, sy, nt)
            nh = _samples(streaks[i, 2], streaks[i, 3], max_samples)
            Ih = _streak(images[h], uh, vh, streaks[i, 2], streaks[i, 3], nh)
            if np.isnan(It) or np.isnan(Ih):
                continue
            cache[i, q, 0] = It
            cache[i, q, 1] = Ih
            if jacobians:
                cache[i, q, 2] = _streak(grad_x[tg], ut, vt, sx, sy, nt)
                cache[i, q, 3] = _streak(grad_y[tg], ut, vt, sx, sy, nt)
    return cache, host_X, target_X, host_ray


@nb.njit(cache=True, inline="always")
def _inlier_targets(cache, affine, h, targets, max_residual, res_out, stats):
    """Per target: whether the whole pattern was sampled there and its residuals' root mean
    square is at most ``max_residual`` (else the point is occluded there, or a highlight).
    Every residual's magnitude goes to ``res_out`` (when not empty) after the stats[2] there."""
    pair_ok = np.zeros(targets.shape[0], np.bool_)
    for i in range(targets.shape[0]):
        tg = targets[i]
        ea = np.exp(affine[tg, 0] - affine[h, 0])
        ss = 0.0
        inside = True
        for q in range(8):
            if np.isnan(cache[i, q, 0]):
                inside = False
                break
            r = cache[i, q, 0] - affine[tg, 1] - ea * (cache[i, q, 1] - affine[h, 1])
            ss += r * r
            if res_out.shape[0] > 0 and stats[2] < res_out.shape[0]:
                res_out[int(stats[2])] = abs(r)
                stats[2] += 1
        pair_ok[i] = inside and ss <= 8 * max_residual * max_residual
    return pair_ok


@nb.njit(cache=True, inline="always")
def _ray_derivative(uh, vh, ray, intr, dxd, dxn):
    """The derivative of host pixel (uh, vh)'s ray over the intrinsics into ``dxn`` (2, 5),
    from its undistortion ``ray`` (as :func:`_sample_pattern` keeps it): with
    x_d = g(x_n; k) = (u - c) / f, dx_n/dθ = G^-1 (dx_d/dθ - ∂g/∂θ). ``dxd``: scratch."""
    f, cx, cy = intr[0], intr[1], intr[2]
    xd = (uh - cx) / f
    yd = (vh - cy) / f
    xn, yn, rn2 = ray[0], ray[1], ray[2]
    g00, g01, g11 = ray[3], ray[4], ray[5]
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


@nb.njit(cache=True, inline="always")
def _robust(r, gw, huber):
    """Huber's weight of residual ``r`` (pattern weight ``gw``) and its cost."""
    ar = abs(r)
    if ar < huber:
        return gw, gw * r * r
    return gw * huber / ar, gw * (2 * huber * ar - huber * huber)


@nb.njit(cache=True, inline="always")
def _residual_jacobian(J, bt, X0, X1, X2, Xh, Rr, gx, gy, ea, Ih, bh, rho, dxn, intr):
    """One residual's Jacobian over the point's camera columns into ``J`` (intrinsics, host,
    targets; ``bt`` the first of its target's), for the point at X in the target's camera
    (Xh in the host's; Rr: host to target) and the target's gradient (gx, gy) there; returns
    the derivative over the point's inverse depth ``rho``. The Jacobians take the rolling
    shutter's motion as fixed (a velocity times a fraction of the readout: ~1 % of the
    points' own change)."""
    f, k1, k2 = intr[0], intr[3], intr[4]
    yx, yy, s2, fac, dfac = distortion_terms(X0, X1, X2, k1, k2)
    dX0, dX1, dX2 = point_gradient(gx, gy, X0, X1, X2, f, yx, yy, fac, dfac)
    for c in range(J.shape[0]):
        J[c] = 0.0
    # target keyframe: dX_t = v + w x X_t
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
    J[bh_ + 3] = -(Xh[1] * e2 - Xh[2] * e1)
    J[bh_ + 4] = -(Xh[2] * e0 - Xh[0] * e2)
    J[bh_ + 5] = -(Xh[0] * e1 - Xh[1] * e0)
    J[bh_ + 6] = ea * (Ih - bh)
    J[bh_ + 7] = ea
    # intrinsics: through the host ray, and directly in the target projection
    for c in range(N_INTR):
        J[c] = (e0 * dxn[0, c] + e1 * dxn[1, c]) / rho
    J[0] += (gx * yx + gy * yy) * fac
    J[1] += gx
    J[2] += gy
    J[3] += f * (gx * yx + gy * yy) * s2
    J[4] += f * (gx * yx + gy * yy) * s2 * s2
    # inverse depth: dX_h / drho = -X_h / rho
    return -(e0 * Xh[0] + e1 * Xh[1] + e2 * Xh[2]) / rho


@nb.njit(cache=True, inline="always")
def _add_residual(J, w, r, jp, bt, nonzero, Hcc, hcp, bc):
    """A residual's share of its point's local system (weight ``w``, derivative ``jp`` over
    the inverse depth). Only the intrinsics', the host's and this target's columns (from
    ``bt``) can be non-zero: the products of those alone (in the same order) are the sums."""
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


@nb.njit(cache=True, inline="always")
def _scatter_schur(h, targets, Hcc, hcp, bc, hpp, bp, idx, Hcp_row, H, b):
    """A point's local system less its inverse depth, H_cc - h_cp h_cp^T / h_pp and
    b_c - h_cp b_p / h_pp, added into the camera system; its columns' places there (-1:
    keyframe 0, fixed) into ``idx`` and h_cp into ``Hcp_row`` for the back-substitution."""
    inv = 1.0 / hpp
    for c1 in range(hcp.shape[0]):
        s1 = (c1 - N_INTR) // N_FRAME
        if c1 < N_INTR:
            g1 = c1
        else:
            fr = h if s1 == 0 else targets[s1 - 1]
            g1 = -1 if fr == 0 else N_INTR + N_FRAME * (fr - 1) + (c1 - N_INTR) % N_FRAME
        idx[c1] = g1
        Hcp_row[c1] = hcp[c1]
    for c1 in range(hcp.shape[0]):
        g1 = idx[c1]
        if g1 < 0:
            continue
        b[g1] += bc[c1] - hcp[c1] * inv * bp
        for c2 in range(c1, hcp.shape[0]):
            g2 = idx[c2]
            if g2 < 0:
                continue
            v = Hcc[c1, c2] - hcp[c1] * inv * hcp[c2]
            H[g1, g2] += v
            if g1 != g2:
                H[g2, g1] += v


@nb.njit(cache=True, nogil=True)
def accumulate(host, uv, rho, target_start, targets, images, grad_x, grad_y, host_weights,
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
    # Long on purpose: a numba kernel, one pass over the points and their residuals (the
    # steps of a point are inlined helpers above).
    dxd = np.zeros((2, N_INTR))
    dxn = np.zeros((2, N_INTR))
    # A residual's camera columns: the intrinsics and the host's (fixed), then its target's.
    nonzero = np.arange(N_INTR + 2 * N_FRAME)
    cost, count = 0.0, 0
    for p in range(host.shape[0]):
        h = host[p]
        bh = affine[h, 1]
        tgs = targets[target_start[p]:target_start[p + 1]]
        n_loc = N_INTR + N_FRAME * (1 + tgs.shape[0])
        # The local camera block (~100 KB a point) only where it is summed.
        m = n_loc if with_cameras and jacobians else 0
        Hcc = np.zeros((m, m))
        hcp, bc, J = np.zeros(n_loc), np.zeros(n_loc), np.zeros(n_loc)
        hpp, bp = 0.0, 0.0
        cache, host_X, target_X, host_ray = _sample_pattern(
            uv[p, 0], uv[p, 1], rho[p], h, tgs, motion, images, grad_x, grad_y, max_samples,
            velocity, readout, rows, R_rel, t_rel, intr, jacobians)
        pair_ok = _inlier_targets(cache, affine, h, tgs, max_residual, res_out, stats)
        for q in range(8):
            _ray_derivative(uv[p, 0] + PATTERN[q, 0], uv[p, 1] + PATTERN[q, 1], host_ray[q],
                            intr, dxd, dxn)
            for i in range(tgs.shape[0]):
                tg = tgs[i]
                if not target_X[i, q, 2] > 1e-9:
                    continue
                if not pair_ok[i]:
                    # Leaving the image costs as much as an outlier, so that no step can
                    # lower the cost by pushing residuals out of view.
                    cost += host_weights[p, q] * (2 * huber * max_residual - huber * huber)
                    count += 1
                    continue
                Ih = cache[i, q, 1]
                ea = np.exp(affine[tg, 0] - affine[h, 0])
                r = cache[i, q, 0] - affine[tg, 1] - ea * (Ih - bh)
                w, c = _robust(r, host_weights[p, q], huber)
                cost += c
                count += 1
                if not jacobians:
                    continue
                bt = N_INTR + N_FRAME * (1 + i)
                jp = _residual_jacobian(J, bt, target_X[i, q, 0], target_X[i, q, 1],
                                        target_X[i, q, 2], host_X[q], R_rel[h, tg],
                                        cache[i, q, 2], cache[i, q, 3], ea, Ih, bh, rho[p],
                                        dxn, intr)
                hpp += w * jp * jp
                bp += w * jp * r
                if with_cameras:
                    _add_residual(J, w, r, jp, bt, nonzero, Hcc, hcp, bc)
        Hpp[p], bpp[p] = hpp, bp
        idx_store[p, :] = -1
        if with_cameras and hpp > 0:
            _scatter_schur(h, tgs, Hcc, hcp, bc, hpp, bp, idx_store[p], Hcp_store[p], H, b)
    stats[0], stats[1] = cost, count
