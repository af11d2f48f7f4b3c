"""The settings of a synthetic capture (``facecap synth --config``)."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator, model_validator
from pydantic_core import PydanticCustomError

from facecap_core.config import StrictModel

MAX_SEED = 2**32 - 1
"""Largest seed of a synthetic capture's random draws, or of an ``ict:SEED`` subject."""


def _is_ict_subject(subject: str) -> bool:
    """Whether ``subject`` is ``ict:mean`` or ``ict:SEED`` with a seed a synthetic capture
    takes (ASCII digits: ``int`` reads other scripts' digits too, and ``-1`` is no seed)."""
    seed = re.fullmatch(r"ict:(?:mean|([0-9]{1,10}))", subject)
    return seed is not None and (seed[1] is None or int(seed[1]) <= MAX_SEED)


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
    """ICT Face Model Light ``.npz``; default ``$FACECAP_ICT_MODEL``, else the trimmed model
    in the package (``facecap_core/data/``)."""
    ict_identity_sigma: float = Field(1.0, ge=0, le=3)
    """Spread of random ICT identity coefficients, in model standard deviations."""

    width: int = Field(1280, ge=64, le=7680)
    """Width in pixels of the frames as stored (the sensor's long side; see
    ``display_rotation_deg``)."""
    height: int = Field(720, ge=64, le=4320)
    """Height in pixels of the frames as stored."""
    fps: float = Field(30.0, ge=1, le=480)
    """Frames per second."""
    duration_s: float = Field(6.0, gt=0, le=120)
    """Length of the sweep in seconds."""

    display_rotation_deg: Literal[0, 90, 180, 270] = 0
    """Phone orientation, stored as phones store it: every frame is encoded as the
    ``width`` × ``height`` sensor image and the container carries this display rotation
    (counter-clockwise degrees, as :mod:`facecap_core.video` reads PyAV's ``frame.rotation``
    and turns the frames upright). 90 or 270: a portrait capture, upright ``height`` ×
    ``width``. The scene is rendered upright; the ground-truth intrinsics and poses are
    those of the upright image. 0: landscape, no rotation (as before)."""

    hfov_deg: float = Field(65.0, gt=20, lt=120)
    """Nominal field of view across the sensor's width (horizontal in landscape, vertical
    in portrait); the true focal length is drawn around it."""
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
    defocus_px: float = Field(0.0, ge=0, le=10)
    """Lens blur: standard deviation (px) of a Gaussian over the image before the sensor
    samples it (a phone's small aperture focused at arm's length, or a soft lens)."""
    bayer: bool = False
    """Sample through an RGGB colour filter array (one colour per photosite, noise per
    photosite) and demosaic (OpenCV's edge-aware demosaicing), as a phone sensor does:
    colour noise, zipper artefacts at edges and noise correlated between neighbours."""
    sharpen: float = Field(0.0, ge=0, le=3)
    """Unsharp-mask amount (radius 1 px) after demosaicing, as phone image processing
    sharpens: it amplifies the noise and compression artefacts along with the detail."""
    specular: float = Field(0.05, ge=0, le=1)
    """Strength of the skin's specular highlight (0 = Lambertian)."""
    ambient: float = Field(0.35, ge=0, le=2)
    """Ambient light level."""
    room: bool = True
    """Render a static textured room around the subject (a background to track)."""
    plain_walls: bool = False
    """Untextured room: every surface (walls, floor, ceiling, furniture) has one uniform
    albedo, its paint colour, so the background offers edges and shading but no texture to
    track. The room's geometry and colours are those of the textured room of the same
    seed."""
    skin_detail: float = Field(1.0, ge=0, le=1)
    """Strength of the procedural skin's fine texture (1.2 mm mottling, 0.5 mm pores and
    freckles) relative to the default: 1 as before, 0 leaves the tone, 4 mm and 25 mm
    variation, lips, brows and hair (real skin, as a phone resolves it, is smoother than
    the default). ICT subjects only; a mesh subject's own texture is used as it is."""

    rolling_shutter_s: float = Field(0.0, ge=0, le=0.1)
    """Rolling-shutter readout time: the sensor's rows (stored rows; columns of the upright
    portrait image) are exposed one after another over this time, first to last, each
    rendered (ray cast, blurred) with the camera pose at its own time; phones read out in
    about 30 ms. A frame's ground-truth pose is the one at mid-exposure of the sensor's
    middle line (``gt/cameras.json`` ``frames[].time``). 0: global shutter (as before)."""
    sway_mm: float = Field(0.0, ge=0, le=50)
    """Subject sway: the head moves rigidly and smoothly (0.1–0.5 Hz) before the still
    room; its largest translation from the reference pose over the frames is exactly this.
    The ground-truth mesh and landmarks are the head at the reference pose (its head
    frame) and the ground-truth cameras are relative to the head, so they stay exact for
    the reconstruction; the head's pose per frame (head to room) is in
    ``gt/cameras.json``. Each frame shows the head at its pose at the frame's ground-truth
    instant (its motion within one exposure and readout, < 0.3 mm at 3 mm of sway, is not
    rendered). 0: a still head (as before)."""
    sway_deg: float = Field(0.0, ge=0, le=10)
    """Largest rotation of the swaying head (about a pivot at the neck) over the frames."""

    codec: Literal["h264", "hevc"] = "h264"
    """Video codec: H.264 (libx264) or HEVC (libx265, tagged ``hvc1`` as phones write
    it), both at ``crf`` with the medium preset."""
    crf: int = Field(16, ge=0, le=51)
    """Constant rate factor of the output video (lower = better quality)."""
    seed: int = Field(0, ge=0, le=MAX_SEED)
    """Seed of every random draw (camera, path, lighting, textures, noise)."""

    @field_validator("subject")
    @classmethod
    def _check_subject(cls, value: str) -> str:
        # Any other string is a mesh path, checked when it is loaded; an ict: one is checked
        # here, before anything is written.
        if value.startswith("ict:") and not _is_ict_subject(value):
            raise PydanticCustomError(
                "subject", "'{subject}' names no subject (the forms are ict:SEED with SEED a "
                "whole number from 0 to {most}, ict:mean, james, or the path of a mesh file)",
                {"subject": value, "most": MAX_SEED})
        return value

    @model_validator(mode="after")
    def _check_ranges(self):
        for name in ("k1_range", "distance_mm"):
            lo, hi = getattr(self, name)
            if lo > hi:
                raise ValueError(f"{name}: lower bound {lo} exceeds upper bound {hi}")
        if self.distance_mm[0] <= 100:
            raise ValueError("distance_mm must stay above 100 mm")
        if self.rolling_shutter_s > 1 / self.fps:
            # A sensor reads a frame out before the next one starts.
            raise ValueError(f"rolling_shutter_s {self.rolling_shutter_s} exceeds the frame "
                             f"interval 1/fps = {1 / self.fps:.4f} s")
        return self
