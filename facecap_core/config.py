"""Typed configuration: one pydantic model per stage, YAML in and out.

Every tunable lives here with a docstring; unknown keys and out-of-range values are
rejected with a message that names the field.
"""

from __future__ import annotations

from pathlib import Path
from typing import TypeVar

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
