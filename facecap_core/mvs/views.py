"""Source-view selection: the paper's pairwise score over shared sparse points.

``s(i, j) = sum_p G(theta_ij(p))`` over the sparse points seen by both keyframes, where
``theta_ij(p)`` is the angle (degrees) at ``p`` between the rays to the two camera centres
and ``G`` is a piecewise Gaussian peaking at ``theta0``: pairs with a ~10° baseline angle
triangulate well, while tiny angles (no depth signal) and large ones (appearance changes,
occlusion) are scored down. MVSNet's score, as used by Agrawal et al. 2020.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
from pydantic import Field

from facecap_core.camera import CAMERAS_JSON, camera_center, project
from facecap_core.coarse import COARSE_PLY
from facecap_core.config import StrictModel
from facecap_core.errors import InputError
from facecap_core.meshio import load_mesh
from facecap_core.mvs.images import MVSView, metric_cameras
from facecap_core.pose.stage import SPARSE
from facecap_core.render import RaycastScene
from facecap_core.stage import Folders, Stage


class ViewSelectionConfig(StrictModel):
    """Which keyframes get a depth map and which keyframes each one is matched against
    (``mvs.views``; the paper's view-selection score)."""

    num_sources: int = Field(12, ge=1, le=64)
    """Source views per reference view, the best by the view-selection score."""
    max_reference_views: int = Field(40, ge=2, le=4096)
    """MVS uses at most this many keyframes, evenly spaced along the sweep: one depth map
    each, sources among them. Neighbouring keyframes of a dense sweep see nearly the same
    surface: beyond about 40 maps the cloud gains little, and the stage, the pipeline's
    slowest, grows linearly."""
    theta0_deg: float = Field(10.0, gt=0, lt=90)
    """Preferred baseline angle theta0 of the view-selection score."""
    sigma1: float = Field(5.0, gt=0)
    """Spread (degrees) of the score below theta0."""
    sigma2: float = Field(10.0, gt=0)
    """Spread (degrees) of the score above theta0."""


log = logging.getLogger(__name__)

VIEWS = "views.json"


def gaussian_score(theta_deg: np.ndarray, theta0: float = 10.0, sigma1: float = 5.0,
                   sigma2: float = 10.0) -> np.ndarray:
    """Piecewise Gaussian G(theta): sigma1 below theta0, sigma2 above, 1 at theta0."""
    theta = np.asarray(theta_deg, float)
    sigma = np.where(theta <= theta0, sigma1, sigma2)
    return np.exp(-((theta - theta0) ** 2) / (2.0 * sigma ** 2))


def pair_scores(points: np.ndarray, visibility: np.ndarray, centres: np.ndarray,
                theta0: float = 10.0, sigma1: float = 5.0, sigma2: float = 10.0) -> np.ndarray:
    """Score matrix (K, K) for K cameras; the diagonal is 0.

    ``points`` (N, 3) sparse points, ``visibility`` (K, N) bool: keyframe k sees point n,
    ``centres`` (K, 3) camera centres, all in the same world frame.
    """
    points = np.asarray(points, float)
    vis = np.asarray(visibility, bool)
    centres = np.asarray(centres, float)
    if points.ndim != 2 or points.shape[1] != 3:
        raise InputError(f"sparse points must be (N, 3); got {points.shape}")
    if vis.shape != (len(centres), len(points)):
        raise InputError(f"visibility must be (cameras, points) = ({len(centres)}, "
                         f"{len(points)}); got {vis.shape}")
    # Unit rays from every point to every camera centre: (K, N, 3).
    rays = centres[:, None, :] - points[None, :, :]
    rays /= np.maximum(np.linalg.norm(rays, axis=-1, keepdims=True), 1e-12)
    k = len(centres)
    scores = np.zeros((k, k))
    for i in range(k):
        for j in range(i + 1, k):
            both = vis[i] & vis[j]
            if not both.any():
                continue
            cos = np.clip(np.sum(rays[i, both] * rays[j, both], axis=-1), -1.0, 1.0)
            s = gaussian_score(np.degrees(np.arccos(cos)), theta0, sigma1, sigma2).sum()
            scores[i, j] = scores[j, i] = s
    return scores


def select_sources(scores: np.ndarray, num_sources: int = 12) -> list[np.ndarray]:
    """For each reference, the indices of its ``num_sources`` best-scoring other views
    (best first); views sharing no point (score 0) are never chosen."""
    scores = np.asarray(scores, float)
    out = []
    for i in range(len(scores)):
        order = [j for j in np.argsort(-scores[i], kind="stable") if j != i and scores[i, j] > 0]
        out.append(np.asarray(order[:num_sources], dtype=np.int64))
    return out


def visible_points(points: np.ndarray, cameras: list, vertices: np.ndarray,
                   faces: np.ndarray, tolerance_mm: float = 0.5) -> np.ndarray:
    """Visibility (K, N) of ``points`` (lying on the mesh) from pinhole ``cameras``
    [(intrinsics, R, t)]: inside the image and not occluded by the mesh (ray casting)."""

    scene = RaycastScene()
    scene.add(vertices, faces)
    points = np.asarray(points, float)
    vis = np.zeros((len(cameras), len(points)), bool)
    for k, (intr, R, t) in enumerate(cameras):
        uv, z = project(points, R, t, intr)
        inside = ((z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= intr.width - 1)
                  & (uv[:, 1] >= 0) & (uv[:, 1] <= intr.height - 1))
        c = camera_center(R, t)
        d = points - c
        dist = np.linalg.norm(d, axis=1)
        hit = scene.cast(np.broadcast_to(c, d.shape), d / dist[:, None])["t_hit"]
        vis[k] = inside & (hit >= dist - tolerance_mm)
    return vis


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


def main(frames_dir: str | Path, cameras_json: str | Path, coarse_ply: str | Path,
               out_dir: str | Path, config: ViewSelectionConfig | None = None,
               sparse_npz: str | Path | None = None) -> Path:
    """The keyframes MVS works on (:func:`reference_views`) and each one's sources among
    them by the paper's score; writes ``views.json``."""
    config = config or ViewSelectionConfig()
    cams = metric_cameras(cameras_json)
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
    log.info("%d of %d keyframes chosen as MVS references, sources scored with %s",
             len(views), count, source)
    return path


def reference_views(count: int, limit: int) -> list[int]:
    """At most ``limit`` of ``count`` keyframes (positions in sweep order), evenly spaced
    and including both ends."""
    return sorted({int(round(x)) for x in np.linspace(0, count - 1, min(count, limit))})


def read_views(views_json: str | Path) -> dict[int, list[int]]:
    doc = json.loads(Path(views_json).read_text())
    return {int(k): [int(j) for j in v] for k, v in doc["sources"].items()}


def run(inputs: Folders, out: Path, config: ViewSelectionConfig, params: dict) -> None:
    main(inputs["frames"], inputs["coarse"] / CAMERAS_JSON, inputs["coarse"] / COARSE_PLY, out,
         config, inputs["poses"] / SPARSE)


STAGE = Stage("views", version="1", inputs=("frames", "coarse", "poses"),
              work_seconds=1.1,
              section="mvs.views", run=run, outputs=(VIEWS,))
