"""Multi-view PatchMatch (Gipuma-style) on the CPU: one depth + normal map per call.

Every pixel of the head region holds a plane hypothesis (depth along its ray and a normal,
camera frame), scored by :mod:`facecap_core.mvs.ncc` (the window's bilaterally weighted NCC
in each source, the mean of the best ``num_best_views``). Hypotheses improve by red–black
checkerboard propagation (Gipuma's neighbour pattern: a pixel of one colour only reads
pixels of the other, so a half-sweep can update in place) and random refinement with steps
that halve every iteration. The search is bounded by the coarse mesh's depth ± a margin.

The kernels are numba ``nogil`` functions: one call computes one depth map on one thread,
and several calls run in parallel from Python threads.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numba
import numpy as np

from facecap_core.camera import Intrinsics
from facecap_core.errors import InputError
from facecap_core.mvs.images import MVSView
from facecap_core.mvs.ncc import (
    MAX_COST,
    bilateral_weights,
    hypothesis_cost,
    padded,
    padded_window,
    plane,
    view_cost,
    window_offsets,
    worst_first,
)
from facecap_core.mvs.prior import CoarsePrior

# Gipuma's propagation patterns, (dx, dy). Every offset has an odd |dx| + |dy|, so it points
# at a pixel of the other checkerboard colour.
NEIGHBOURS_FAST = np.array([(0, -1), (0, 1), (-1, 0), (1, 0),
                            (0, -5), (0, 5), (-5, 0), (5, 0)], np.int32)
NEIGHBOURS_NEAR = np.ascontiguousarray(NEIGHBOURS_FAST[:4])
NEIGHBOURS_FULL = np.array(
    [(0, -1), (0, 1), (-1, 0), (1, 0), (0, -3), (0, 3), (-3, 0), (3, 0),
     (0, -5), (0, 5), (-5, 0), (5, 0), (-1, -2), (1, -2), (-2, -1), (2, -1),
     (-1, 2), (1, 2), (-2, 1), (2, 1)], np.int32)


@dataclass
class DepthMap:
    """One reference view's PatchMatch result (pinhole camera of the processed image)."""

    index: int  # keyframe index of the reference
    depth: np.ndarray  # float32 (H, W), camera z in mm; 0 = no depth
    normal: np.ndarray  # float32 (H, W, 3), camera frame, facing the camera; 0 = none
    cost: np.ndarray  # float32 (H, W), aggregated 1 - NCC; MAX_COST where not computed
    intr: Intrinsics
    R: np.ndarray
    t: np.ndarray
    sources: np.ndarray | None = None  # keyframe indices of the source views
    seconds: float = 0.0  # wall time of the call
    cpu_seconds: float = 0.0  # CPU time of the calling thread

    @property
    def valid(self) -> np.ndarray:
        return self.depth > 0


# --------------------------------------------------------------------------- kernels


@numba.njit(nogil=True, cache=True, fastmath=True, error_model="numpy")
def _select_views(us, vs, ok, depth, normal, srcs, flat, A, b, fx, fy, cx, cy, dxs, dys, wn,
                  wa, nbest, views, cost):
    """Per pixel, the sources sorted by their cost under the pixel's current plane (best
    first), written into the rows of ``views``; the pixel's cost again from these."""
    costs = np.empty(srcs.shape[0])
    for r in range(us.shape[0]):
        if not ok[r]:
            continue
        u, v = us[r], vs[r]
        m0, m1, m2, seen = plane(u, v, depth[v, u], normal[v, u, 0], normal[v, u, 1],
                                  normal[v, u, 2], fx, fy, cx, cy)
        if not seen:
            continue
        for s in range(srcs.shape[0]):
            costs[s] = view_cost(s, u, v, r, m0, m1, m2, srcs, flat, A, b, dxs, dys, wn,
                                  wa)
        order = np.argsort(costs, kind="mergesort")
        views[r] = order.astype(np.int32)
        total = 0.0
        for k in range(nbest):
            total += costs[order[k]]
        cost[v, u] = total / nbest


@numba.njit(nogil=True, cache=True, fastmath=True, error_model="numpy")
def _random_normal(rx, ry, max_tilt):
    """Random unit normal facing the camera, within ``max_tilt`` (cosine) of the view ray."""
    inv = 1.0 / np.sqrt(rx * rx + ry * ry + 1.0)
    for _ in range(20):
        n0 = np.random.normal()
        n1 = np.random.normal()
        n2 = np.random.normal()
        norm = np.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
        if norm < 1e-9:
            continue
        n0 /= norm
        n1 /= norm
        n2 /= norm
        dot = (n0 * rx + n1 * ry + n2) * inv
        if dot > 0:
            n0, n1, n2, dot = -n0, -n1, -n2, -dot
        if -dot >= max_tilt:
            return n0, n1, n2
    return -rx * inv, -ry * inv, -inv


@numba.njit(nogil=True, cache=True, fastmath=True, error_model="numpy")
def _perturb_normal(n0, n1, n2, sigma, rx, ry):
    """Normal rotated by a random angle of about ``sigma`` radians, kept facing the camera."""
    m0 = n0 + sigma * np.random.normal()
    m1 = n1 + sigma * np.random.normal()
    m2 = n2 + sigma * np.random.normal()
    norm = np.sqrt(m0 * m0 + m1 * m1 + m2 * m2)
    m0 /= norm
    m1 /= norm
    m2 /= norm
    if m0 * rx + m1 * ry + m2 >= 0:
        return n0, n1, n2
    return m0, m1, m2


@numba.njit(nogil=True, cache=True, fastmath=True, error_model="numpy")
def _patchmatch(us, vs, idx, ok, lo, hi, prior_depth, prior_normal, use_prior,
                srcs, A, b, fx, fy, cx, cy, dxs, dys, wn, wa, nbest, iterations, first_step,
                nbr, refine_trials, normal_sigma, seed, pixel_views, depth, normal, cost):
    """Initialise and iterate PatchMatch in place on ``depth``, ``normal``, ``cost``; after
    the first iteration each pixel is matched against its best ``pixel_views`` sources
    (0: all). A pixel whose ``depth`` is set on entry starts from that plane instead of a
    random one; the refinement steps start at ``0.5 ** first_step``. ``srcs`` are the
    sources as :func:`padded` leaves them, the window's offsets and weights as
    :func:`padded_window` does."""
    # Long on purpose: a numba kernel: the initialisation, propagation and refinement sweeps share
    # the per-pixel state in place.
    np.random.seed(seed)
    best = np.empty(nbest + srcs.shape[0])
    flat = srcs.reshape(srcs.size)
    h, w = idx.shape
    m = us.shape[0]
    max_tilt = 0.17  # cos(80°): steeper planes are not plausible skin
    nsrc = srcs.shape[0]
    views = np.empty((m, nsrc), np.int32)
    for r in range(m):
        views[r] = np.arange(nsrc)
    nviews = nsrc
    for r in range(m):
        u, v = us[r], vs[r]
        rx = (u - cx) / fx
        ry = (v - cy) / fy
        if not ok[r]:
            continue
        if lo[v, u] <= depth[v, u] <= hi[v, u]:
            d = depth[v, u]
            n0, n1, n2 = normal[v, u, 0], normal[v, u, 1], normal[v, u, 2]
        else:
            d = lo[v, u] + np.random.random() * (hi[v, u] - lo[v, u])
            n0, n1, n2 = _random_normal(rx, ry, max_tilt)
        c = hypothesis_cost(u, v, r, d, n0, n1, n2, views[r], srcs, flat, A, b, fx, fy, cx,
                             cy, dxs, dys, wn, wa, nbest, best, MAX_COST)
        if c < MAX_COST:
            worst_first(views[r], best, nbest)
        if use_prior and np.isfinite(prior_depth[v, u]):
            p0, p1, p2 = prior_normal[v, u, 0], prior_normal[v, u, 1], prior_normal[v, u, 2]
            pd = prior_depth[v, u]
            pc = hypothesis_cost(u, v, r, pd, p0, p1, p2, views[r], srcs, flat, A, b, fx, fy,
                                  cx, cy, dxs, dys, wn, wa, nbest, best, c)
            if pc < c:
                d, n0, n1, n2, c = pd, p0, p1, p2, pc
                worst_first(views[r], best, nbest)
        depth[v, u] = d
        normal[v, u, 0] = n0
        normal[v, u, 1] = n1
        normal[v, u, 2] = n2
        cost[v, u] = c

    for it in range(iterations):
        scale = 0.5 ** (it + first_step)
        if it >= 1 and 0 < pixel_views < nsrc:
            # Once the planes have roughly converged, a plane's best views are the
            # surface's: the sources that see the pixel occluded or foreshortened drop
            # out, and each hypothesis costs pixel_views / nsrc as much. Chosen again every
            # iteration, from the plane the last one left.
            _select_views(us, vs, ok, depth, normal, srcs, flat, A, b, fx, fy, cx, cy, dxs,
                          dys, wn, wa, nbest, views, cost)
            nviews = pixel_views
        for colour in range(2):
            for r in range(m):
                u, v = us[r], vs[r]
                if (u + v) % 2 != colour or not ok[r]:
                    continue
                rx = (u - cx) / fx
                ry = (v - cy) / fy
                d = depth[v, u]
                n0, n1, n2 = normal[v, u, 0], normal[v, u, 1], normal[v, u, 2]
                c = cost[v, u]
                dlo, dhi = lo[v, u], hi[v, u]
                # Propagation: the neighbour's plane, intersected with this pixel's ray.
                for k in range(nbr.shape[0]):
                    qu = u + nbr[k, 0]
                    qv = v + nbr[k, 1]
                    if qu < 0 or qv < 0 or qu >= w or qv >= h:
                        continue
                    q = idx[qv, qu]
                    if q < 0 or not ok[q]:
                        continue
                    q0, q1, q2 = normal[qv, qu, 0], normal[qv, qu, 1], normal[qv, qu, 2]
                    qd = depth[qv, qu]
                    delta = qd * (q0 * (qu - cx) / fx + q1 * (qv - cy) / fy + q2)
                    ndr = q0 * rx + q1 * ry + q2
                    if ndr > -1e-3:
                        continue
                    dp = delta / ndr
                    if dp < dlo or dp > dhi:
                        continue
                    # The same plane as the current one: nothing to test.
                    if abs(dp - d) < 1e-5 * d and q0 == n0 and q1 == n1 and q2 == n2:
                        continue
                    cc = hypothesis_cost(u, v, r, dp, q0, q1, q2, views[r, :nviews], srcs,
                                          flat, A, b, fx, fy, cx, cy, dxs, dys, wn, wa, nbest,
                                          best, c)
                    if cc < c:
                        d, n0, n1, n2, c = dp, q0, q1, q2, cc
                        if nviews == nsrc:
                            worst_first(views[r], best, nbest)
                # Refinement: perturb depth, normal, then both, by shrinking steps.
                for j in range(refine_trials):
                    kind = j % 3
                    step = scale * 0.5 ** (j // 3)
                    dd = d
                    m0, m1, m2 = n0, n1, n2
                    if kind != 1:
                        dd = d + (2.0 * np.random.random() - 1.0) * 0.5 * (dhi - dlo) * step
                        if dd < dlo or dd > dhi:
                            continue
                    if kind != 0:
                        m0, m1, m2 = _perturb_normal(n0, n1, n2, normal_sigma * step, rx, ry)
                    cc = hypothesis_cost(u, v, r, dd, m0, m1, m2, views[r, :nviews], srcs,
                                          flat, A, b, fx, fy, cx, cy, dxs, dys, wn, wa, nbest,
                                          best, c)
                    if cc < c:
                        d, n0, n1, n2, c = dd, m0, m1, m2, cc
                        if nviews == nsrc:
                            worst_first(views[r], best, nbest)
                depth[v, u] = d
                normal[v, u, 0] = n0
                normal[v, u, 1] = n1
                normal[v, u, 2] = n2
                cost[v, u] = c


# --------------------------------------------------------------------------- driver


def presmoothed(grey: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian pre-smoothing: a sparse window samples every other pixel, so sensor noise
    above the sampling rate would otherwise alias straight into the NCC."""
    if sigma <= 0:
        return grey
    return cv2.GaussianBlur(grey, (0, 0), sigma)


def _relative_poses(ref: MVSView, sources: list[MVSView]) -> tuple[np.ndarray, np.ndarray]:
    """Per source: A = K_s R_rel K_r^-1 and b = K_s t_rel (reference camera -> source)."""
    k_inv = np.linalg.inv(ref.intr.K)
    A = np.empty((len(sources), 3, 3))
    b = np.empty((len(sources), 3))
    for i, s in enumerate(sources):
        r_rel = s.R @ ref.R.T
        t_rel = s.t - r_rel @ ref.t
        A[i] = s.intr.K @ r_rel @ k_inv
        b[i] = s.intr.K @ t_rel
    return A, b


def check_inputs(ref: MVSView, sources: list[MVSView], prior: CoarsePrior) -> None:
    """One-line InputErrors for inputs PatchMatch cannot use."""
    if not sources:
        raise InputError(f"keyframe {ref.index}: no source views to match against")
    for s in sources:
        if s.grey.shape != ref.grey.shape:
            raise InputError(f"keyframe {s.index} is {s.grey.shape[1]}x{s.grey.shape[0]} but "
                             f"reference {ref.index} is {ref.grey.shape[1]}x{ref.grey.shape[0]};"
                             " process all keyframes at one size")
        if (s.intr.width, s.intr.height) != (s.grey.shape[1], s.grey.shape[0]):
            raise InputError(f"keyframe {s.index}: camera is {s.intr.width}x{s.intr.height} but "
                             f"its image is {s.grey.shape[1]}x{s.grey.shape[0]}")
    if (ref.intr.width, ref.intr.height) != (ref.grey.shape[1], ref.grey.shape[0]):
        raise InputError(f"keyframe {ref.index}: camera is {ref.intr.width}x{ref.intr.height} "
                         f"but its image is {ref.grey.shape[1]}x{ref.grey.shape[0]}")
    if prior.mask.shape != ref.grey.shape:
        raise InputError(f"keyframe {ref.index}: coarse prior is {prior.mask.shape[::-1]} but "
                         f"the image is {ref.grey.shape[::-1]}")
    if not prior.mask.any():
        raise InputError(f"keyframe {ref.index}: the coarse mesh does not overlap the image")


def planes_at(coarse: DepthMap, intr: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Depth and normal maps at the resolution of ``intr`` (the same camera as ``coarse``'s at
    another size): each pixel takes the plane of the coarse pixel it lies in, intersected with
    its own ray (depth 0 where that pixel has none, or sees the plane edge-on)."""
    hc, wc = coarse.depth.shape
    u = np.arange(intr.width, dtype=float)
    v = np.arange(intr.height, dtype=float)
    uc = np.minimum(((u + 0.5) * wc / intr.width).astype(int), wc - 1)
    vc = np.minimum(((v + 0.5) * hc / intr.height).astype(int), hc - 1)
    d = coarse.depth[vc[:, None], uc[None, :]].astype(float)
    n = coarse.normal[vc[:, None], uc[None, :]].astype(float)
    k = coarse.intr
    # The plane n . X = delta through the coarse pixel's point d * ray.
    delta = d * (n[..., 0] * ((uc[None, :] - k.cx) / k.fx) + n[..., 1] * ((vc[:, None] - k.cy)
                                                                       / k.fy) + n[..., 2])
    ndr = (n[..., 0] * ((u[None, :] - intr.cx) / intr.fx)
           + n[..., 1] * ((v[:, None] - intr.cy) / intr.fy) + n[..., 2])
    seen = (d > 0) & (ndr < -1e-3)
    depth = np.where(seen, delta / np.where(seen, ndr, -1.0), 0.0).astype(np.float32)
    normal = np.where(seen[..., None], n, 0.0).astype(np.float32)
    return depth, normal


def neighbour_pattern(name: str) -> np.ndarray:
    """Gipuma's propagation pattern by its name (``DepthMapConfig.neighbours``)."""
    return NEIGHBOURS_FAST if name == "fast" else NEIGHBOURS_FULL


def patchmatch_depth(ref: MVSView, sources: list[MVSView], prior: CoarsePrior, config,
                     start_planes: DepthMap | None = None, iterations: int | None = None,
                     first_step: int = 0, neighbours: np.ndarray | None = None) -> DepthMap:
    """Depth, normal and cost maps of ``ref`` over the prior's region (``config``:
    :class:`~facecap_core.mvs.depth.DepthMapConfig`). Raw: no filtering.

    ``start_planes``: a map of the same view (a coarser level's, or the plane sweep's at the
    same size), whose planes the pixels start from (:func:`planes_at`) instead of random
    ones; ``iterations`` (default ``config.iterations``) then run with refinement steps from
    ``0.5 ** first_step``. Propagation follows ``config.neighbours`` from random planes and
    the four nearest neighbours from ``start_planes``, unless ``neighbours`` (a pattern of
    :func:`neighbour_pattern`) says otherwise.
    """
    start, cpu = time.perf_counter(), time.thread_time()
    check_inputs(ref, sources, prior)
    h, w = ref.grey.shape
    vs, us = np.nonzero(prior.mask)
    us, vs = us.astype(np.int32), vs.astype(np.int32)
    idx = np.full((h, w), -1, np.int32)
    idx[vs, us] = np.arange(len(us), dtype=np.int32)
    dxs, dys = window_offsets(config.window_radius, config.window_step)
    wn = np.empty((len(us), len(dxs)), np.float32)
    wa = np.empty_like(wn)
    ok = np.empty(len(us), np.bool_)
    sigma_s = config.sigma_spatial or float(config.window_radius)
    ref_grey = presmoothed(ref.grey, config.presmooth_sigma)
    bilateral_weights(ref_grey, us, vs, dxs, dys, config.sigma_color, sigma_s, wn, wa, ok)
    dxs, dys, wn, wa = padded_window(dxs, dys, wn, wa)
    srcs = padded([presmoothed(s.grey, config.presmooth_sigma) for s in sources])
    if srcs.size >= 2**31:  # the cost's 32-bit sample indices (mvs.ncc.view_cost)
        raise InputError(f"keyframe {ref.index}: {len(sources)} source views of {w}x{h} are "
                         "more pixels than PatchMatch indexes (2**31); lower "
                         "mvs.depth.processing_width or mvs.views.num_sources")
    A, b = _relative_poses(ref, sources)
    nbr = neighbour_pattern(config.neighbours)
    if start_planes is None:
        depth = np.zeros((h, w), np.float32)
        normal = np.zeros((h, w, 3), np.float32)
    else:
        depth, normal = planes_at(start_planes, ref.intr)
        depth[~prior.mask] = 0.0  # outside the region nothing is computed, nor kept
        normal[~prior.mask] = 0.0
        # The coarser level's planes already carry what the far neighbours would: the four
        # nearest make the map 22 % faster, as accurate
        # (docs/experiments/2026-11-28-coarse-to-fine-patchmatch.md).
        nbr = NEIGHBOURS_NEAR
    if neighbours is not None:
        nbr = neighbours
    cost = np.full((h, w), MAX_COST, np.float32)
    nbest = int(min(config.num_best_views, len(sources)))
    k = ref.intr
    _patchmatch(us, vs, idx, ok, prior.lo, prior.hi, prior.depth, prior.normal,
                bool(config.init_from_coarse), srcs, A, b, k.fx, k.fy, k.cx, k.cy, dxs, dys,
                wn, wa, nbest, int(iterations or config.iterations), int(first_step), nbr,
                int(config.refine_trials),
                float(np.radians(config.normal_perturbation_deg)),
                int(config.seed) * 1000003 + int(ref.index), int(config.pixel_views), depth,
                normal, cost)
    # Pixels without a usable window keep no depth.
    depth[vs[~ok], us[~ok]] = 0.0
    normal[vs[~ok], us[~ok]] = 0.0
    return DepthMap(ref.index, depth, normal, cost, ref.intr, ref.R, ref.t,
                    np.array([s.index for s in sources]), time.perf_counter() - start,
                    time.thread_time() - cpu)
