"""One keyframe's depth map: the coarse mesh's prior, PatchMatch and the per-map filter
(the MVS stage's fan-out unit, one artifact per reference keyframe).

    main(index, frames, cameras.json, views.json, coarse.ply, out) -> depth_<index>.npz
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from facecap_core.camera import Intrinsics
from facecap_core.config import DepthMapConfig
from facecap_core.errors import InputError
from facecap_core.meshio import load_mesh
from facecap_core.mvs.filtering import filter_with_prior
from facecap_core.mvs.images import MVSView, load_view, metric_cameras
from facecap_core.mvs.patchmatch import DepthMap, patchmatch_depth
from facecap_core.mvs.prior import coarse_prior
from facecap_core.mvs.sweep import sweep_depth
from facecap_core.mvs.views import read_views

log = logging.getLogger(__name__)


def depth_map_name(index: int) -> str:
    """File of one keyframe's depth map (:func:`save_depth_map`)."""
    return f"depth_{int(index):05d}.npz"


def compute_depth_map(ref: MVSView, sources: list[MVSView], coarse_vertices: np.ndarray,
                      coarse_faces: np.ndarray, config: DepthMapConfig
                      ) -> tuple[DepthMap, DepthMap]:
    """One keyframe's depth map: coarse prior, PatchMatch or the plane sweep
    (``config.method``), coarse-mesh filter.

    Returns (raw, filtered); both carry depth, camera-frame normal and cost maps.
    """
    prior = coarse_prior(ref, coarse_vertices, coarse_faces, config.depth_margin_mm,
                         config.head_dilation_px)
    if config.method == "sweep":
        raw = sweep_depth(ref, sources, prior, config.depth_margin_mm, config.sweep_step_mm,
                          config.window_radius, config.num_best_views)
    else:
        raw = patchmatch_depth(ref, sources, prior, config)
    filtered = filter_with_prior(raw, prior, config.max_cost, config.coarse_max_distance_mm,
                                 config.depth_margin_mm)
    return raw, filtered


def save_depth_map(depth: DepthMap, folder: str | Path) -> Path:
    """``depth_<index>.npz`` (depth, normal, cost, K, size, R, t, sources)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / depth_map_name(depth.index)
    tmp = folder / f".{path.stem}.part.npz"
    np.savez_compressed(tmp, depth=depth.depth, normal=depth.normal, cost=depth.cost,
                        K=depth.intr.K, size=np.array([depth.intr.width, depth.intr.height]),
                        R=depth.R, t=depth.t,
                        sources=np.asarray(depth.sources if depth.sources is not None else []))
    tmp.replace(path)
    return path


def load_depth_map(path: str | Path) -> DepthMap:
    """A depth map written by :func:`save_depth_map`."""
    with np.load(path) as z:
        w, h = (int(v) for v in z["size"])
        K = z["K"]
        intr = Intrinsics(w, h, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
        index = int(Path(path).stem.split("_")[-1])
        return DepthMap(index, z["depth"], z["normal"], z["cost"], intr, z["R"], z["t"],
                        z["sources"])


def main(index: int, frames_dir: str | Path, cameras_json: str | Path,
               views_json: str | Path, coarse_ply: str | Path, out_dir: str | Path,
               config: DepthMapConfig | None = None) -> Path:
    """One keyframe's filtered depth map; writes ``depth_<index>.npz`` and returns it."""
    config = config or DepthMapConfig()
    cams = metric_cameras(cameras_json)
    sources = read_views(views_json)
    if int(index) not in sources:
        raise InputError(f"keyframe {index} is not in {views_json}")
    coarse = load_mesh(coarse_ply, "coarse mesh")
    ref = load_view(frames_dir, cams, index, config.processing_width)
    srcs = [load_view(frames_dir, cams, j, config.processing_width) for j in sources[int(index)]]
    _, filtered = compute_depth_map(ref, srcs, coarse.vertices, coarse.faces, config)
    path = save_depth_map(filtered, out_dir)
    meta = {"index": int(index), "seconds": round(filtered.seconds, 3),
            "cpu_seconds": round(filtered.cpu_seconds, 3),
            "valid_pixels": int(filtered.valid.sum())}
    path.with_suffix(".json").write_text(json.dumps(meta))
    log.info("depth map of keyframe %d: %d valid pixels (%.0f %%) from %d source views in "
             "%.1f s", int(index), meta["valid_pixels"], 100.0 * filtered.valid.mean(),
             len(srcs), filtered.seconds)
    return path
