"""The MVS stage cut where the service fans it out: view selection once, one depth map per
keyframe (independent calls, any worker), then fusion of all maps.

Inputs are files: keyframe PNGs (:mod:`facecap_core.frames`), the metric ``cameras.json``
and ``coarse.ply`` of the coarse stage, and optionally the pose stage's ``sparse.npz``
(sparse points + visibility, in the pose stage's units: ``metric_scale`` converts them).

    views_main   -> views.json          sources of every keyframe (frame indices)
    depth_main   -> depth_<index>.npz   filtered depth, normal, cost (see save_depth_map)
    fusion_main  -> cloud.ply           fused points with normals and colours, fusion.json
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from facecap_core.camera import CameraSet, Intrinsics, read_cameras_json
from facecap_core.config import DepthMapConfig, FusionConfig, ViewSelectionConfig
from facecap_core.errors import InputError
from facecap_core.frames import load_frame
from facecap_core.meshio import load_mesh
from facecap_core.mvs.filtering import filter_with_prior, geometric_filter
from facecap_core.mvs.fusion import fuse, write_ply
from facecap_core.mvs.images import MVSView, prepare_view
from facecap_core.mvs.patchmatch import DepthMap, patchmatch_depth
from facecap_core.mvs.prior import coarse_prior
from facecap_core.mvs.views import pair_scores, select_sources, visible_points

VIEWS = "views.json"
CLOUD = "cloud.ply"
FUSION = "fusion.json"


def depth_map_name(index: int) -> str:
    """File of one keyframe's depth map (:func:`save_depth_map`)."""
    return f"depth_{int(index):05d}.npz"


def choose_sources(views: list[MVSView], points: np.ndarray, visibility: np.ndarray,
                   config: ViewSelectionConfig) -> list[np.ndarray]:
    """Indices (into ``views``) of each view's sources by the paper's view-selection score."""
    centres = np.stack([v.centre for v in views])
    scores = pair_scores(points, visibility, centres, config.theta0_deg, config.sigma1,
                         config.sigma2)
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
                      coarse_faces: np.ndarray, config: DepthMapConfig
                      ) -> tuple[DepthMap, DepthMap]:
    """One keyframe's depth map: coarse prior, PatchMatch, coarse-mesh filter.

    Returns (raw, filtered); both carry depth, camera-frame normal and cost maps.
    """
    prior = coarse_prior(ref, coarse_vertices, coarse_faces, config.depth_margin_mm,
                         config.head_dilation_px)
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
               out_dir: str | Path, config: ViewSelectionConfig | None = None,
               sparse_npz: str | Path | None = None) -> Path:
    """The keyframes MVS works on (:func:`reference_views`) and each one's sources among
    them by the paper's score; writes ``views.json``."""
    config = config or ViewSelectionConfig()
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
    path = Path(out_dir) / VIEWS
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
               config: DepthMapConfig | None = None) -> Path:
    """One keyframe's filtered depth map; writes ``depth_<index>.npz`` and returns it."""
    config = config or DepthMapConfig()
    cams = _metric_cameras(cameras_json)
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


def fusion_main(depth_npzs: list[str | Path], frames_dir: str | Path, cameras_json: str | Path,
                out_dir: str | Path, config: FusionConfig | None = None) -> Path:
    """Consistency-filter and fuse the depth maps; writes ``cloud.ply`` and ``fusion.json``."""
    config = config or FusionConfig()
    start = time.perf_counter()
    cams = _metric_cameras(cameras_json)
    maps = sorted((load_depth_map(p) for p in depth_npzs), key=lambda m: m.index)
    if len(maps) < 2:
        raise InputError(f"fusion needs at least 2 depth maps; got {len(maps)}")
    # The colours at the depth maps' own resolution (the depth stage's processing width).
    images = [load_view(frames_dir, cams, m.index, m.intr.width).rgb for m in maps]
    maps = geometric_filter(maps, config.min_consistent_views, config.max_depth_mm,
                            config.max_reprojection_px, config.max_normal_deg)
    cloud = fuse(maps, images, config.min_consistent_views, config.max_depth_mm,
                 config.max_reprojection_px, config.max_normal_deg)
    if len(cloud.points) == 0:
        raise InputError("fusion kept no point: no two depth maps agree (check the cameras and "
                         "the coarse mesh)")
    out = Path(out_dir)
    ply = write_ply(cloud, out / CLOUD)
    (out / FUSION).write_text(json.dumps({
        "points": len(cloud.points), "depth_maps": len(maps),
        "seconds": round(time.perf_counter() - start, 2)}))
    return ply
