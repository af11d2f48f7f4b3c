"""Typed configuration: one pydantic model per stage, YAML in and out.

Every tunable lives here with a docstring; unknown keys and out-of-range values are
rejected with a message that names the field.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal, TypeVar

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from facecap_core.errors import InputError


class StrictModel(BaseModel):
    """Base: unknown keys are errors, values are validated on assignment too."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class SynthConfig(StrictModel):
    """A synthetic handheld ear-to-ear capture of a textured head, with exact ground truth."""

    subject: str = "ict:0"
    """``ict:SEED`` (random ICT identity, needs ``ict_model``), ``ict:mean``, ``james``
    (menpo3d's real scan), or a path to a mesh file (with ``subject_landmarks``)."""
    subject_landmarks: Path | None = None
    """68 3D landmarks (iBUG order, mesh units) of a ``subject`` given as a mesh path."""
    subject_scale: float = Field(1.0, gt=0)
    """Factor that converts a mesh-path subject to millimetres."""
    ict_model: Path | None = None
    """ICT Face Model Light ``.npz``; default ``$FACECAP_ICT_MODEL``."""
    ict_identity_sigma: float = Field(1.0, ge=0, le=3)
    """Spread of random ICT identity coefficients, in model standard deviations."""

    width: int = Field(1280, ge=64, le=7680)
    """Video width in pixels (landscape)."""
    height: int = Field(720, ge=64, le=4320)
    """Video height in pixels."""
    fps: float = Field(30.0, gt=0, le=480)
    """Frames per second."""
    duration_s: float = Field(6.0, gt=0, le=120)
    """Length of the sweep in seconds."""

    hfov_deg: float = Field(65.0, gt=20, lt=120)
    """Nominal horizontal field of view; the true focal length is drawn around it."""
    focal_jitter: float = Field(0.04, ge=0, le=0.3)
    """Relative standard deviation of the drawn focal length (the focal is 'unknown')."""
    principal_point_jitter: float = Field(0.01, ge=0, le=0.1)
    """Standard deviation of the principal point offset, as a fraction of the image size."""
    k1_range: tuple[float, float] = (-0.10, -0.02)
    """Range of the radial distortion k1 (negative: barrel, as a phone's wide lens leaves
    after the ISP's own correction; positive: pincushion). k2 = -0.25 k1."""

    yaw_start_deg: float = Field(-95.0, ge=-180, le=180)
    """Camera azimuth at the start, around the head's vertical axis (0 = frontal,
    negative = on the subject's right)."""
    yaw_end_deg: float = Field(95.0, ge=-180, le=180)
    """Camera azimuth at the end."""
    distance_mm: tuple[float, float] = (350.0, 500.0)
    """Range of the camera's distance to the head centre; it drifts slowly within it."""
    elevation_deg: float = Field(6.0, ge=-45, le=45)
    """Mean camera elevation above the eye plane (looking slightly down)."""
    elevation_wobble_deg: float = Field(4.0, ge=0, le=30)
    """Slow up/down drift of the elevation."""
    hand_jitter_mm: float = Field(3.0, ge=0, le=50)
    """Hand tremor: amplitude of fast position noise."""
    hand_jitter_deg: float = Field(0.8, ge=0, le=10)
    """Hand tremor: amplitude of fast rotation noise."""
    roll_deg: float = Field(3.0, ge=0, le=45)
    """Amplitude of the slow roll of the phone."""

    exposure_fraction: float = Field(0.25, ge=0, le=1)
    """Exposure time as a fraction of the frame interval (motion blur)."""
    blur_samples: int = Field(5, ge=1, le=32)
    """Sub-frame samples used to integrate motion blur."""
    exposure_drift: float = Field(0.08, ge=0, le=0.5)
    """Amplitude of the slow auto-exposure gain drift (relative)."""
    read_noise: float = Field(0.008, ge=0, le=0.2)
    """Sensor read-noise standard deviation (fraction of full scale)."""
    shot_noise: float = Field(0.012, ge=0, le=0.2)
    """Shot-noise scale: standard deviation = shot_noise * sqrt(intensity)."""
    specular: float = Field(0.05, ge=0, le=1)
    """Strength of the skin's specular highlight (0 = Lambertian)."""
    ambient: float = Field(0.35, ge=0, le=2)
    """Ambient light level."""
    room: bool = True
    """Render a static textured room around the subject (a background to track)."""

    crf: int = Field(16, ge=0, le=51)
    """H.264 constant rate factor of the output video (lower = better quality)."""
    seed: int = 0
    """Seed of every random draw (camera, path, lighting, textures, noise)."""

    @model_validator(mode="after")
    def _check_ranges(self):
        for name in ("k1_range", "distance_mm"):
            lo, hi = getattr(self, name)
            if lo > hi:
                raise ValueError(f"{name}: lower bound {lo} exceeds upper bound {hi}")
        if self.distance_mm[0] <= 100:
            raise ValueError("distance_mm must stay above 100 mm")
        return self


M = TypeVar("M", bound=BaseModel)


def validation_message(exc: ValidationError) -> str:
    """One line naming each bad field and why."""
    parts = []
    for err in exc.errors():
        loc = ".".join(str(x) for x in err["loc"]) or "config"
        parts.append(f"{loc}: {err['msg']}")
    return "; ".join(parts)


def build(model: type[M], values: dict, source: str = "config") -> M:
    """Validate ``values`` into ``model``; bad values raise one-line :class:`InputError`."""
    try:
        return model.model_validate(values)
    except ValidationError as exc:
        raise InputError(f"invalid {source}: {validation_message(exc)}") from None


def load_yaml(model: type[M], path: str | Path, overrides: dict | None = None) -> M:
    """Read a YAML config (``{}`` for an empty file) and apply ``overrides`` on top."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"config file not found: {path}")
    try:
        values = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise InputError(f"config file {path} is not valid YAML ({str(exc).splitlines()[0]})"
                         ) from None
    if not isinstance(values, dict):
        raise InputError(f"config file {path} must hold a mapping of settings")
    return build(model, {**values, **(overrides or {})}, source=f"config {path}")


def dump_yaml(config: BaseModel, path: str | Path) -> Path:
    path = Path(path)
    path.write_text(yaml.safe_dump(config.model_dump(mode="json"), sort_keys=False))
    return path


class KeyframeConfig(StrictModel):
    """Lucas–Kanade tracking and keyframe selection (``facecap_core/keyframes.py``)."""

    track_width: int = Field(640, ge=160, le=4096)
    """Frames are tracked at this width (pixels); keyframe positions are full resolution."""
    max_features: int = Field(800, ge=50, le=10000)
    """Features kept per frame."""
    min_features: int = Field(400, ge=20, le=10000)
    """Re-seed new features when fewer than this many are tracked."""
    feature_quality: float = Field(0.005, gt=0, lt=1)
    """Shi–Tomasi quality level relative to the best corner."""
    min_distance_px: int = Field(8, ge=1, le=100)
    """Minimum spacing of features (tracking pixels)."""
    lk_window: int = Field(21, ge=5, le=101)
    """LK window size (tracking pixels)."""
    lk_levels: int = Field(3, ge=0, le=8)
    """LK pyramid levels above the base image."""
    fb_max_px: float = Field(0.7, gt=0, le=10)
    """Largest forward–backward error of a kept track (tracking pixels)."""
    keyframe_angle_deg: float = Field(4.0, gt=0.2, le=45)
    """A keyframe is due when the view has turned this much since the last one."""
    angle_slack: float = Field(0.25, ge=0, lt=1)
    """Frames past (1 - slack) of that angle compete on sharpness to be the keyframe."""
    nominal_hfov_deg: float = Field(65.0, gt=20, lt=150)
    """Horizontal field of view assumed while measuring angles (the true focal comes later)."""
    sharpness_window: int = Field(6, ge=1, le=240)
    """The sharpest of this many recent frames becomes the keyframe."""
    min_shared_tracks: int = Field(30, ge=8)
    """A keyframe is forced when fewer tracks than this link back to the last one."""
    min_frames: int = Field(15, ge=2)
    """Videos with fewer frames are refused."""
    min_keyframes: int = Field(5, ge=2)
    """Fewer keyframes than this means the camera did not move enough."""


class PBAConfig(StrictModel):
    """Photometric bundle adjustment (``facecap_core/pose/pba.py``)."""

    cell: int = Field(12, ge=4, le=64)
    """One point per cell×cell block of each keyframe (its strongest gradient)."""
    min_gradient: float = Field(8.0, ge=0)
    """Weakest gradient (grey levels per pixel) a point may have."""
    search_level: int = Field(1, ge=0, le=5)
    """Pyramid level of the initial depth search along the epipolar lines."""
    search_samples: int = Field(96, ge=8, le=1024)
    """Inverse-depth samples of that search (log-spaced over the sparse points' range)."""
    min_search_quality: float = Field(1.5, ge=1)
    """A point is kept when its second-best match costs this many times its best."""
    neighbours: int = Field(4, ge=1, le=15)
    """Each point is compared in this many keyframes before and after its host."""
    pyramid_levels: int = Field(3, ge=1, le=6)
    """Coarse-to-fine levels (each half the size of the previous)."""
    iterations: int = Field(12, ge=1, le=200)
    """Levenberg–Marquardt iterations per pyramid level."""
    depth_only_iterations: int = Field(2, ge=0)
    """The first iterations of each level move only the inverse depths."""
    huber: float = Field(9.0, gt=0)
    """Huber threshold of the photometric residual (grey levels)."""
    gradient_weight: float = Field(50.0, gt=0)
    """DSO's gradient weight c²/(c² + |∇I|²): strong edges count less (sub-pixel noise)."""
    max_residual: float = Field(40.0, gt=0)
    """Residuals above this (grey levels) are dropped: occlusions and highlights."""
    initial_lambda: float = Field(1e-3, gt=0)
    """Initial Levenberg–Marquardt damping."""
    refine_intrinsics: bool = True
    """Refine focal length, principal point and k1, k2 with the poses."""
    scale_prior: float = Field(1e8, gt=0)
    """Weight of the prior that fixes the length of the first baseline (the scale gauge)."""


class FittingConfig(StrictModel):
    """Non-rigid template fitting: optimal-step NICP (Amberg et al. 2007) to a fused point
    cloud, 3D landmarks, ear points and keyframe silhouettes (Agrawal et al. 2020, "Mesh
    fitting"). Distances in mm, weights relative to one cloud target."""

    stiffness: list[float] = [50.0, 20.0, 10.0, 5.0, 2.0, 1.0]
    """Stiffness alpha per level, from global (large) to local (small) deformation; the
    template is centred and scaled to unit RMS radius, so the values do not depend on units."""
    landmark_weight: list[float] = [50.0, 20.0, 10.0, 5.0, 2.0, 1.0]
    """Weight of each landmark target per level (same length as ``stiffness``); falls with
    the stiffness so that landmarks place the mesh first and the cloud refines it."""
    iterations_per_level: int = Field(3, ge=1, le=100)
    """Most optimal steps per stiffness level (fewer when the mesh stops moving)."""
    convergence_mm: float = Field(0.02, ge=0)
    """A level ends early when no vertex moved more than this in its last step."""
    gamma: float = Field(1.0, gt=0)
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

    data_weight: float = Field(1.0, gt=0)
    """Weight of one point-cloud target."""
    search_radius_mm: tuple[float, float] = (8.0, 3.0)
    """How far along the vertex normal cloud points are accepted, at the first and last
    level (geometric in between): wide while the template is far, tight at the end."""
    normal_distance_mm: float = Field(1.5, gt=0)
    """Largest distance of an accepted cloud point from the vertex-normal line."""
    min_points: int = Field(3, ge=1)
    """Fewest accepted points for a cloud target; vertices with fewer fall back to stiffness."""
    normal_agreement_deg: float = Field(60.0, gt=0, le=180)
    """When the cloud has normals, accept only points whose normal is within this angle of
    the vertex normal (180: no check)."""
    recompute_every: int = Field(1, ge=1)
    """Recompute the cloud targets every this many steps (the paper: every few)."""

    ear_weight: float = Field(1.0, ge=0)
    """Ear point weight relative to the level's landmark weight."""

    edge_weight: float = Field(1.0, ge=0)
    """Weight of one silhouette target (per keyframe that sees the vertex on its contour)."""
    edge_recompute_every: int = Field(2, ge=1)
    """Recompute silhouette vertices and their edge targets every this many steps."""
    edge_first_level: int = Field(1, ge=0)
    """First level (0-based) that uses edges: before it the mesh is too far for a few-pixel
    match."""
    edge_max_px: float = Field(3.0, gt=0)
    """Largest image distance from a projected contour vertex to its edge pixel."""
    edge_min_cos: float = Field(0.7, ge=0, le=1)
    """The edge pixel must lie along the projected vertex normal: |cos| of the angle at least
    this."""
    edge_blur_sigma: float = Field(1.0, ge=0)
    """Gaussian blur (px) before Canny."""
    canny_thresholds: tuple[int, int] = (30, 90)
    """Canny hysteresis thresholds on the grey image."""
    edge_boundary_rings: int = Field(4, ge=0)
    """Template vertices this many edges or fewer from the template's open border never give
    silhouettes (the border is not a real contour)."""

    texture: bool = True
    """Colour the fitted mesh from the keyframes (per-vertex colour) when keyframes are given."""
    texture_min_cos: float = Field(0.25, ge=0, le=1)
    """A view colours a vertex only when the vertex faces it at least this much (cos)."""

    @model_validator(mode="after")
    def _check_schedule(self):
        if len(self.stiffness) == 0 or len(self.stiffness) != len(self.landmark_weight):
            raise ValueError("stiffness and landmark_weight need the same, non-zero length")
        if any(a <= 0 for a in self.stiffness) or any(b < 0 for b in self.landmark_weight):
            raise ValueError("stiffness must be > 0 and landmark_weight >= 0")
        if self.search_radius_mm[1] <= self.normal_distance_mm / 2 or \
                self.search_radius_mm[0] < self.search_radius_mm[1]:
            raise ValueError("search_radius_mm: (start, end) with start >= end > "
                             "normal_distance_mm / 2")
        return self


class MVSConfig(StrictModel):
    """Dense multi-view stereo: view selection, PatchMatch depth maps, filtering, fusion."""

    processing_width: int = Field(640, ge=64, le=4096)
    """Width (px) the keyframes are resized to before undistortion and matching."""
    num_sources: int = Field(12, ge=1, le=64)
    """Source views per reference view, the best by the view-selection score."""
    view_theta0_deg: float = Field(10.0, gt=0, lt=90)
    """Preferred baseline angle theta0 of the view-selection score."""
    view_sigma1: float = Field(5.0, gt=0)
    """Spread (degrees) of the score below theta0."""
    view_sigma2: float = Field(10.0, gt=0)
    """Spread (degrees) of the score above theta0."""

    depth_margin_mm: float = Field(8.0, gt=0, le=100)
    """Half-width of the depth search range around the coarse mesh."""
    head_dilation_px: int = Field(6, ge=0, le=100)
    """Pixels the coarse mesh's silhouette is grown by to form the computed region."""
    init_from_coarse: bool = True
    """Also test the coarse mesh's plane at initialisation (the paper initialises with it)."""

    iterations: int = Field(5, ge=1, le=32)
    """Red–black PatchMatch iterations (each updates both colours once)."""
    neighbours: str = Field("fast", pattern="^(fast|full)$")
    """Gipuma's propagation pattern: 8 ('fast': ±1, ±5 on both axes) or 20 ('full')."""
    refine_trials: int = Field(3, ge=0, le=10)
    """Random refinements per pixel and iteration (depth, normal, both perturbed)."""
    normal_perturbation_deg: float = Field(30.0, gt=0, le=90)
    """Largest normal perturbation; the depth and normal steps halve every iteration."""
    window_radius: int = Field(5, ge=1, le=15)
    """Half-size (px) of the matching window."""
    window_step: int = Field(2, ge=1, le=5)
    """Sample every ``window_step``-th pixel of the window (sparse window)."""
    presmooth_sigma: float = Field(0.8, ge=0, le=5)
    """Gaussian blur (px) of the grey images before matching (noise vs. sparse sampling)."""
    sigma_color: float = Field(0.2, gt=0)
    """Bilateral weight's intensity spread (intensities in [0, 1])."""
    sigma_spatial: float | None = Field(None, gt=0)
    """Bilateral weight's spatial spread in px; default: the window radius."""
    num_best_views: int = Field(8, ge=1, le=64)
    """A hypothesis' cost is the mean of its best this-many per-view costs (occlusion)."""
    seed: int = 0
    """Seed of the random hypotheses (results are reproducible per keyframe)."""

    max_cost: float = Field(0.5, gt=0, le=2)
    """Depths whose aggregated cost (1 - NCC) exceeds this are rejected."""
    coarse_max_distance_mm: float = Field(6.0, gt=0)
    """Depths farther than this from the coarse mesh (along the ray) are rejected."""

    fusion_max_depth_mm: float = Field(1.0, gt=0)
    """Fusion: a source agrees when its depth differs by at most this from the reprojection."""
    fusion_max_reprojection_px: float = Field(1.0, gt=0)
    """Fusion: ... and the round trip through its depth lands within this many pixels."""
    fusion_max_normal_deg: float = Field(30.0, gt=0, le=180)
    """Fusion: ... and its normal is within this angle."""
    min_consistent_views: int = Field(2, ge=1)
    """Fusion: source views that must agree with a reference pixel to make a point."""

    workers: int = Field(2, ge=1, le=256)
    """Depth maps computed at once (threads; the kernels release the GIL)."""
