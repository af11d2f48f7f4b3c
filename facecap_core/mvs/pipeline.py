"""The MVS stage end to end: sources per keyframe, depth maps (fanned out), filtering, fusion.

:func:`compute_depth_map` is the unit of work (one reference keyframe, independent of the
others), so an orchestrator can map it over keyframes on any worker; :func:`run_mvs` does
the same on local threads (the numba kernels release the GIL) and fuses the result.
"""

from __future__ import annotations

import json
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from facecap_core.errors import InputError
from facecap_core.mvs.filtering import filter_with_prior, geometric_filter
from facecap_core.mvs.fusion import PointCloud, fuse, write_ply
from facecap_core.mvs.images import MVSView
from facecap_core.mvs.patchmatch import DepthMap, patchmatch_depth
from facecap_core.mvs.prior import coarse_prior
from facecap_core.mvs.views import pair_scores, select_sources, visible_points

from facecap_core.config import MVSConfig


@dataclass
class MVSResult:
    """Depth maps (filtered by the coarse mesh and by consistency), the fused cloud, the
    source views chosen per reference and, if written, the cloud's path."""

    maps: list[DepthMap]
    cloud: PointCloud
    sources: list[np.ndarray]
    raw: list[DepthMap] | None = None
    ply: Path | None = None


def choose_sources(views: list[MVSView], points: np.ndarray, visibility: np.ndarray,
                   config: MVSConfig) -> list[np.ndarray]:
    """Indices (into ``views``) of each view's sources by the paper's view-selection score."""
    centres = np.stack([v.centre for v in views])
    scores = pair_scores(points, visibility, centres, config.view_theta0_deg,
                         config.view_sigma1, config.view_sigma2)
    return select_sources(scores, config.num_sources)


def sparse_from_mesh(views: list[MVSView], vertices: np.ndarray, faces: np.ndarray,
                     count: int = 4000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Sparse points (mesh vertices, subsampled) and their visibility per view, for when
    no structure-from-motion points are at hand."""
    rng = np.random.default_rng(seed)
    v = np.asarray(vertices, float)
    pick = rng.choice(len(v), size=min(count, len(v)), replace=False)
    vis = visible_points(v[pick], [(w.intr, w.R, w.t) for w in views], vertices, faces)
    return v[pick], vis


def compute_depth_map(ref: MVSView, sources: list[MVSView], coarse_vertices: np.ndarray,
                      coarse_faces: np.ndarray, config: MVSConfig) -> tuple[DepthMap, DepthMap]:
    """One keyframe's depth map: coarse prior, PatchMatch, coarse-mesh filter.

    Returns (raw, filtered); both carry depth, camera-frame normal and cost maps.
    """
    prior = coarse_prior(ref, coarse_vertices, coarse_faces, config.depth_margin_mm,
                         config.head_dilation_px)
    raw = patchmatch_depth(ref, sources, prior, config)
    filtered = filter_with_prior(raw, prior, config.max_cost, config.coarse_max_distance_mm,
                                 config.depth_margin_mm)
    return raw, filtered


def run_mvs(views: list[MVSView], coarse_vertices: np.ndarray, coarse_faces: np.ndarray,
            config: MVSConfig | None = None, points: np.ndarray | None = None,
            visibility: np.ndarray | None = None, progress=None) -> MVSResult:
    """Depth maps for every view (``config.workers`` at a time), filtered and fused.

    ``points``/``visibility``: sparse points (N, 3) and (views, N) visibility for the view
    selection; without them the coarse mesh's vertices stand in.
    """
    config = config or MVSConfig()
    if len(views) < 2:
        raise InputError(f"multi-view stereo needs at least 2 keyframes; got {len(views)}")
    if points is None:
        points, visibility = sparse_from_mesh(views, coarse_vertices, coarse_faces)
    sources = choose_sources(views, points, visibility, config)
    for i, s in enumerate(sources):
        if len(s) == 0:
            raise InputError(f"keyframe {views[i].index} shares no sparse point with any "
                             "other keyframe; it cannot be matched")

    def one(i):
        out = compute_depth_map(views[i], [views[j] for j in sources[i]], coarse_vertices,
                                coarse_faces, config)
        if progress:
            progress(i, out[0])
        return out

    with ThreadPoolExecutor(max_workers=config.workers) as pool:
        results = list(pool.map(one, range(len(views))))
    raw = [r[0] for r in results]
    maps = geometric_filter([r[1] for r in results], config.min_consistent_views,
                            config.fusion_max_depth_mm, config.fusion_max_reprojection_px,
                            config.fusion_max_normal_deg)
    cloud = fuse(maps, [v.rgb for v in views], config.min_consistent_views,
                 config.fusion_max_depth_mm, config.fusion_max_reprojection_px,
                 config.fusion_max_normal_deg)
    return MVSResult(maps, cloud, sources, raw)


def save_depth_maps(maps: list[DepthMap], folder: str | Path) -> list[Path]:
    """One ``depth_<index>.npz`` per map (depth, normal, cost, K, R, t, sources)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for m in maps:
        p = folder / f"depth_{m.index:05d}.npz"
        tmp = folder / f".depth_{m.index:05d}.part.npz"
        np.savez_compressed(tmp, depth=m.depth, normal=m.normal, cost=m.cost, K=m.intr.K,
                            size=np.array([m.intr.width, m.intr.height]), R=m.R, t=m.t,
                            sources=np.asarray(m.sources if m.sources is not None else []))
        tmp.replace(p)
        paths.append(p)
    return paths


def main(views: list[MVSView], coarse_vertices: np.ndarray, coarse_faces: np.ndarray,
         out_dir: str | Path, config: MVSConfig | None = None,
         points: np.ndarray | None = None, visibility: np.ndarray | None = None) -> Path:
    """Run the stage and write ``out_dir/{cloud.ply, depth/, mvs.json}``; returns the PLY."""
    config = config or MVSConfig()
    out = Path(out_dir)
    result = run_mvs(views, coarse_vertices, coarse_faces, config, points, visibility)
    save_depth_maps(result.maps, out / "depth")
    ply = write_ply(result.cloud, out / "cloud.ply")
    (out / "mvs.json").write_text(json.dumps({
        "config": config.model_dump(mode="json"),
        "points": len(result.cloud),
        "sources": {int(views[i].index): [int(views[j].index) for j in s]
                    for i, s in enumerate(result.sources)},
        "seconds_per_map": [round(m.seconds, 3) for m in result.raw],
    }, indent=1))
    return ply
