"""Fusing depth maps into one point cloud with normals and colours (Gipuma's fusion).

Each reference pixel with a depth is projected into the other depth maps; where at least
``min_consistent_views`` of them agree (depth, round-trip reprojection and normal, see
:func:`~facecap_core.mvs.filtering.agreement`) the agreeing 3D points, normals and colours
are averaged into one output point, and the pixels used are marked so that the same surface
point is not emitted again from another view. Each point keeps its measured uncertainty: the
spread (standard deviation, mm) of the agreeing views' points along its normal. The views'
errors are independent (each its own window, sources and noise), so where they scatter the
surface is uncertain, however densely it is sampled; the fit weighs each point by it.
"""

from __future__ import annotations

import json
import logging
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydantic import Field

from facecap_core.camera import CAMERAS_JSON
from facecap_core.config import StrictModel
from facecap_core.errors import InputError
from facecap_core.lazy import LazyModule
from facecap_core.mvs import depth
from facecap_core.mvs.depth import load_depth_map
from facecap_core.mvs.filtering import _partners, agreement, backproject, geometric_filter
from facecap_core.mvs.images import load_view, metric_cameras
from facecap_core.mvs.patchmatch import DepthMap
from facecap_core.stage import Folders, Stage

o3d = LazyModule("open3d")


class FusionConfig(StrictModel):
    """The consistency filter across depth maps and their fusion into one cloud
    (``mvs.fusion``)."""

    max_depth_mm: float = Field(1.0, gt=0)
    """A source agrees when its depth differs by at most this from the reprojection."""
    max_reprojection_px: float = Field(1.0, gt=0)
    """... and the round trip through its depth lands within this many pixels."""
    max_normal_deg: float = Field(30.0, gt=0, le=180)
    """... and its normal is within this angle."""
    min_consistent_views: int = Field(2, ge=1, le=64)
    """Source views that must agree with a reference pixel to make a point."""


log = logging.getLogger(__name__)

CLOUD = "cloud.ply"
FUSION = "fusion.json"
FUSION_THREADS = 2
"""Threads that load the depth maps and images and check each map against the others
(the fusion itself goes map after map: each map's points use up its partners' pixels)."""


@dataclass
class PointCloud:
    """Fused points (N, 3) mm world frame, unit normals (N, 3), uint8 colours (N, 3),
    how many views each point was seen consistently in, and the spread (N,) mm of those
    views' points along the normal (their sample standard deviation)."""

    points: np.ndarray
    normals: np.ndarray
    colors: np.ndarray
    views: np.ndarray
    spread: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.points)


def fuse(maps: list[DepthMap], images: list[np.ndarray] | None = None,
         min_consistent_views: int = 2, max_depth_mm: float = 1.0,
         max_reprojection_px: float = 1.0, max_normal_deg: float = 30.0) -> PointCloud:
    """Fuse depth maps; ``images`` are the RGB images (same size) aligned with ``maps``."""
    if images is not None and len(images) != len(maps):
        raise InputError(f"fusion: {len(images)} images for {len(maps)} depth maps")
    used = [np.zeros(m.depth.shape, bool) for m in maps]
    out_p, out_n, out_c, out_v, out_s = [], [], [], [], []
    for i, dm in enumerate(maps):
        rows, cols = np.nonzero((dm.depth > 0) & ~used[i])
        if len(rows) == 0:
            continue
        pts, nrm = backproject(dm, rows, cols)
        s_p, s_n = pts.copy(), nrm.copy()
        s_c = (images[i][rows, cols].astype(float) if images is not None
               else np.zeros((len(rows), 3)))
        count = np.ones(len(rows), np.int32)
        # Depths along the reference normal, relative to the reference point (no cancellation).
        s_d, s_dd = np.zeros(len(rows)), np.zeros(len(rows))
        contrib = []
        for j in _partners(maps, i):
            if j == i:
                continue
            ok, orow, ocol, o_p, o_n = agreement(pts, nrm, rows, cols, dm, maps[j],
                                                 max_depth_mm, max_reprojection_px,
                                                 max_normal_deg)
            ok &= ~used[j][orow, ocol]
            s_p[ok] += o_p[ok]
            s_n[ok] += o_n[ok]
            d = np.einsum("ij,ij->i", o_p - pts, nrm)
            s_d[ok] += d[ok]
            s_dd[ok] += d[ok] ** 2
            if images is not None:
                s_c[ok] += images[j][orow[ok], ocol[ok]]
            count += ok
            contrib.append((j, ok, orow, ocol))
        keep = count - 1 >= min_consistent_views
        for j, ok, orow, ocol in contrib:
            sel = ok & keep
            used[j][orow[sel], ocol[sel]] = True
        used[i][rows[keep], cols[keep]] = True
        c = count[keep][:, None]
        n = s_n[keep]
        out_p.append(s_p[keep] / c)
        out_n.append(n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12))
        out_c.append(np.clip(np.rint(s_c[keep] / c), 0, 255).astype(np.uint8))
        out_v.append(count[keep])
        k = count[keep].astype(float)
        var = (s_dd[keep] - s_d[keep] ** 2 / k) / np.maximum(k - 1, 1)
        out_s.append(np.sqrt(np.maximum(var, 0.0)))
    if not out_p:
        return PointCloud(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3), np.uint8),
                          np.zeros(0, np.int32), np.zeros(0))
    return PointCloud(np.concatenate(out_p), np.concatenate(out_n), np.concatenate(out_c),
                      np.concatenate(out_v), np.concatenate(out_s))


def write_ply(cloud: PointCloud, path: str | Path) -> Path:
    """Binary PLY with positions, normals, colours and, when known, each point's ``spread``
    (mm) and ``views`` as scalar properties (MeshLab, CloudCompare, open3d); written to a temporary name
    first so a crash never leaves half a file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    pc = o3d.t.geometry.PointCloud()
    pc.point.positions = o3d.core.Tensor(np.asarray(cloud.points, np.float64).reshape(-1, 3))
    pc.point.normals = o3d.core.Tensor(np.asarray(cloud.normals, np.float64).reshape(-1, 3))
    pc.point.colors = o3d.core.Tensor(np.asarray(cloud.colors, np.uint8).reshape(-1, 3))
    if cloud.spread is not None:
        pc.point.spread = o3d.core.Tensor(np.asarray(cloud.spread, np.float32).reshape(-1, 1))
        pc.point.views = o3d.core.Tensor(np.asarray(cloud.views, np.float32).reshape(-1, 1))
    tmp = path.with_name(f".{path.stem}.part{path.suffix}")
    if not o3d.t.io.write_point_cloud(str(tmp), pc, write_ascii=False):
        raise InputError(f"could not write the point cloud to {path}")
    os.replace(tmp, path)
    return path


def main(depth_npzs: list[str | Path], frames_dir: str | Path, cameras_json: str | Path,
                out_dir: str | Path, config: FusionConfig | None = None) -> Path:
    """Consistency-filter and fuse the depth maps; writes ``cloud.ply`` and ``fusion.json``."""
    config = config or FusionConfig()
    start = time.perf_counter()
    cams = metric_cameras(cameras_json)
    with ThreadPoolExecutor(FUSION_THREADS) as pool:  # zlib and PNG decoding let go of the GIL
        maps = sorted(pool.map(load_depth_map, depth_npzs), key=lambda m: m.index)
        if len(maps) < 2:
            raise InputError(f"fusion needs at least 2 depth maps; got {len(maps)}")
        # The colours at the depth maps' own resolution (the depth stage's processing width).
        images = list(pool.map(lambda m: load_view(frames_dir, cams, m.index,
                                                   m.intr.width).rgb, maps))
    maps = geometric_filter(maps, config.min_consistent_views, config.max_depth_mm,
                            config.max_reprojection_px, config.max_normal_deg,
                            threads=FUSION_THREADS)
    cloud = fuse(maps, images, config.min_consistent_views, config.max_depth_mm,
                 config.max_reprojection_px, config.max_normal_deg)
    if len(cloud.points) == 0:
        raise InputError("fusion kept no point: no two depth maps agree (check the cameras and "
                         "the coarse mesh)")
    out = Path(out_dir)
    ply = write_ply(cloud, out / CLOUD)
    seconds = round(time.perf_counter() - start, 2)
    (out / FUSION).write_text(json.dumps({
        "points": len(cloud.points), "depth_maps": len(maps), "seconds": seconds}))
    log.info("fused %d points from %d depth maps in %.1f s", len(cloud.points), len(maps),
             seconds)
    return ply


def run(inputs: Folders, out: Path, config: FusionConfig, params: dict) -> None:
    maps = sorted(p for name, folder in inputs.items() if depth.STAGE.is_row(name)
                  for p in folder.glob("depth_*.npz"))
    main(maps, inputs["frames"], inputs["coarse"] / CAMERAS_JSON, out, config)


STAGE = Stage("fusion", version="2", inputs=("frames", "coarse", "depth"),
              work_seconds=3.5,
              section="mvs.fusion", run=run, outputs=(CLOUD, FUSION), exported=(CLOUD,))
