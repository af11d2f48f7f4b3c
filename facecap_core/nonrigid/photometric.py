"""Photometric refinement of a fitted mesh against its keyframes.

The fused cloud carries the depth maps' errors: a plane over each matching window flattens
convex skin and fills concave skin, and its noise follows coverage
(docs/experiments/2026-11-28-raking-light-lumps.md). Here each vertex is moved along its
normal to where the keyframes agree best on a patch curved as the mesh is, so a correct
surface is where the views agree.

Each round, for every vertex:

1. its views: the keyframes that see it (a ray cast against the mesh) at
   ``cos >= MIN_COS``, at most ``MAX_VIEWS`` spread along the sweep;
2. its patch: a (2r+1)² grid in its tangent plane, ``patch_step_px`` of its best view's
   pixels apart, lifted onto the mesh's local quadric (its two-ring neighbours' heights);
3. each of ``CANDIDATES`` offsets along the normal moves the patch rigidly; the views' grey
   samples of it, normalised, give the mean pairwise NCC; the best offset (a parabola
   through the peak) and a confidence (the peak's height over the candidates' mean) are
   the vertex's measurement, its weight ``min(confidence / confidence_scale, MAX_WEIGHT)``;
4. the offsets from the fitted surface are solved for on the mesh graph,
   ``(W + fit_weight + ANCHOR + smoothness L) Δ = W (t - t̄)`` (``L`` the graph Laplacian,
   ``t`` the measured offsets, ``t̄`` their weighted mean): a vertex the images say nothing
   about follows its neighbours, and the images set the surface's shape while the fused
   cloud keeps its position.

The search reach shrinks by ``SHRINK`` every round.
"""

from __future__ import annotations

import logging
import time
from concurrent.futures import ThreadPoolExecutor

import cv2
import numba
import numpy as np
import scipy.sparse as sp
from pydantic import Field
from scipy.sparse.linalg import spsolve

from facecap_core.config import StrictModel
from facecap_core.nonrigid.constraints import FIT_THREADS
from facecap_core.nonrigid.solver import edges_of
from facecap_core.render import RaycastScene, vertex_normals, visible_vertices

__all__ = ["PhotometricConfig", "refine"]

log = logging.getLogger(__name__)


CANDIDATES = 11
"""Offsets tried along the normal in a round, evenly over ± the round's reach."""
SHRINK = 0.7
"""Each round's reach is this fraction of the round's before it."""
MIN_COS = 0.5
"""A keyframe measures a vertex that faces it at least this much (cos): beyond 60° the
patch's samples crowd into a few pixels."""
MAX_VIEWS = 8
"""Most keyframes that measure a vertex, spread along the sweep (more cost time: 12
measured the same on the clean calibration capture)."""
ANCHOR = 0.01
"""A pull of every vertex toward the fitted surface beside ``fit_weight``, so that the
offsets' system stays regular with ``fit_weight`` 0."""
VISIBILITY_TOL_MM = 0.5
"""A vertex is occluded in a view when the view's ray hits the mesh more than this before
it."""
MIN_CONFIDENCE = 0.5
"""A measurement whose confidence is below this fraction of the first round's median
confidence is not used (a flat score: texture-less skin, or a view that disagrees)."""
MAX_WEIGHT = 2.0
"""The most one measurement weighs (a confidence of twice ``confidence_scale``): against
the fitted surface's 1, a vertex moves at most two thirds of the way to it."""


class PhotometricConfig(StrictModel):
    """Photometric refinement of the fitted mesh: each vertex moved along its normal to
    where the keyframes agree on a patch curved as the mesh is
    (:mod:`facecap_core.nonrigid.photometric`)."""

    rounds: int = Field(2, ge=0, le=10)
    """Rounds of measuring and moving (0: the mesh as the fit leaves it)."""
    search_mm: float = Field(2.0, gt=0, le=20)
    """How far along the normal the first round looks, either way (each round after it
    looks 0.7 as far)."""
    patch_radius: int = Field(5, ge=1, le=10)
    """The patch is (2r + 1)² samples."""
    patch_step_px: float = Field(1.5, gt=0, le=10)
    """The patch's samples lie this many of the vertex's best view's pixels apart."""
    confidence_scale: float | None = Field(0.03, gt=0, le=1)
    """A measurement whose confidence (its NCC peak's height over the mean of the
    candidates) is this weighs 1 against ``fit_weight``; None: the capture's own median
    confidence in the first round."""
    fit_weight: float = Field(1.0, ge=0, le=1e4)
    """Pull of every vertex toward the fitted surface (the cloud's), against a measurement
    of confidence ``confidence_scale``: 1 puts such a vertex halfway between the two."""
    smoothness: float = Field(16.0, ge=0, le=1e4)
    """Weight of the mesh-graph Laplacian on the offsets against a measurement of weight 1:
    how far a measurement's offset spreads over its neighbours (16, with ``fit_weight`` 1:
    about four rings, some 5 mm on the default template)."""


def _graph(faces: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, sp.csr_matrix]:
    """The mesh's two-ring pairs (i, j), i ≠ j, both ways, and its graph Laplacian."""
    e = edges_of(faces)
    adjacency = sp.coo_matrix((np.ones(2 * len(e)), (np.r_[e[:, 0], e[:, 1]],
                                                     np.r_[e[:, 1], e[:, 0]])),
                              shape=(n, n)).tocsr()
    ring2 = ((adjacency @ adjacency + adjacency) > 0).tocoo()
    keep = ring2.row != ring2.col
    laplacian = sp.diags(np.asarray(adjacency.sum(1)).ravel()) - adjacency
    return ring2.row[keep], ring2.col[keep], laplacian


def _tangents(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    helper = np.where(np.abs(normals[:, [0]]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = np.cross(normals, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    return t1, np.cross(normals, t1)


def _quadrics(v: np.ndarray, normals: np.ndarray, t1: np.ndarray, t2: np.ndarray,
              i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Per vertex (a, b, c) of the height h = a u² + b u v + c v² of its two-ring (the pairs
    ``i``, ``j``) over its tangent plane (least squares, a small ridge toward flat)."""
    d = v[j] - v[i]
    u = np.einsum("ij,ij->i", d, t1[i])
    w = np.einsum("ij,ij->i", d, t2[i])
    h = np.einsum("ij,ij->i", d, normals[i])
    phi = np.stack([u * u, u * w, w * w], axis=1)
    n = len(v)
    # Sums per vertex by bincount, which adds in the pairs' order as np.add.at did, at a
    # fraction of its time; m is symmetric, so each of its upper entries is summed once.
    m = np.empty((n, 3, 3))
    for a, b in zip(*np.triu_indices(3)):
        m[:, a, b] = m[:, b, a] = np.bincount(i, phi[:, a] * phi[:, b], n)
    r = np.column_stack([np.bincount(i, phi[:, a] * h, n) for a in range(3)])
    scale = np.trace(m, axis1=1, axis2=2)[:, None, None]
    m += np.eye(3) * (1e-3 * scale + 1e-9)
    return np.linalg.solve(m, r[..., None])[..., 0]


def _grey(image: np.ndarray) -> np.ndarray:
    g = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    return g.astype(np.float32)


def _views_per_vertex(scene, v, normals, keyframes, margin_px: float):
    """(n, K) keyframe indices (-1 none) and the pixel footprint (mm) in the best view."""
    n = len(v)
    cos_all = np.full((len(keyframes), n), -1.0, np.float32)
    footprint = np.full(n, np.inf)
    best = np.full(n, -1.0)
    for k, kf in enumerate(keyframes):
        ids, cos, _, z = visible_vertices(scene, v, normals, kf.R, kf.t, kf.intrinsics,
                                          MIN_COS, VISIBILITY_TOL_MM, margin_px)
        cos_all[k, ids] = cos
        better = cos > best[ids]
        best[ids[better]] = cos[better]
        footprint[ids[better]] = z[better] / kf.intrinsics.fx
    seen = cos_all >= MIN_COS
    count = seen.sum(0)
    # Views spread along the sweep: of a vertex's c seeing views (in keyframe order) those
    # of rank round(j (c - 1) / (K - 1)), j < K; all of them when c <= K.
    rank = np.cumsum(seen, axis=0) - 1
    K = MAX_VIEWS
    c1 = np.maximum(count - 1, 1)[None]
    j = np.round(rank * (K - 1) / c1)
    chosen = seen & ((count[None] <= K) | (np.round(j * c1 / (K - 1)) == rank))
    chosen[:, count < 2] = False
    k_idx = np.where(chosen, np.arange(len(keyframes))[:, None], len(keyframes))
    views = np.sort(k_idx, axis=0)[:K].T
    views = np.where(views == len(keyframes), -1, views)
    return views, footprint


@numba.njit(nogil=True, cache=True, fastmath=True)
def _patch_scores(base, normals, views, offsets, images, rotations, translations, cameras,
                  rows, score):
    """For the patches ``rows``: the mean pairwise NCC of the views ``views[i]``' grey
    samples of the patch ``base[i]`` (G, 3) moved by each of ``offsets`` along
    ``normals[i]``, into ``score[i]`` (D,). ``cameras[k]``: fx, fy, cx, cy, k1, k2 of
    keyframe k. The samples are clamped to the image; the views are chosen with the patch's
    reach inside it."""
    n_off, n_pts = len(offsets), base.shape[1]
    height, width = images.shape[1], images.shape[2]
    total = np.empty((n_off, n_pts))
    vals = np.empty(n_pts)
    for i in rows:
        total[:] = 0.0
        count = 0
        for slot in range(views.shape[1]):
            k = views[i, slot]
            if k < 0:
                continue
            count += 1
            fx, fy, cx, cy, k1, k2 = cameras[k]
            R, t = rotations[k], translations[k]
            for d in range(n_off):
                mean = 0.0
                for g in range(n_pts):
                    px = base[i, g, 0] + offsets[d] * normals[i, 0]
                    py = base[i, g, 1] + offsets[d] * normals[i, 1]
                    pz = base[i, g, 2] + offsets[d] * normals[i, 2]
                    xc = R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz + t[0]
                    yc = R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz + t[1]
                    zc = max(R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz + t[2], 1e-6)
                    x, y = xc / zc, yc / zc
                    r2 = x * x + y * y
                    f = 1.0 + k1 * r2 + k2 * r2 * r2
                    u = min(max(fx * x * f + cx, 0.0), width - 1.001)
                    v = min(max(fy * y * f + cy, 0.0), height - 1.001)
                    u0, v0 = int(u), int(v)
                    a, b = u - u0, v - v0
                    val = ((1 - a) * (1 - b) * images[k, v0, u0]
                           + a * (1 - b) * images[k, v0, u0 + 1]
                           + (1 - a) * b * images[k, v0 + 1, u0]
                           + a * b * images[k, v0 + 1, u0 + 1])
                    vals[g] = val
                    mean += val
                mean /= n_pts
                norm = 0.0
                for g in range(n_pts):
                    vals[g] -= mean
                    norm += vals[g] * vals[g]
                norm = max(np.sqrt(norm), 1e-3)
                for g in range(n_pts):
                    total[d, g] += vals[g] / norm
        for d in range(n_off):
            if count < 2:
                score[i, d] = 0.0
                continue
            sq = 0.0
            for g in range(n_pts):
                sq += total[d, g] * total[d, g]
            score[i, d] = (sq - count) / (count * (count - 1))


@numba.njit(nogil=True, cache=True)
def _patch_points(v, t1, t2, normals, quad, step, gu, gv):
    """(m, G, 3): vertex i's patch, the grid ``(gu, gv) step[i]`` in its tangent plane
    (``t1``, ``t2``) lifted by its quadric ``quad[i]`` along its normal. No fastmath: each
    point is the float operations, in their order, of the numpy expression it replaces,
    without the temporary arrays of the patches' size."""
    base = np.empty((len(v), len(gu), 3))
    for i in range(len(v)):
        a, b, c = quad[i, 0], quad[i, 1], quad[i, 2]
        for g in range(len(gu)):
            u, w = gu[g] * step[i], gv[g] * step[i]
            h = a * u * u + b * u * w + c * w * w
            for k in range(3):
                base[i, g, k] = v[i, k] + u * t1[i, k] + w * t2[i, k] + h * normals[i, k]
    return base


def _measure(v, normals, keyframes, images, views, footprint, quad, t1, t2,
             offsets: np.ndarray, s: PhotometricConfig):
    """Per vertex the best offset along the normal and its confidence (0: not measured)."""
    n, D = len(v), len(offsets)
    r = s.patch_radius
    g = np.arange(-r, r + 1, dtype=float)
    gu, gv = np.meshgrid(g, g, indexing="ij")
    gu, gv = gu.ravel(), gv.ravel()  # (G,)
    todo = np.flatnonzero(views[:, 1] >= 0)
    step = s.patch_step_px * footprint[todo]  # mm
    base = _patch_points(*(np.ascontiguousarray(x[todo], float) for x in (v, t1, t2, normals,
                                                                           quad)),
                         step, gu, gv)
    rotations = np.ascontiguousarray([kf.R for kf in keyframes], float)
    translations = np.ascontiguousarray([kf.t for kf in keyframes], float)
    cameras = np.ascontiguousarray([[kf.intrinsics.fx, kf.intrinsics.fy, kf.intrinsics.cx,
                                     kf.intrinsics.cy, kf.intrinsics.k1, kf.intrinsics.k2]
                                    for kf in keyframes], float)
    score = np.zeros((len(todo), D))
    todo_views = np.ascontiguousarray(views[todo], np.int64)
    todo_normals = np.ascontiguousarray(normals[todo], float)
    parts = np.array_split(np.arange(len(todo), dtype=np.int64), 8 * FIT_THREADS)
    with ThreadPoolExecutor(FIT_THREADS) as pool:  # the kernel lets go of the GIL
        list(pool.map(lambda rows: _patch_scores(base, todo_normals, todo_views, offsets,
                                                 images, rotations, translations, cameras,
                                                 rows, score), parts))
    j = np.argmax(score, axis=1)
    rows = np.arange(len(todo))
    peak = score[rows, j]
    inner = (j > 0) & (j < D - 1)
    sl, sr = score[rows, np.clip(j - 1, 0, D - 1)], score[rows, np.clip(j + 1, 0, D - 1)]
    denom = sl - 2 * peak + sr
    frac = np.where(inner & (denom < 0), 0.5 * (sl - sr) / np.where(denom < 0, denom, -1), 0.0)
    best_d, conf = np.zeros(n), np.zeros(n)
    best_d[todo] = offsets[j] + frac * (offsets[1] - offsets[0])
    conf[todo] = np.where(inner, np.maximum(peak - score.mean(axis=1), 0.0), 0.0)
    return best_d, conf


def refine(vertices: np.ndarray, faces: np.ndarray, keyframes,
           settings: PhotometricConfig | None = None) -> tuple[np.ndarray, dict]:
    """The mesh's vertices moved along their normals to where the keyframes agree; and a
    log: per round, its reach, the vertices measured, their median confidence, the mean
    move, its seconds. Fewer than two keyframes measure nothing: the mesh as given."""
    s = settings or PhotometricConfig()
    start = np.asarray(vertices, float)
    if len(keyframes) < 2 or s.rounds == 0:
        return start.copy(), {"rounds": [], "seconds": 0.0}
    t_start = time.perf_counter()
    f = np.asarray(faces, np.int64)
    n = len(start)
    # Offsets are along the fitted mesh's normals, and the fit's surface is their prior.
    start_normals = vertex_normals(start, f)
    v, offset = start.copy(), np.zeros(n)
    # Each vertex's latest measurement (the offset it asks for, its weight): a later round's
    # narrower search leaves some vertices unmeasured, and they keep what they had.
    target, weight = np.zeros(n), np.zeros(n)
    ring_i, ring_j, laplacian = _graph(f, n)
    images = np.ascontiguousarray(np.stack([_grey(kf.image) for kf in keyframes]))
    margin_px = s.patch_radius * s.patch_step_px + 2.0
    rounds, typical = [], None
    for rnd in range(s.rounds):
        t0 = time.perf_counter()
        normals = vertex_normals(v, f)
        scene = RaycastScene()
        scene.add(v, f)
        views, footprint = _views_per_vertex(scene, v, normals, keyframes, margin_px)
        t1, t2 = _tangents(normals)
        quad = _quadrics(v, normals, t1, t2, ring_i, ring_j)
        reach = s.search_mm * SHRINK ** rnd
        offsets = np.linspace(-reach, reach, CANDIDATES)
        d, conf = _measure(v, normals, keyframes, images, views, footprint, quad, t1, t2,
                           offsets, s)
        ok = conf > 0
        # The first round's median confidence, at the widest reach (later rounds' are lower).
        if typical is None:
            typical = float(np.median(conf[ok])) if ok.any() else 1.0
        scale = typical if s.confidence_scale is None else s.confidence_scale
        w = np.where(ok & (conf >= MIN_CONFIDENCE * typical),
                     np.minimum(conf / scale, MAX_WEIGHT), 0.0)
        new = w > 0
        # The offset along the start normal that reaches the measured point's tangent plane.
        along = np.maximum(np.einsum("ij,ij->i", normals, start_normals), 0.5)
        target[new], weight[new] = offset[new] + d[new] / along[new], w[new]
        measured = weight > 0
        delta = np.zeros(n)
        if measured.any():
            # The shape from the images, the position from the cloud: the measurements'
            # weighted mean offset is the lighting's as much as the surface's
            # (docs/fitting.md).
            centred = target - np.average(target[measured], weights=weight[measured])
            a = sp.diags(weight + s.fit_weight + ANCHOR) + s.smoothness * laplacian
            delta = np.clip(spsolve(a.tocsc(), weight * centred) - offset, -reach, reach)
            offset += delta
            v = start + offset[:, None] * start_normals
        rounds.append({"reach_mm": reach, "measured": int(new.sum()),
                       "median_conf": float(np.median(conf[new])) if new.any() else 0.0,
                       "mean_abs_move_mm": float(np.abs(delta[measured]).mean())
                       if measured.any() else 0.0,
                       "seconds": round(time.perf_counter() - t0, 2)})
        log.info("photometric round %d: %s", rnd, rounds[-1])
    return v, {"rounds": rounds, "seconds": round(time.perf_counter() - t_start, 2)}
