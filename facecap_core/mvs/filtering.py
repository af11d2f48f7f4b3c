"""Cleaning depth maps: the coarse mesh's veto and agreement between views.

PatchMatch returns a depth for every pixel it computed, including ones with no texture,
occluded in most sources, or on the background next to the head. Two independent checks
remove them: (1) the coarse mesh is a few mm off at most, so depths farther from it are
wrong (the paper's filter), as are costs too high to be a match; (2) a depth seen
consistently by other views' depth maps (depth, reprojection and normal agree) is real —
the same test as the fusion's, applied per map.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace

import numpy as np

from facecap_core.mvs.patchmatch import DepthMap
from facecap_core.mvs.prior import CoarsePrior


def filter_with_prior(dm: DepthMap, prior: CoarsePrior, max_cost: float,
                      max_distance_mm: float, margin_mm: float) -> DepthMap:
    """Reject depths with cost above ``max_cost`` or farther than ``max_distance_mm`` from
    the coarse mesh (where the mesh is not hit, from the range of its depths nearby)."""
    d = dm.depth
    near = np.isfinite(prior.depth)
    ref_lo = np.where(near, prior.depth, prior.lo + margin_mm)
    ref_hi = np.where(near, prior.depth, prior.hi - margin_mm)
    keep = ((d > 0) & (dm.cost <= max_cost) & (d >= ref_lo - max_distance_mm)
            & (d <= ref_hi + max_distance_mm))
    return replace(dm, depth=np.where(keep, d, 0).astype(np.float32),
                   normal=np.where(keep[..., None], dm.normal, 0).astype(np.float32))


def backproject(dm: DepthMap, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points and unit normals (N, 3) of the given pixels of a depth map."""
    k = dm.intr
    z = dm.depth[rows, cols].astype(float)
    x_cam = np.stack([(cols - k.cx) / k.fx * z, (rows - k.cy) / k.fy * z, z], 1)
    world = (x_cam - dm.t) @ dm.R  # R.T @ (x - t) per row
    n_world = dm.normal[rows, cols].astype(float) @ dm.R
    return world, n_world


def agreement(points: np.ndarray, normals: np.ndarray, rows: np.ndarray, cols: np.ndarray,
              ref: DepthMap, other: DepthMap, max_depth_mm: float, max_reprojection_px: float,
              max_normal_deg: float):
    """Which reference pixels (rows, cols) with world points/normals ``other`` confirms.

    The point is projected into ``other``; its depth map there must hold a depth within
    ``max_depth_mm`` of the projected depth, whose 3D point projects back into the reference
    within ``max_reprojection_px`` of the pixel, with a normal within ``max_normal_deg``.
    Returns (agree (N,) bool, other's rows, cols (N,), other's points and normals (N, 3)).
    """
    k = other.intr
    x = points @ other.R.T + other.t
    z = x[:, 2]
    zs = np.where(z > 1e-6, z, 1e-6)
    u = k.fx * x[:, 0] / zs + k.cx
    v = k.fy * x[:, 1] / zs + k.cy
    oc = np.rint(u).astype(np.int64)
    orow = np.rint(v).astype(np.int64)
    h, w = other.depth.shape
    inside = (z > 1e-6) & (oc >= 0) & (oc < w) & (orow >= 0) & (orow < h)
    oc = np.where(inside, oc, 0)
    orow = np.where(inside, orow, 0)
    d_other = other.depth[orow, oc]
    agree = inside & (d_other > 0) & (np.abs(d_other - z) <= max_depth_mm)
    o_pts, o_nrm = backproject(other, orow, oc)
    # Round trip: the other view's point seen from the reference.
    kr = ref.intr
    y = o_pts @ ref.R.T + ref.t
    yz = np.where(y[:, 2] > 1e-6, y[:, 2], 1e-6)
    du = kr.fx * y[:, 0] / yz + kr.cx - cols
    dv = kr.fy * y[:, 1] / yz + kr.cy - rows
    agree &= (du * du + dv * dv) <= max_reprojection_px ** 2
    agree &= np.sum(o_nrm * normals, 1) >= np.cos(np.radians(max_normal_deg))
    return agree, orow, oc, o_pts, o_nrm


def _partners(maps: list[DepthMap], i: int) -> list[int]:
    """Maps checked against map i: its source views when known, else all others."""
    by_index = {m.index: j for j, m in enumerate(maps)}
    src = maps[i].sources
    if src is None:
        return [j for j in range(len(maps)) if j != i]
    return [by_index[s] for s in src if s in by_index and by_index[s] != i]


def geometric_filter(maps: list[DepthMap], min_views: int, max_depth_mm: float,
                     max_reprojection_px: float, max_normal_deg: float,
                     threads: int = 1) -> list[DepthMap]:
    """Keep the depths at least ``min_views`` other depth maps agree with. Each map is
    checked against the unfiltered others, so ``threads`` maps at once give the same maps."""

    def filtered(i: int) -> DepthMap:
        dm = maps[i]
        rows, cols = np.nonzero(dm.depth > 0)
        pts, nrm = backproject(dm, rows, cols)
        count = np.zeros(len(rows), np.int32)
        for j in _partners(maps, i):
            count += agreement(pts, nrm, rows, cols, dm, maps[j], max_depth_mm,
                               max_reprojection_px, max_normal_deg)[0]
        keep = np.zeros(dm.depth.shape, bool)
        keep[rows[count >= min_views], cols[count >= min_views]] = True
        return replace(dm, depth=np.where(keep, dm.depth, 0).astype(np.float32),
                       normal=np.where(keep[..., None], dm.normal, 0).astype(np.float32))

    with ThreadPoolExecutor(threads) as pool:  # numpy's array loops let go of the GIL
        return list(pool.map(filtered, range(len(maps))))
