"""The matching cost of multi-view PatchMatch: a plane hypothesis scored against the sources.

A sparse window of the reference around a pixel is warped into each source view by the
plane's homography and compared by bilaterally weighted NCC; a hypothesis' cost is the mean
of its best ``nbest`` per-view costs (1 - NCC), so views where the point is occluded or
foreshortened drop out. The weights, the reference window's mean and deviation depend on the
reference only and are computed once per pixel (:func:`bilateral_weights`: exp() per sample
costs 3×, docs/mvs.md). The samples are taken in float32 in one branch-free loop over whole
vectors of them (:func:`padded_window`) from one flat array of the sources (:func:`padded`):
the same costs as float64 up to its rounding (tests/mvs/test_view_cost.py), in 0.37 of the
old kernel's time (docs/mvs.md, "Speed").
"""

from __future__ import annotations

import numba
import numpy as np

MAX_COST = 2.0  # 1 - NCC ranges over [0, 2]; invalid views and hypotheses score this


def window_offsets(radius: int, step: int) -> tuple[np.ndarray, np.ndarray]:
    """Sparse window sample offsets (dx, dy): every ``step``-th pixel, centred."""
    k = np.arange(-(radius // step), radius // step + 1) * step
    dy, dx = np.meshgrid(k, k, indexing="ij")
    return dx.ravel().astype(np.int32), dy.ravel().astype(np.int32)


LANES = 16
"""The window is padded to a multiple of this many samples (AVX-512's float32 lanes, two of
AVX2's): the vectorised sample loop of ``view_cost`` then runs without a remainder."""


def padded_window(dxs: np.ndarray, dys: np.ndarray, wn: np.ndarray, wa: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The window's offsets (float32) and per-pixel weights with weightless samples at its
    centre put first, up to a multiple of :data:`LANES`: they add exactly zero to every sum,
    and the last offset stays the window's corner (``view_cost`` reads its radius there)."""
    pad = -len(dxs) % LANES
    return (np.concatenate([np.zeros(pad, np.float32), dxs.astype(np.float32)]),
            np.concatenate([np.zeros(pad, np.float32), dys.astype(np.float32)]),
            np.pad(wn, ((0, 0), (pad, 0))), np.pad(wa, ((0, 0), (pad, 0))))


def padded(images: list[np.ndarray]) -> np.ndarray:
    """The source images as one float32 array (S, H + 1, W + 1), each with its last row and
    column repeated: a sample inside the image reads its 2x2 neighbours without a test, at
    the border too, where float32 rounding may put it a hair past the last pixel."""
    stack = np.stack(images).astype(np.float32, copy=False)
    return np.ascontiguousarray(np.pad(stack, ((0, 0), (0, 1), (0, 1)), mode="edge"))


@numba.njit(nogil=True, cache=True, fastmath=True, error_model="numpy")
def bilateral_weights(ref, us, vs, dxs, dys, sigma_c, sigma_s, wn, wa, ok):
    """Per pixel and window sample: normalised bilateral weight ``wn`` and ``wa = wn (r - mean)
    / std`` so that NCC against a source needs only sum(wn s), sum(wn s^2), sum(wa s)."""
    h, w = ref.shape
    ns = dxs.shape[0]
    ic = 1.0 / (2.0 * sigma_c * sigma_c)
    is_ = 1.0 / (2.0 * sigma_s * sigma_s)
    vals = np.empty(ns)
    for r in range(us.shape[0]):
        u, v = us[r], vs[r]
        centre = ref[v, u]
        sw = 0.0
        for k in range(ns):
            x = min(max(u + dxs[k], 0), w - 1)
            y = min(max(v + dys[k], 0), h - 1)
            val = ref[y, x]
            vals[k] = val
            dc = val - centre
            wk = np.exp(-dc * dc * ic - (dxs[k] * dxs[k] + dys[k] * dys[k]) * is_)
            wn[r, k] = wk
            sw += wk
        mean = 0.0
        sq = 0.0
        for k in range(ns):
            wn[r, k] /= sw
            mean += wn[r, k] * vals[k]
            sq += wn[r, k] * vals[k] * vals[k]
        var = sq - mean * mean
        # A flat reference window has no signal to match (NCC undefined).
        ok[r] = var > 1e-6
        sd = np.sqrt(max(var, 1e-12))
        for k in range(ns):
            wa[r, k] = wn[r, k] * (vals[k] - mean) / sd


@numba.njit(nogil=True, cache=True, fastmath=True, error_model="numpy", inline="always")
def window_inside(px, py, pz, h00, h01, h10, h11, h20, h21, rad, xmax, ymax):
    """Whether every sample of a window of radius ``rad`` maps in front of the source and
    inside [0, xmax) x [0, ymax): the samples include the window's corners, and a homography
    with z > 0 over the window maps it onto a convex quadrilateral, so the four corners
    decide (tested as x z and y z against z, without a branch between them)."""
    inside = True
    for cxs in (-rad, rad):
        for cys in (-rad, rad):
            z = pz + h20 * cxs + h21 * cys
            xn = px + h00 * cxs + h01 * cys
            yn = py + h10 * cxs + h11 * cys
            inside &= (z > 1e-9) & (xn >= 0.0) & (yn >= 0.0) & (xn < xmax * z) & (yn < ymax * z)
    return inside


@numba.njit(nogil=True, cache=True, fastmath=True, error_model="numpy", inline="always")
def view_cost(s, u, v, row, m0, m1, m2, srcs, flat, A, b, dxs, dys, wn, wa):
    """1 - NCC of the window at (u, v) against source ``s`` under the plane m (the
    homography H = A + b m^T maps reference pixels to source pixels); MAX_COST where a
    sample falls behind the source or off its image.

    ``srcs`` are the sources with their last row and column repeated once (:func:`padded`),
    ``flat`` the same array as one vector; the window's ``dxs``, ``dys`` and weights are
    padded to whole vectors (:func:`padded_window`). The homography is built in float64 and
    the samples are taken in float32: a 16-lane loop without a branch.
    """
    h = srcs.shape[1] - 1
    w = srcs.shape[2] - 1
    h00 = A[s, 0, 0] + b[s, 0] * m0
    h01 = A[s, 0, 1] + b[s, 0] * m1
    h02 = A[s, 0, 2] + b[s, 0] * m2
    h10 = A[s, 1, 0] + b[s, 1] * m0
    h11 = A[s, 1, 1] + b[s, 1] * m1
    h12 = A[s, 1, 2] + b[s, 1] * m2
    h20 = A[s, 2, 0] + b[s, 2] * m0
    h21 = A[s, 2, 1] + b[s, 2] * m1
    h22 = A[s, 2, 2] + b[s, 2] * m2
    px = h00 * u + h01 * v + h02
    py = h10 * u + h11 * v + h12
    pz = h20 * u + h21 * v + h22
    if not window_inside(px, py, pz, h00, h01, h10, h11, h20, h21, float(dxs[dxs.shape[0] - 1]),
                         w - 1.0, h - 1.0):
        return MAX_COST
    f32 = np.float32
    g00 = f32(h00)
    g01 = f32(h01)
    g10 = f32(h10)
    g11 = f32(h11)
    g20 = f32(h20)
    g21 = f32(h21)
    gx = f32(px)
    gy = f32(py)
    gz = f32(pz)
    one = f32(1.0)
    # 32-bit indices into the one flat array of the sources (a 16-lane gather; LLVM emits
    # one only for an index it knows to be below 2**31).
    below = np.uint32(0x7FFFFFFF)
    w1 = np.uint32(w + 1)
    base = np.uint32(s) * np.uint32((h + 1) * (w + 1))
    # The sums are taken about the source's value nearest the window's centre: NCC does
    # not see the offset, and float32 keeps the variance of a faint texture.
    iz = one / gz
    off = flat[(base + np.uint32(gy * iz) * w1 + np.uint32(gx * iz)) & below]
    s1 = f32(0.0)
    s2 = f32(0.0)
    c = f32(0.0)
    for k in range(dxs.shape[0]):
        dx = dxs[k]
        dy = dys[k]
        iz = one / (gz + g20 * dx + g21 * dy)
        x = (gx + g00 * dx + g01 * dy) * iz
        y = (gy + g10 * dx + g11 * dy) * iz
        # x, y lie in (-1, w - 1) and (-1, h - 1) up to float32's rounding (the corners
        # are inside): truncation and the repeated last row and column keep every load in.
        xi = np.uint32(x)
        yi = np.uint32(y)
        ax = x - f32(xi)
        ay = y - f32(yi)
        i = np.uint32(base + yi * w1 + xi) & below
        a = flat[i]
        top = a + ax * (flat[i + np.uint32(1)] - a)
        i = (i + w1) & below
        a = flat[i]
        bot = a + ax * (flat[i + np.uint32(1)] - a)
        val = top + ay * (bot - top) - off
        wk = wn[row, k]
        s1 += wk * val
        s2 += wk * val * val
        c += wa[row, k] * val
    var = s2 - s1 * s1
    if var <= 1e-10:
        return MAX_COST
    return min(max(1.0 - c / np.sqrt(var), 0.0), MAX_COST)


@numba.njit(nogil=True, cache=True, fastmath=True, error_model="numpy")
def plane(u, v, d, n0, n1, n2, fx, fy, cx, cy):
    """m = K^-T n / delta of the plane through depth ``d`` at pixel (u, v) with normal n;
    ok is False for a plane seen edge-on or from behind."""
    rx = (u - cx) / fx
    ry = (v - cy) / fy
    ndr = n0 * rx + n1 * ry + n2
    if ndr > -1e-3:
        return 0.0, 0.0, 0.0, False
    delta = d * ndr  # plane: n . X = delta (camera frame)
    return (n0 / fx / delta, n1 / fy / delta,
            (n2 - n0 * cx / fx - n1 * cy / fy) / delta, True)


@numba.njit(nogil=True, cache=True, fastmath=True, error_model="numpy")
def hypothesis_cost(u, v, row, d, n0, n1, n2, views, srcs, flat, A, b, fx, fy, cx, cy, dxs,
                     dys, wn, wa, nbest, best, bound):
    """Aggregated cost of plane (depth ``d`` at pixel (u, v), normal n): the mean of the
    best ``nbest`` per-view costs over the sources ``views``; MAX_COST as soon as it is
    certain not to be below ``bound`` (the caller keeps a hypothesis only if it is).
    ``best`` holds ``nbest`` + one entry per source: the sorted best costs, then each
    view's cost (read by :func:`worst_first`)."""
    m0, m1, m2, seen = plane(u, v, d, n0, n1, n2, fx, fy, cx, cy)
    if not seen:
        return MAX_COST
    for k in range(nbest):
        best[k] = MAX_COST
    nviews = views.shape[0]
    # A hair above bound * nbest, so that the sums' rounding (in any order) can never stop
    # a hypothesis the caller would have kept.
    limit = bound * nbest * (1.0 + 1e-9)
    lower = 0.0
    for i in range(nviews):
        cost = view_cost(views[i], u, v, row, m0, m1, m2, srcs, flat, A, b, dxs, dys, wn, wa)
        best[nbest + views[i]] = cost
        # Of the final best nbest, at least ``known`` = nbest - (views left) are among
        # those scored: their sum bounds the total from below (every cost is >= 0). It
        # grows by the smaller of this cost and the known-th smallest before it. With
        # bound = MAX_COST it stops only where every cost is MAX_COST: what the mean would be.
        known = nbest - (nviews - 1 - i)
        if known > 0:
            lower += min(cost, best[known - 1])
        # Into the sorted best nbest without a branch on the cost: entry j becomes the
        # smaller of itself and the larger of its left neighbour and the cost.
        for j in range(nbest - 1, 0, -1):
            best[j] = min(best[j], max(best[j - 1], cost))
        best[0] = min(best[0], cost)
        if lower >= limit:
            return MAX_COST
    total = 0.0
    for k in range(nbest):
        total += best[k]
    return total / nbest


@numba.njit(nogil=True, cache=True, fastmath=True, error_model="numpy")
def worst_first(order, best, nbest):
    """Sort a pixel's sources by the per-view costs of the hypothesis just scored
    (``best[nbest:]``), the worst first: the next hypotheses' lower bound then grows
    fastest, and one that loses stops earliest. Their costs are the same in any order."""
    for i in range(1, order.shape[0]):
        o = order[i]
        key = best[nbest + o]
        j = i
        while j > 0 and best[nbest + order[j - 1]] < key:
            order[j] = order[j - 1]
            j -= 1
        order[j] = o
