"""Plane sweep around the coarse mesh: a depth map from fronto-parallel planes (numpy/OpenCV).

Depth hypotheses are offsets from the coarse mesh's depth along each pixel's ray, every
``step_mm`` over the same ±margin PatchMatch searches. For each offset the reference window
is compared with every source by box-window NCC (OpenCV box filters over the warped source),
the per-view costs are aggregated over the best ``nbest`` sources as PatchMatch does
(views where the point is occluded drop out), the cheapest offset wins, and a parabola
through its neighbours' costs gives the sub-step depth. Normals come from the depth map's
central differences.

The window is dense (every pixel of a (2r+1)² box, against PatchMatch's sparse 36 samples)
and follows the coarse mesh's shape (each pixel at its own coarse depth plus the offset); on
rendered faces it is as accurate as PatchMatch or more at about a seventh of the CPU time,
on real photos and the real head scan less consistent, so it is the fast setting
(``mvs.depth.method: sweep``), not the default (docs/mvs.md, "Which depth search").
OpenCV releases the GIL, so depth maps in Python threads run in parallel.
"""

from __future__ import annotations

import time

import cv2
import numpy as np

from facecap_core.mvs.images import MVSView
from facecap_core.mvs.ncc import MAX_COST
from facecap_core.mvs.patchmatch import DepthMap, check_inputs
from facecap_core.mvs.prior import CoarsePrior


def _box(x: np.ndarray, radius: int) -> np.ndarray:
    return cv2.boxFilter(x, -1, (2 * radius + 1, 2 * radius + 1), borderType=cv2.BORDER_REFLECT)


def depth_normals(depth: np.ndarray, intr) -> np.ndarray:
    """Camera-frame unit normals (H, W, 3) from a depth map's central differences, facing
    the camera."""
    h, w = depth.shape
    u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    X = np.stack([(u - intr.cx) / intr.fx * depth, (v - intr.cy) / intr.fy * depth, depth], -1)
    du = np.zeros_like(X)
    dv = np.zeros_like(X)
    du[:, 1:-1] = X[:, 2:] - X[:, :-2]
    dv[1:-1] = X[2:] - X[:-2]
    n = np.cross(du, dv)
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-9)
    # Towards the camera: against the pixel's ray (X is the ray scaled by the depth).
    return np.where(np.sum(n * X, -1, keepdims=True) > 0, -n, n).astype(np.float32)


def smooth_normals(depth: np.ndarray, intr, sigma_px: float) -> np.ndarray:
    """Camera-frame unit normals (H, W, 3) facing the camera: at each valid (positive) pixel
    the plane fitted to its valid neighbours' depths, weighted by a Gaussian of
    ``sigma_px``: the slant over a matching window, not one pixel's sub-step noise. Zero
    where the depth is not, or where the neighbours are too few or in a line to fit a plane.

    A plane's inverse depth is affine in the normalised image coordinates (n . X = delta
    with X = d (x, y, 1) gives 1/d = (n0 x + n1 y + n2) / delta), so a weighted least-squares
    fit of 1/d is exact on a plane, also at the edge of the valid region, where a smoothed
    depth would flatten the slope (its weights one-sided)."""
    valid = depth > 0
    h, w = depth.shape
    x, y = np.meshgrid((np.arange(w, dtype=np.float64) - intr.cx) / intr.fx,
                       (np.arange(h, dtype=np.float64) - intr.cy) / intr.fy)
    q = np.where(valid, 1.0 / np.where(valid, depth, 1.0), 0.0)
    weight = valid.astype(np.float64)

    def mean(a: np.ndarray) -> np.ndarray:  # the Gaussian-weighted sums, float64 throughout
        return cv2.GaussianBlur(weight * a, (0, 0), sigma_px, borderType=cv2.BORDER_CONSTANT)

    s0 = mean(np.ones_like(x))
    # At least a twentieth of a full window's weight: fewer pixels fit no plane worth
    # starting from.
    fit = valid & (s0 > 0.05)
    s0 = np.where(fit, s0, 1.0)
    mx, my, mq = mean(x) / s0, mean(y) / s0, mean(q) / s0
    cxx = mean(x * x) / s0 - mx * mx
    cxy = mean(x * y) / s0 - mx * my
    cyy = mean(y * y) / s0 - my * my
    cxq = mean(x * q) / s0 - mx * mq
    cyq = mean(y * q) / s0 - my * mq
    det = cxx * cyy - cxy * cxy
    fit &= det > 0.01 * (cxx + cyy) ** 2  # neighbours in a line: no slope across it
    det = np.where(fit, det, 1.0)
    a = (cyy * cxq - cxy * cyq) / det
    b = (cxx * cyq - cxy * cxq) / det
    c = mq - a * mx - b * my
    # (a, b, c) = n / delta, and delta < 0 for a plane facing the camera.
    n = -np.stack([a, b, c], -1)
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-300)
    return np.where(fit[..., None], n, 0).astype(np.float32)


def sweep_depth(ref: MVSView, sources: list[MVSView], prior: CoarsePrior, margin_mm: float,
                step_mm: float = 0.5, radius: int = 5, nbest: int = 8) -> DepthMap:
    """Depth, normal and cost maps of ``ref`` over the prior's region: the best of the
    planes at offsets from the coarse depth every ``step_mm``, symmetric, covering ±margin
    (at least one on each side). Raw: no filtering."""
    start, cpu = time.perf_counter(), time.thread_time()
    check_inputs(ref, sources, prior)
    rows, cols = np.nonzero(prior.mask)
    r0, r1 = max(rows.min() - radius, 0), min(rows.max() + radius + 1, prior.mask.shape[0])
    c0, c1 = max(cols.min() - radius, 0), min(cols.max() + radius + 1, prior.mask.shape[1])
    mask = prior.mask[r0:r1, c0:c1]
    k = ref.intr
    u, v = np.meshgrid(np.arange(c0, c1, dtype=float), np.arange(r0, r1, dtype=float))
    rays = np.stack([(u - k.cx) / k.fx, (v - k.cy) / k.fy, np.ones_like(u)], -1)
    # Where the coarse mesh is not hit (the dilated rim) the search is centred in its range.
    base = np.where(np.isfinite(prior.depth), prior.depth, 0.5 * (prior.lo + prior.hi))
    base = base[r0:r1, c0:c1].astype(float)
    ref_g = ref.grey[r0:r1, c0:c1]
    mr = _box(ref_g, radius)
    sr = np.sqrt(np.maximum(_box(ref_g * ref_g, radius) - mr * mr, 1e-8))
    # Symmetric, and at least three planes (the parabola needs the best one's neighbours).
    half = max(1, int(np.ceil(margin_mm / step_mm - 1e-9)))
    offsets = step_mm * np.arange(-half, half + 1)
    agg = np.empty((len(offsets),) + base.shape, np.float32)
    nb = min(nbest, len(sources))
    costs = np.empty((len(sources),) + base.shape, np.float32)
    # A point at depth d on a reference ray projects into a source at the homogeneous
    # coordinates d * a + b (a: the ray in the source's pixel frame, b: the reference centre
    # in it), so each plane costs a multiply-add per pixel and view, not a matrix product.
    world_rays = rays @ ref.R  # R^T ray, row-wise
    centre = -ref.R.T @ ref.t
    proj = []
    for src in sources:
        a = (world_rays @ src.R.T) @ src.intr.K.T
        b = src.intr.K @ (src.R @ centre + src.t)
        proj.append(((a * base[..., None] + b).astype(np.float32), a.astype(np.float32)))
    for p, off in enumerate(offsets):
        for s, src in enumerate(sources):
            x0, a = proj[s]
            x = x0 + np.float32(off) * a
            z = np.maximum(x[..., 2], 1e-6)
            mu = x[..., 0] / z
            mv = x[..., 1] / z
            # Outside the source image reads -1, which no grey level is: such windows cost
            # MAX_COST.
            warped = cv2.remap(src.grey, mu, mv, cv2.INTER_LINEAR, borderValue=-1.0)
            ms = _box(warped, radius)
            ss = np.sqrt(np.maximum(_box(warped * warped, radius) - ms * ms, 1e-8))
            ncc = (_box(ref_g * warped, radius) - mr * ms) / (sr * ss)
            bad = _box((warped < 0).astype(np.float32), radius) > 0
            costs[s] = np.where(bad, MAX_COST, np.clip(1.0 - ncc, 0, MAX_COST))
        agg[p] = np.partition(costs, nb - 1, axis=0)[:nb].mean(0)
    best = np.argmin(agg, axis=0)
    i = np.clip(best, 1, len(offsets) - 2)
    c_m = np.take_along_axis(agg, (i - 1)[None], 0)[0]
    c_0 = np.take_along_axis(agg, i[None], 0)[0]
    c_p = np.take_along_axis(agg, (i + 1)[None], 0)[0]
    curv = c_m - 2 * c_0 + c_p
    sub = np.where(curv > 1e-9, 0.5 * (c_m - c_p) / np.where(curv > 1e-9, curv, 1), 0)
    depth_c = base + offsets[i] + np.clip(sub, -1, 1) * step_mm
    cost_c = np.take_along_axis(agg, best[None], 0)[0]
    depth = np.zeros(prior.mask.shape, np.float32)
    cost = np.full(prior.mask.shape, MAX_COST, np.float32)
    depth[r0:r1, c0:c1] = np.where(mask, depth_c, 0)
    cost[r0:r1, c0:c1] = np.where(mask, cost_c, MAX_COST)
    normal = np.where((depth > 0)[..., None], depth_normals(depth, k), 0).astype(np.float32)
    return DepthMap(ref.index, depth, normal, cost, ref.intr, ref.R, ref.t,
                    np.array([s.index for s in sources]), time.perf_counter() - start,
                    time.thread_time() - cpu)
