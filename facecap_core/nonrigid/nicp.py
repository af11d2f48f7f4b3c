"""Optimal-step non-rigid ICP of the template to cloud, landmarks, ear points and edges.

:func:`fit` runs the schedule of :class:`~facecap_core.nonrigid.nicp.NicpConfig`: for each
stiffness level (global → local, landmark weight falling with it) up to
``iterations_per_level`` optimal steps; each step recomputes the cloud targets (every
``recompute_every`` steps) and the silhouette targets (every ``edge_recompute_every``) from
the current mesh, then solves the NICP system (:mod:`.solver`). The result keeps the
template's topology exactly: only vertex positions change.
"""

from __future__ import annotations

import logging
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from facecap_core.config import MAX_LEVELS, StrictModel
from facecap_core.errors import InputError
from facecap_core.geometry import umeyama
from facecap_core.nonrigid.constraints import (
    FIT_THREADS,
    CloudGrid,
    Keyframe,
    boundary_distance,
    cloud_targets,
    edge_map,
    edge_targets,
    face_planes,
    landmark_targets,
    nearest_edge_pixels,
)
from facecap_core.nonrigid.roughness import face_vertices
from facecap_core.nonrigid.solver import NicpSystem
from facecap_core.render import RaycastScene, vertex_normals
from facecap_core.template import INNER_LANDMARKS, Template

STIFFNESS_RANGE = (1e-3, 1e4)
"""The stiffness values the solver works with (the template is scaled to unit radius)."""
WEIGHT_MAX = 1e4
"""The largest weight of a landmark (one cloud target weighs ``data_weight``, about 1)."""


class NicpConfig(StrictModel):
    """Non-rigid registration: optimal-step NICP (Amberg et al. 2007) to a fused point
    cloud, 3D landmarks, ear points and keyframe silhouettes (Agrawal et al. 2020, "Mesh
    fitting"). Distances in mm, weights relative to one cloud target. The fitting stage's
    settings (:class:`facecap_core.fitting.settings.NicpConfig`) are these and what the
    stage does with the fitted mesh; the coarse stage's deformation uses these alone."""

    stiffness: list[float] = Field([50.0, 20.0, 10.0, 5.0, 2.0], max_length=MAX_LEVELS)
    """Stiffness alpha per level, from global (large) to local (small) deformation; the
    template is centred and scaled to unit RMS radius, so the values do not depend on units.
    The schedule ends at 2: a last level at 1 follows the MVS noise into millimetre ridges
    on clean renders as on real skin (calibration renders, docs/fitting.md)."""
    landmark_weight: list[float] = Field([50.0, 20.0, 10.0, 5.0, 2.0],
                                         max_length=MAX_LEVELS)
    """Weight of each landmark target per level (same length as ``stiffness``); falls with
    the stiffness so that landmarks place the mesh first and the cloud refines it."""
    iterations_per_level: int = Field(3, ge=1, le=100)
    """Most optimal steps per stiffness level (fewer when the mesh stops moving)."""
    convergence_mm: float = Field(0.02, ge=0, le=10)
    """A level ends early when no vertex moved more than this in its last step."""
    gamma: float = Field(1.0, ge=1e-3, le=1e3)
    """Weight of the translation part against the linear part in the stiffness term."""
    reuse_factorization: bool = True
    """Keep the per-vertex weights fixed within a level, so the matrix is factored once per
    level; vertices that lose their cloud target during the level hold their position."""
    solver: Literal["auto", "cholmod", "scipy"] = "auto"
    """Sparse solver: CHOLMOD via cvxopt (supernodal Cholesky), scipy's SuperLU, or auto."""
    initial_similarity: bool = True
    """Start from a similarity (Umeyama) fit of the template's inner landmarks to the given
    landmarks."""

    use_cloud: bool = True
    """Use the point-cloud constraint (False: the landmarks-only ablation)."""
    use_edges: bool = True
    """Use keyframe silhouette/edge constraints when keyframes are given."""
    use_ear_landmarks: bool = True
    """Use ear points (vertex id, 3D target) when given."""

    data_weight: float = Field(1.0, ge=1e-4, le=1e4)
    """Weight of one point-cloud target."""
    search_radius_mm: tuple[float, float] = (8.0, 3.0)
    """How far along the vertex normal cloud points are accepted, at the first and last
    level (geometric in between): wide while the template is far, tight at the end."""
    normal_distance_mm: float = Field(1.5, gt=0, le=20)
    """Largest distance of an accepted cloud point from the vertex-normal line."""
    min_points: int = Field(3, ge=1, le=1000)
    """Fewest accepted points for a cloud target; vertices with fewer fall back to stiffness."""
    normal_agreement_deg: float = Field(60.0, gt=0, le=180)
    """When the cloud has normals, accept only points whose normal is within this angle of
    the vertex normal (180: no check)."""
    cloud_noise_mm: float | None = Field(0.12, gt=0, le=10)
    """The smoothness follows the cloud's measured noise: when the fused points that give the
    face its targets are less certain than this (their median standard error, from the
    spread of the views that agree on each point), every cloud target weighs
    ``(cloud_noise_mm / noise)²`` of ``data_weight``: the cloud then counts less against the
    stiffness (and against the landmarks, ear points and silhouettes), so the stiffness, not
    the noise, shapes the surface. 0.12 mm is the noise of the clean calibration render (ICT
    identity 11, 640x360: 0.117 mm); held-out clean renders measured 0.094 (ict:12) and
    0.102 mm (the demo) and keep the full weight. None: always ``data_weight``."""
    recompute_every: int = Field(1, ge=1, le=100)
    """Recompute the cloud targets every this many steps (the paper: every few)."""

    ear_weight: float = Field(1.0, ge=0, le=1e4)
    """Ear point weight relative to the level's landmark weight."""

    edge_weight: float = Field(1.0, ge=0, le=1e4)
    """Weight of one silhouette target (per keyframe that sees the vertex on its contour)."""
    edge_recompute_every: int = Field(2, ge=1, le=100)
    """Recompute silhouette vertices and their edge targets every this many steps."""
    edge_first_level: int = Field(1, ge=0, le=MAX_LEVELS)
    """First level (0-based) that uses edges: before it the mesh is too far for a few-pixel
    match."""
    edge_max_px: float = Field(3.0, gt=0, le=100)
    """Largest image distance from a projected contour vertex to its edge pixel."""
    edge_min_cos: float = Field(0.7, ge=0, le=1)
    """The edge pixel must lie along the projected vertex normal: |cos| of the angle at least
    this."""
    edge_blur_sigma: float = Field(1.0, ge=0, le=20)
    """Gaussian blur (px) before Canny."""
    canny_thresholds: tuple[int, int] = (30, 90)
    """Canny hysteresis thresholds on the grey image."""
    edge_boundary_rings: int = Field(4, ge=0, le=100)
    """Template vertices this many edges or fewer from the template's open border never give
    silhouettes (the border is not a real contour)."""

    @model_validator(mode="after")
    def _check_schedule(self):
        if len(self.stiffness) == 0 or len(self.stiffness) != len(self.landmark_weight):
            raise ValueError("stiffness and landmark_weight need the same, non-zero length")
        # The solver's matrix sums stiffness² and weights: values this far apart leave it
        # singular or lose one of the two to rounding (a double has 16 digits).
        if any(not STIFFNESS_RANGE[0] <= a <= STIFFNESS_RANGE[1] for a in self.stiffness) or \
                any(not 0 <= b <= WEIGHT_MAX for b in self.landmark_weight):
            raise ValueError(f"stiffness must lie in [{STIFFNESS_RANGE[0]:g}, "
                             f"{STIFFNESS_RANGE[1]:g}] and landmark_weight in [0, "
                             f"{WEIGHT_MAX:g}]")
        if not 0 <= self.canny_thresholds[0] <= self.canny_thresholds[1] <= 1020:
            raise ValueError("canny_thresholds: (low, high) with 0 <= low <= high <= 1020 "
                             "(Sobel gradients of 8-bit images)")
        if self.search_radius_mm[1] <= self.normal_distance_mm / 2 or \
                self.search_radius_mm[0] < self.search_radius_mm[1] or \
                self.search_radius_mm[0] > 100:
            raise ValueError("search_radius_mm: (start, end) with 100 >= start >= end > "
                             "normal_distance_mm / 2")
        return self


log = logging.getLogger(__name__)

__all__ = ["FitResult", "fit", "check_inputs", "initial_similarity"]


@dataclass
class FitResult:
    """The fitted mesh (template topology, mm) and how the fit went."""

    template: Template  # the fitted vertices in the template's topology
    initial: np.ndarray  # vertices after the initial similarity
    iterations: int
    factorizations: int
    wall_s: float
    cpu_s: float
    log: list[dict] = field(default_factory=list)  # one record per step
    supported: np.ndarray | None = None  # last cloud support mask
    cloud_noise_mm: float | None = None  # the cloud's measured noise over the face
    cloud_weight: float | None = None  # the weight of one cloud target it gave

    @property
    def vertices(self) -> np.ndarray:
        return self.template.vertices

    @property
    def faces(self) -> np.ndarray:
        return self.template.faces

    def timing(self) -> dict:
        steps = [r["wall_s"] for r in self.log]
        return {"iterations": self.iterations, "factorizations": self.factorizations,
                "wall_s": self.wall_s, "cpu_s": self.cpu_s,
                "wall_s_per_iteration": float(np.mean(steps)) if steps else float("nan")}


def check_inputs(template: Template, cloud: np.ndarray | None, landmarks: np.ndarray | None,
                 ear_points: tuple[np.ndarray, ...] | None,
                 cloud_normals: np.ndarray | None, config: NicpConfig):
    """Validate shapes; raises :class:`InputError` with one line naming the problem."""
    if landmarks is None:
        raise InputError("fitting needs the 68 3D landmarks (iBUG order, mm) of the subject")
    L = np.asarray(landmarks, float)
    if L.shape != (68, 3):
        raise InputError(f"fitting landmarks must be 68 3D points (68, 3); got shape {L.shape}")
    if not np.all(np.isfinite(L[INNER_LANDMARKS])):
        raise InputError("fitting landmarks 17-67 hold non-finite coordinates")
    if config.use_cloud:
        if cloud is None:
            raise InputError("fitting needs a point cloud (N, 3) in mm (or use_cloud=False)")
        C = np.asarray(cloud, float)
        if C.ndim != 2 or C.shape[1] != 3:
            raise InputError(f"point cloud must be (N, 3) points; got shape {C.shape}")
        if len(C) < 100:
            raise InputError(f"point cloud has {len(C)} points; fitting needs at least 100 "
                             "(did fusion fail?)")
        if not np.all(np.isfinite(C)):
            raise InputError("point cloud holds non-finite coordinates")
        if cloud_normals is not None and np.shape(cloud_normals) != C.shape:
            raise InputError(f"cloud normals shape {np.shape(cloud_normals)} does not match "
                             f"the cloud's {C.shape}")
        # Template/cloud mismatch: the landmarks must lie near the cloud (same frame, units).
        size = np.linalg.norm(L[36] - L[45])
        lo, hi = C.min(0) - size, C.max(0) + size
        if not np.all((L[INNER_LANDMARKS] >= lo) & (L[INNER_LANDMARKS] <= hi)):
            raise InputError("landmarks lie outside the point cloud's bounding box: cloud and "
                             "landmarks are in different frames or units")
    if ear_points is not None:
        ids, pts = np.asarray(ear_points[0]), np.asarray(ear_points[1], float)
        if ids.ndim != 1 or pts.shape != (len(ids), 3):
            raise InputError(f"ear points must be (k,) vertex ids and (k, 3) targets; got "
                             f"{ids.shape} and {pts.shape}")
        if len(ids) and (ids.min() < 0 or ids.max() >= len(template.vertices)):
            raise InputError(f"ear point vertex ids must be in [0, {len(template.vertices)})")
        if len(ear_points) > 2 and (np.shape(ear_points[2]) != ids.shape
                                    or not np.all(np.asarray(ear_points[2], float) >= 0)):
            raise InputError(f"ear point weights must be {len(ids)} non-negative numbers, one "
                             "per ear point")


def initial_similarity(template: Template, landmarks: np.ndarray) -> np.ndarray:
    src = template.vertices[template.landmarks[INNER_LANDMARKS]]
    s, R, t = umeyama(src, np.asarray(landmarks, float)[INNER_LANDMARKS], with_scale=True)
    return s * template.vertices @ R.T + t


def fit(template: Template, cloud: np.ndarray | None, landmarks: np.ndarray,
        keyframes: list[Keyframe] | tuple = (),
        ear_points: tuple[np.ndarray, ...] | None = None,
        cloud_normals: np.ndarray | None = None,
        config: NicpConfig | None = None,
        cloud_errors: np.ndarray | None = None) -> FitResult:
    """Deform ``template`` onto the constraints; returns a :class:`FitResult`.

    ``cloud`` (N, 3) mm (with optional ``cloud_normals``), ``landmarks`` the subject's 68 3D
    landmarks (only 17-67 are used), ``keyframes`` images with cameras for the silhouettes,
    ``ear_points`` ``(vertex ids (k,), targets (k, 3)[, weights (k,)])``, the weights each
    point's reliability (1 without them), ``cloud_errors`` (N,) each cloud point's standard
    error in mm (the fusion stage's; see ``NicpConfig.cloud_noise_mm``). The template is
    used as given
    (in the subject's frame) unless ``config.initial_similarity``.
    """
    # Long on purpose: the schedule's state (targets, their weights, the edge terms, the noise
    # weight) carries from step to step; split, each part would take and return most of it.
    config = config or NicpConfig()
    check_inputs(template, cloud, landmarks, ear_points, cloud_normals, config)
    if config.use_cloud and cloud_errors is not None and \
            np.shape(cloud_errors) != (len(cloud),):
        raise InputError(f"cloud errors shape {np.shape(cloud_errors)} does not match the "
                         f"cloud's {len(cloud)} points")
    t_wall, t_cpu = time.perf_counter(), time.process_time()
    L = np.asarray(landmarks, float)
    faces = template.faces
    n = len(template.vertices)
    v0 = initial_similarity(template, L) if config.initial_similarity else template.vertices.copy()
    system = NicpSystem(v0, faces, gamma=config.gamma, solver=config.solver)

    levels = len(config.stiffness)
    r0, r1 = config.search_radius_mm
    radii = np.geomspace(r0, r1, levels) if levels > 1 else np.array([r1])
    grid = None
    if config.use_cloud:
        grid = CloudGrid.build(cloud, cloud_normals, max(r1, 2.0 * config.normal_distance_mm),
                               cloud_errors)

    lm_ids = template.landmarks[INNER_LANDMARKS]
    lm_pts = L[INNER_LANDMARKS]
    ears = None
    if ear_points is not None and config.use_ear_landmarks and len(ear_points[0]):
        ears = (np.asarray(ear_points[0], np.int64), np.asarray(ear_points[1], float),
                np.asarray(ear_points[2], float) if len(ear_points) > 2
                else np.ones(len(ear_points[0])))
    use_edges = config.use_edges and len(keyframes) > 0 and config.edge_weight > 0
    edge_exclude = boundary_distance(n, faces, config.edge_boundary_rings) if use_edges else None
    nearest = []
    if use_edges:
        def edges_near(kf: Keyframe):
            return nearest_edge_pixels(edge_map(kf.image, config.edge_blur_sigma,
                                                *config.canny_thresholds))

        with ThreadPoolExecutor(FIT_THREADS) as pool:  # OpenCV's calls let go of the GIL
            nearest = list(pool.map(edges_near, keyframes))

    V = v0.copy()
    face = face_vertices(template.vertices, template.landmarks)
    cloud_noise, cloud_w = None, config.data_weight
    records: list[dict] = []
    step = 0
    ok = np.zeros(n, bool)
    cloud_t = np.zeros((n, 3))
    edge_w = np.zeros(n)
    edge_wu = np.zeros((n, 3))
    for level, (alpha, beta) in enumerate(zip(config.stiffness, config.landmark_weight)):
        w_level = None
        for it in range(config.iterations_per_level):
            t0 = time.perf_counter()
            normals = vertex_normals(V, faces)
            if grid is not None and (step % config.recompute_every == 0 or it == 0):
                ok, cloud_t, _, point_error = cloud_targets(V, normals, grid, radii[level],
                                                            config.normal_distance_mm,
                                                            config.min_points,
                                                            config.normal_agreement_deg)
                if cloud_noise is None or (len(grid.errors) and not np.isfinite(cloud_noise)):
                    # Once, where the cloud has errors: measured again while no face vertex
                    # has found its points yet.
                    cloud_noise, cloud_w = _noise_weight(point_error, ok & face, config)
            t_cloud = time.perf_counter() - t0
            if use_edges and level >= config.edge_first_level and \
                    (it == 0 or step % config.edge_recompute_every == 0):
                edge_w, edge_wu = _edge_terms(V, normals, faces, keyframes, nearest,
                                              edge_exclude, config)
            elif not use_edges or level < config.edge_first_level:
                edge_w, edge_wu = np.zeros(n), np.zeros((n, 3))

            w = np.where(ok, cloud_w, 0.0) if grid is not None else np.zeros(n)
            wu = w[:, None] * cloud_t
            lw, lwu = landmark_targets(n, lm_ids, lm_pts, beta)
            w, wu = w + lw, wu + lwu
            if ears is not None:
                ew, ewu = landmark_targets(n, ears[0], ears[1], beta * config.ear_weight * ears[2])
                w, wu = w + ew, wu + ewu
            w, wu = w + edge_w, wu + edge_wu
            targets = wu / np.maximum(w, 1e-300)[:, None]
            if config.reuse_factorization:
                if w_level is None:
                    w_level = w
                else:
                    # Same weights as the level's first step: vertices that lost their
                    # targets hold their place, new ones wait for the next level.
                    lost = (w == 0) & (w_level > 0)
                    targets = np.where(lost[:, None], V, targets)
                    new = (w > 0) & (w_level == 0)
                    targets[new] = 0.0
                    # Reweight to the level's weights (targets are weighted means already).
                    w = w_level
            t1 = time.perf_counter()
            V_new = system.solve(alpha, w, targets)
            t_solve = time.perf_counter() - t1
            moved = float(np.max(np.linalg.norm(V_new - V, axis=1)))
            V = V_new
            rec = {"level": level, "alpha": alpha, "landmark_weight": beta, "step": step,
                   "cloud_weight": cloud_w,
                   "cloud_targets": int(ok.sum()), "edge_targets": int((edge_w > 0).sum()),
                   "max_move_mm": moved, "cloud_s": t_cloud, "solve_s": t_solve,
                   "wall_s": time.perf_counter() - t0,
                   "landmark_rms_mm": float(np.sqrt(np.mean(np.sum((V[lm_ids] - lm_pts) ** 2, 1))))}
            records.append(rec)
            log.debug("fit step %s", rec)
            step += 1
            if moved < config.convergence_mm:
                break

    fitted = template.with_vertices(V)
    return FitResult(fitted, v0, step, system.factorizations, time.perf_counter() - t_wall,
                     time.process_time() - t_cpu, records, ok, cloud_noise, cloud_w)


def _noise_weight(point_error: np.ndarray, face_targets: np.ndarray,
                  config: NicpConfig) -> tuple[float, float]:
    """The cloud's noise over the face (the median error of the points that give the face's
    vertices their targets, mm; nan when the cloud does not say) and the weight of one cloud
    target: ``data_weight``, times the inverse variance relative to ``cloud_noise_mm`` when
    the cloud is noisier than that. One weight for the whole face: a weight that varied from
    vertex to vertex would itself pull neighbours apart."""
    errors = point_error[face_targets]
    errors = errors[np.isfinite(errors)]
    noise = float(np.median(errors)) if len(errors) else float("nan")
    if config.cloud_noise_mm is None or not np.isfinite(noise) or noise <= 0:
        return noise, config.data_weight
    return noise, config.data_weight * min(1.0, (config.cloud_noise_mm / noise) ** 2)


def _edge_terms(V, normals, faces, keyframes, nearest, exclude, config):
    n = len(V)
    w = np.zeros(n)
    wu = np.zeros((n, 3))
    scene = RaycastScene()
    scene.add(V, faces)
    planes = face_planes(V, faces)
    for kf, near in zip(keyframes, nearest):
        ids, tg = edge_targets(V, normals, faces, kf, scene, near, config.edge_max_px,
                               config.edge_min_cos, exclude, planes)
        np.add.at(w, ids, config.edge_weight)
        np.add.at(wu, ids, config.edge_weight * tg)
    return w, wu
