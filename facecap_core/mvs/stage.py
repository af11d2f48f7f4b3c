"""The MVS stage cut where the service fans it out: view selection once, one depth map per
keyframe (independent calls, any worker), then fusion of all maps.

Inputs are files: keyframe PNGs (:mod:`facecap_core.frames`), the metric ``cameras.json``
and ``coarse.ply`` of the coarse stage, and optionally the pose stage's ``sparse.npz``
(sparse points + visibility, in the pose stage's units: ``metric_scale`` converts them).

    views_main   -> views.json          sources of every keyframe (frame indices)
    depth_main   -> depth_<index>.npz   filtered depth, normal, cost (see save_depth_maps)
    fusion_main  -> cloud.ply           fused points with normals and colours, fusion.json
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from facecap_core.camera import CameraSet, Intrinsics, read_cameras_json
from facecap_core.config import MVSConfig
from facecap_core.errors import InputError
from facecap_core.frames import load_frame
from facecap_core.meshio import load_mesh
from facecap_core.mvs.filtering import geometric_filter
from facecap_core.mvs.fusion import fuse, write_ply
from facecap_core.mvs.images import MVSView, prepare_view
from facecap_core.mvs.patchmatch import DepthMap
from facecap_core.mvs.pipeline import choose_sources, compute_depth_map, save_depth_maps, sparse_from_mesh

DEPTH_FIELDS = {
    "processing_width", "depth_margin_mm", "head_dilation_px", "init_from_coarse", "iterations",
    "neighbours", "refine_trials", "normal_perturbation_deg", "window_radius", "window_step",
    "presmooth_sigma", "sigma_color", "sigma_spatial", "num_best_views", "seed", "max_cost",
    "coarse_max_distance_mm"}
"""MVSConfig fields a single depth map depends on (its cache key holds only these)."""
VIEW_FIELDS = {"processing_width", "num_sources", "view_theta0_deg", "view_sigma1", "view_sigma2",
               "max_reference_views"}
"""MVSConfig fields the view selection depends on."""
FUSION_FIELDS = {"processing_width", "fusion_max_depth_mm", "fusion_max_reprojection_px",
                 "fusion_max_normal_deg", "min_consistent_views"}
"""MVSConfig fields the consistency filter and the fusion depend on."""


def config_part(config: MVSConfig, fields: set[str]) -> dict:
    """The part of the MVS config one sub-stage depends on (JSON data)."""
    return {k: v for k, v in config.model_dump(mode="json").items() if k in fields}


def load_view(frames_dir: str | Path, cams: CameraSet, index: int, width: int) -> MVSView:
    R, t = cams.pose(index)
    return prepare_view(index, load_frame(frames_dir, index), cams.intrinsics, R, t, width)


def _metric_cameras(cameras_json: str | Path) -> CameraSet:
    cams = read_cameras_json(cameras_json)
    if cams.units != "mm":
        raise InputError(f"{cameras_json} is not metric (units: {cams.units}); MVS needs the "
                         "coarse stage's cameras in mm")
    return cams


def views_main(frames_dir: str | Path, cameras_json: str | Path, coarse_ply: str | Path,
               out_dir: str | Path, config: MVSConfig | None = None,
               sparse_npz: str | Path | None = None) -> Path:
    """The keyframes MVS works on (:func:`reference_views`) and each one's sources among
    them by the paper's score; writes ``views.json``."""
    config = config or MVSConfig()
    cams = _metric_cameras(cameras_json)
    if len(cams.frame_indices) < 2:
        raise InputError(f"multi-view stereo needs at least 2 keyframes; got "
                         f"{len(cams.frame_indices)}")
    # MVS works on the references alone: every depth map's sources then have depth maps too,
    # which the consistency filter and the fusion check it against.
    count = len(cams.frame_indices)
    references = reference_views(count, config.max_reference_views)
    # Only cameras matter for the score: views without images are enough.
    views = [MVSView(cams.frame_indices[k], cams.intrinsics, cams.R[k], cams.t[k],
                     np.zeros((1, 1, 3), np.uint8), np.zeros((1, 1), np.float32))
             for k in references]
    source = "sparse points"
    points = visibility = None
    if sparse_npz is not None and Path(sparse_npz).is_file():
        with np.load(sparse_npz) as z:
            points, visibility = z["points"] * float(cams.metric_scale or 1.0), z["visibility"]
        if visibility.shape != (count, len(points)) or len(points) < 10:
            points = visibility = None
        else:
            visibility = visibility[references]
    if points is None:
        coarse = load_mesh(coarse_ply, "coarse mesh")
        points, visibility = sparse_from_mesh(views, coarse.vertices, coarse.faces)
        source = "coarse mesh vertices"
    sources = choose_sources(views, points, visibility, config)
    for i, s in enumerate(sources):
        if len(s) == 0:
            raise InputError(f"keyframe {views[i].index} shares no sparse point with any other "
                             "keyframe; it cannot be matched")
    path = Path(out_dir) / "views.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({
        "scored_with": source,
        "sources": {str(views[i].index): [int(views[j].index) for j in s]
                    for i, s in enumerate(sources)}}, indent=1))
    return path


def reference_views(count: int, limit: int) -> list[int]:
    """At most ``limit`` of ``count`` keyframes (positions in sweep order), evenly spaced
    and including both ends."""
    return sorted({int(round(x)) for x in np.linspace(0, count - 1, min(count, limit))})


def read_views(views_json: str | Path) -> dict[int, list[int]]:
    doc = json.loads(Path(views_json).read_text())
    return {int(k): [int(j) for j in v] for k, v in doc["sources"].items()}


def depth_main(index: int, frames_dir: str | Path, cameras_json: str | Path,
               views_json: str | Path, coarse_ply: str | Path, out_dir: str | Path,
               config: MVSConfig | None = None) -> Path:
    """One keyframe's filtered depth map; writes ``depth_<index>.npz`` and returns it."""
    config = config or MVSConfig()
    cams = _metric_cameras(cameras_json)
    sources = read_views(views_json)
    if int(index) not in sources:
        raise InputError(f"keyframe {index} is not in {views_json}")
    coarse = load_mesh(coarse_ply, "coarse mesh")
    ref = load_view(frames_dir, cams, index, config.processing_width)
    srcs = [load_view(frames_dir, cams, j, config.processing_width) for j in sources[int(index)]]
    _, filtered = compute_depth_map(ref, srcs, coarse.vertices, coarse.faces, config)
    [path] = save_depth_maps([filtered], out_dir)
    meta = {"index": int(index), "seconds": round(filtered.seconds, 3),
            "cpu_seconds": round(filtered.cpu_seconds, 3),
            "valid_pixels": int(filtered.valid.sum())}
    (Path(out_dir) / f"depth_{int(index):05d}.json").write_text(json.dumps(meta))
    return path


def load_depth_map(path: str | Path) -> DepthMap:
    """A depth map written by :func:`save_depth_maps`."""
    with np.load(path) as z:
        w, h = (int(v) for v in z["size"])
        K = z["K"]
        intr = Intrinsics(w, h, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
        index = int(Path(path).stem.split("_")[-1])
        return DepthMap(index, z["depth"], z["normal"], z["cost"], intr, z["R"], z["t"],
                        z["sources"])


def fusion_main(depth_npzs: list[str | Path], frames_dir: str | Path, cameras_json: str | Path,
                out_dir: str | Path, config: MVSConfig | None = None) -> Path:
    """Consistency-filter and fuse the depth maps; writes ``cloud.ply`` and ``fusion.json``."""
    config = config or MVSConfig()
    start = time.perf_counter()
    cams = _metric_cameras(cameras_json)
    maps = sorted((load_depth_map(p) for p in depth_npzs), key=lambda m: m.index)
    if len(maps) < 2:
        raise InputError(f"fusion needs at least 2 depth maps; got {len(maps)}")
    images = [load_view(frames_dir, cams, m.index, config.processing_width).rgb for m in maps]
    maps = geometric_filter(maps, config.min_consistent_views, config.fusion_max_depth_mm,
                            config.fusion_max_reprojection_px, config.fusion_max_normal_deg)
    cloud = fuse(maps, images, config.min_consistent_views, config.fusion_max_depth_mm,
                 config.fusion_max_reprojection_px, config.fusion_max_normal_deg)
    if len(cloud.points) == 0:
        raise InputError("fusion kept no point: no two depth maps agree (check the cameras and "
                         "the coarse mesh)")
    out = Path(out_dir)
    ply = write_ply(cloud, out / "cloud.ply")
    (out / "fusion.json").write_text(json.dumps({
        "points": len(cloud.points), "depth_maps": len(maps),
        "seconds": round(time.perf_counter() - start, 2)}))
    return ply
