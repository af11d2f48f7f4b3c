"""Typed configuration: one pydantic model per stage, YAML in and out.

One module of ~800 lines on purpose: the pipeline's whole settings schema (what the docs
and the YAML files show) in one place, which every stage module imports
without importing another stage.

Every tunable lives here with a docstring; unknown keys and out-of-range values are
rejected with a message that names the field.
"""

from __future__ import annotations

import re
import stat
from functools import lru_cache
from pathlib import Path
from typing import Any, Literal, TypeVar, get_args

import yaml
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)
from pydantic_core import PydanticCustomError

from facecap_core.errors import InputError

MAX_LEVELS = 32
"""Most levels of a stiffness schedule: each level is a sparse solve of the whole template,
and a schedule longer than this is a mistake, not a setting (the default has 6)."""
MAX_CONFIG_BYTES = 256 * 1024
"""Largest config file read: every setting with a comment fits in a few kilobytes."""
MAX_FRAMES = 100_000
"""Most frames any setting may ask a capture to have (about 7 minutes at 240 fps)."""
MAX_SEED = 2**32 - 1
"""Largest seed of a synthetic capture's random draws, or of an ``ict:SEED`` subject."""


def _is_ict_subject(subject: str) -> bool:
    """Whether ``subject`` is ``ict:mean`` or ``ict:SEED`` with a seed a synthetic capture
    takes (ASCII digits: ``int`` reads other scripts' digits too, and ``-1`` is no seed)."""
    seed = re.fullmatch(r"ict:(?:mean|([0-9]{1,10}))", subject)
    return seed is not None and (seed[1] is None or int(seed[1]) <= MAX_SEED)


class StrictModel(BaseModel):
    """Base: unknown keys are errors, values are validated on assignment too, and NaN or
    infinite numbers are refused (they pass every ``gt``/``le`` bound they meet in a list
    or an unbounded field)."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False,
                              use_attribute_docstrings=True)

    @field_validator("*", mode="before")
    @classmethod
    def _no_boolean_for_a_number(cls, value: Any, info: ValidationInfo) -> Any:
        """``true`` is no number, but pydantic's lax mode takes it as 1 (and YAML reads
        ``yes`` and ``on`` as ``true``). Strict mode would refuse it, and also the strings
        and lists that YAML and flow parameters give for paths and tuples."""
        items = value if isinstance(value, list | tuple) else (value,)
        if any(isinstance(v, bool) for v in items) and _is_numeric(
                cls.model_fields[info.field_name].annotation):
            raise PydanticCustomError("bool_for_number", "Input should be a number, not a "
                                      "boolean (true/false, yes/no, on/off)")
        return value


@lru_cache
def _is_numeric(annotation: Any) -> bool:
    """Whether a field's type holds numbers (``int``, ``float | None``, ``list[float]``,
    ``tuple[int, int]``) and no bool (a ``Literal`` of numbers lists values, not types:
    pydantic itself refuses ``true`` there)."""
    types, todo = set(), [annotation]
    while todo:
        t = todo.pop()
        types.add(t)
        todo.extend(get_args(t))
    return bool(types & {int, float}) and bool not in types


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
        raise InputError(f"invalid {source}: {validation_message(exc)}; correct or remove "
                         "these settings") from None


class ConfigLoader(yaml.SafeLoader):
    """PyYAML's safe loader without a YAML 1.1 surprise: ``1:30`` is a string, not the
    base-60 integer 90 (nor ``1:30.5`` a float), so that a number field refuses it."""


# The implicit int and float resolvers of PyYAML's resolver.py, without their base-60 forms;
# every other resolver as SafeLoader has it.
ConfigLoader.yaml_implicit_resolvers = {
    first: [(tag, regexp) for tag, regexp in resolvers
            if tag not in ("tag:yaml.org,2002:int", "tag:yaml.org,2002:float")]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()}
ConfigLoader.add_implicit_resolver(
    "tag:yaml.org,2002:int",
    re.compile(r"""^(?:[-+]?0b[0-1_]+
                   |[-+]?0[0-7_]+
                   |[-+]?(?:0|[1-9][0-9_]*)
                   |[-+]?0x[0-9a-fA-F_]+)$""", re.X),
    list("-+0123456789"))
ConfigLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+][0-9]+)?
                   |\.[0-9][0-9_]*(?:[eE][-+][0-9]+)?
                   |[-+]?\.(?:inf|Inf|INF)
                   |\.(?:nan|NaN|NAN))$""", re.X),
    list("-+0123456789."))


class DuplicateKeyError(yaml.YAMLError):
    """A mapping of a YAML document gives one key twice."""

    def __init__(self, key: str, line: int):
        super().__init__(f"{key} is given twice (line {line})")
        self.key, self.line = key, line


def parse_yaml(text: str) -> Any:
    """The one YAML document of ``text`` (None when empty), read by :class:`ConfigLoader`;
    a key given twice in one mapping raises :class:`DuplicateKeyError` (PyYAML would keep
    the last silently)."""
    loader = ConfigLoader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        _check_unique_keys(node)
        try:
            return loader.construct_document(node)
        except (ValueError, TypeError, OverflowError) as exc:  # a scalar its resolver misread
            raise yaml.constructor.ConstructorError(None, None, str(exc)) from None
    finally:
        loader.dispose()


def _check_unique_keys(node: yaml.Node, path: tuple[str, ...] = (),
                       seen: set[int] | None = None) -> None:
    """Raise :class:`DuplicateKeyError`, naming the key's dotted path, for a key given twice
    in one mapping under ``node``."""
    seen = set() if seen is None else seen
    if id(node) in seen:  # an alias: its node is checked once (and may contain itself)
        return
    seen.add(id(node))
    if isinstance(node, yaml.SequenceNode):
        for i, item in enumerate(node.value):
            _check_unique_keys(item, (*path, str(i)), seen)
    elif isinstance(node, yaml.MappingNode):
        keys = set()
        for key, value in node.value:
            name = str(key.value) if isinstance(key, yaml.ScalarNode) else "?"
            # The tag tells 'iterations' and "iterations" (one key) from 1 and "1" (two);
            # a merge key (<<) brings its own mapping's keys, which the mapping may override.
            if isinstance(key, yaml.ScalarNode) and key.tag != "tag:yaml.org,2002:merge":
                if (key.tag, key.value) in keys:
                    raise DuplicateKeyError(".".join((*path, name)), key.start_mark.line + 1)
                keys.add((key.tag, key.value))
            _check_unique_keys(value, (*path, name), seen)


def _config_text(path: Path) -> str:
    """The text of a config file: a regular UTF-8 file of at most MAX_CONFIG_BYTES."""
    try:
        info = path.stat()
    except (FileNotFoundError, NotADirectoryError):
        raise InputError(f"config file not found: {path}; check the path") from None
    except OSError as exc:
        raise InputError(f"config file {path} cannot be read ({exc.strerror}); check the path "
                         "and its permissions") from None
    if stat.S_ISDIR(info.st_mode):
        raise InputError(f"config file {path} is a folder, not a file; give the path of a YAML "
                         "file")
    if not stat.S_ISREG(info.st_mode):  # a FIFO or a device: opening it could block
        raise InputError(f"config file {path} is not a regular file; give the path of a YAML "
                         "file")
    if info.st_size > MAX_CONFIG_BYTES:
        raise InputError(f"config file {path} is {info.st_size} bytes, too large to be a config "
                         f"(at most {MAX_CONFIG_BYTES}); give the settings that differ from the "
                         "defaults")
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise InputError(f"config file {path} is not UTF-8 text (byte {exc.start} is not); "
                         "save it as UTF-8") from None
    except OSError as exc:
        raise InputError(f"config file {path} cannot be read ({exc.strerror}); check its "
                         "permissions") from None


def load_yaml(model: type[M], path: str | Path, overrides: dict | None = None) -> M:
    """Read a YAML config (``{}`` for an empty file) and apply ``overrides`` on top."""
    path = Path(path)
    text = _config_text(path)
    try:
        values = parse_yaml(text)
    except DuplicateKeyError as exc:
        raise InputError(f"config file {path} sets {exc.key} twice (the second time on line "
                         f"{exc.line}); keep one of them") from None
    except yaml.YAMLError as exc:
        raise InputError(f"config file {path} is not valid YAML ({str(exc).splitlines()[0]});"
                         " fix its syntax") from None
    except RecursionError:
        raise InputError(f"config file {path} nests too deeply to be a config; settings are "
                         "two or three levels deep, such as 'mvs: {depth: {iterations: 4}}'") from None
    values = {} if values is None else values  # an empty file; [] or 0 are not
    if not isinstance(values, dict):
        raise InputError(f"config file {path} must hold a mapping of settings, such as "
                         "'mvs: {depth: {iterations: 4}}'")
    return build(model, {**values, **(overrides or {})}, source=f"config {path}")


def dump_yaml(config: BaseModel, path: str | Path) -> Path:
    path = Path(path)
    path.write_text(yaml.safe_dump(config.model_dump(mode="json"), sort_keys=False))
    return path


MIN_YAW_SPAN_DEG = 40.0
"""Fewest degrees round the head a capture's views must span (see
``LandmarkConfig.min_yaw_span_deg``)."""


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
    min_shared_tracks: int = Field(30, ge=8, le=10000)
    """A keyframe is forced when fewer tracks than this link back to the last one."""
    min_frames: int = Field(15, ge=2, le=MAX_FRAMES)
    """Videos with fewer frames are refused."""
    min_keyframes: int = Field(5, ge=2, le=1000)
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
    neighbours: int = Field(6, ge=1, le=15)
    """Each point is compared in this many keyframes before and after its host."""
    pyramid_levels: int = Field(2, ge=1, le=6)
    """Coarse-to-fine levels (each half the size of the previous)."""
    iterations: int = Field(8, ge=1, le=200)
    """Levenberg–Marquardt iterations per pyramid level."""
    depth_only_iterations: int = Field(2, ge=0, le=200)
    """The first iterations of each level move only the inverse depths."""
    huber: float = Field(1.5, gt=0)
    """Huber threshold of the photometric residual, in units of the residuals' robust
    standard deviation (1.4826 x their median magnitude at the level's starting cameras)."""
    gradient_weight: float = Field(50.0, gt=0)
    """DSO's gradient weight c²/(c² + |∇I|²): strong edges count less (sub-pixel noise)."""
    max_residual: float = Field(3.0, gt=0)
    """A point's pattern in one target is an outlier (occluded, a highlight) when its root
    mean square residual exceeds this many robust standard deviations; it then costs a
    constant."""
    initial_lambda: float = Field(1e-3, gt=0)
    """Initial Levenberg–Marquardt damping."""
    refine_intrinsics: bool = True
    """Refine focal length, principal point and k1, k2 with the poses, when the tracked points
    are in the solve (``track_weight``): photometric residuals over neighbouring keyframes
    alone leave the principal point free against a tilt of every camera."""
    principal_point_prior_pct: float = Field(1.0, ge=0)
    """With the intrinsics refined, the principal point is held near the image centre with
    this standard deviation (% of the image's width for x, of its height for y; the spread
    of facecap's sensor model), weighed against the tracks by their noise: the data move it
    as far as they pin it (a tilt of every camera and a shift of the principal point
    reproject almost alike). 0: free."""
    scale_prior: float = Field(1e8, gt=0)
    """Weight of the prior that fixes the length of the first baseline (the scale gauge)."""
    points_from_sparse: bool = True
    """Use the initial reconstruction's points (at their depths) instead of an epipolar
    search for strong-gradient pixels."""
    centre_prior_pct: float = Field(0.0, ge=0)
    """Camera centres are held near the start's with this standard deviation (% of the mean
    camera distance from their centroid; 0: free, the gauge is then the first keyframe and
    the first baseline's length)."""
    intrinsics_level: int = Field(0, ge=0, le=5)
    """Intrinsics are held fixed at pyramid levels coarser than this one (coarse levels bias
    the focal length)."""
    motion_blur: bool = True
    """Model each keyframe's motion blur: the streak the camera's motion (a constant velocity
    through the neighbouring keyframes) draws over the exposure. Each residual compares the
    host and the target each blurred by the other's streak. Videos only (photos have no
    times)."""
    exposure_fraction: float | None = Field(None, ge=0, le=1)
    """Exposure as a fraction of the frame interval; None: the one of
    ``exposure_candidates`` whose blur model fits the starting cameras best."""
    exposure_candidates: tuple[float, ...] = Field((0.0, 0.25, 0.5, 0.75), min_length=1)
    """Exposures (fractions of the frame interval) tried when ``exposure_fraction`` is None."""
    track_weight: float = Field(30.0, ge=0)
    """The tracked points' reprojection errors join the photometric residuals in one solve:
    one pixel of reprojection error costs as much as this many grey levels of photometric
    residual (0: photometric only)."""
    track_huber_px: float = Field(1.0, gt=0)
    """Huber threshold of the reprojection errors (pixels)."""
    rolling_shutter: bool = False
    """Model a rolling shutter: each image row exposed at its own time, the camera moving at
    a constant velocity (through the neighbouring keyframes) over the readout; with the
    readout chosen from the tracks, their adjustment under it is PBA's start. Videos only.
    Off by default: SfM and the geometric solution model no rolling shutter, and from their
    start it did not help on the benchmark's rolling-shutter capture (docs/poses.md)."""
    readout_s: float | None = Field(None, ge=0, le=0.1)
    """Readout time from the first row to the last (seconds; 0: global shutter); None: the
    one of ``readout_candidates`` whose model fits the keyframes best."""
    readout_candidates: tuple[float, ...] = Field((0.0, 0.01, 0.02, 0.03, 0.04), min_length=1)
    """Readouts (seconds) tried when ``readout_s`` is None (phones: about 10-35 ms)."""
    blur_samples: int = Field(9, ge=1, le=64)
    """Most samples along one streak (one per pixel of its length)."""
    max_width: int | None = Field(1920, ge=160, le=8192)
    """Keyframes wider than this (pixels) are adjusted at this width (area filter, aspect kept;
    the intrinsics scaled to it and the result's scaled back; poses are metric and do not
    change with it). PBA holds every keyframe with its pyramid and gradients, about 14 bytes
    a pixel: at 3840×2160 that is 116 MB a keyframe, 5 GB for 45 keyframes; at 1920×1080,
    29 MB. None: full resolution. 720p and 1080p captures are not affected."""


class PoseConfig(StrictModel):
    """Camera poses of the keyframes (``facecap_core/pose/stage.py``): pycolmap SfM, our
    geometric refinement with the LK tracks, then photometric bundle adjustment."""

    sfm_width: int = Field(1280, ge=320, le=8192)
    """Keyframes are given to SIFT/SfM at most this wide (pixels)."""
    match_overlap: int = Field(10, ge=1, le=100)
    """Sequential matching pairs each keyframe with this many following ones."""
    use_tracks: bool = True
    """Add the keyframe tracker's LK tracks to the SfM model and re-adjust it with the
    principal point free (otherwise the SfM result is the geometric solution)."""
    method: Literal["geometric", "pba"] = "pba"
    """Final refinement: ``pba`` (photometric bundle adjustment) or ``geometric`` only."""
    pba: PBAConfig = Field(default_factory=lambda: PBAConfig())
    """Photometric bundle adjustment settings."""
    min_registered: int = Field(5, ge=3, le=1000)
    """Fewest registered keyframes to go on with (unregistered ones are left out)."""
    min_registered_fraction: float = Field(0.5, ge=0, le=1)
    """Fewest registered keyframes as a fraction of all: below it the capture is refused, as
    the views that did register are then as likely a lucky subset as the face."""
    threads: int = Field(1, ge=1, le=256)
    """Threads for SfM's matching and mapping. One makes the stage reproducible (a rerun
    gives the same cameras, so nightly re-evaluations compare like with like); with more,
    COLMAP's threaded matching moves the focal length by up to 0.2 % from run to run."""
    extraction_threads: int = Field(2, ge=1, le=256)
    """Threads for SfM's SIFT extraction (one image each): an image's features do not
    depend on them (the same keypoints from 1 and 2 threads), so they cost no
    reproducibility; two halve the extraction, a third of SfM's time at 720p."""


class FittingConfig(StrictModel):
    """Non-rigid template fitting: optimal-step NICP (Amberg et al. 2007) to a fused point
    cloud, 3D landmarks, ear points and keyframe silhouettes (Agrawal et al. 2020, "Mesh
    fitting"). Distances in mm, weights relative to one cloud target."""

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

    ear_weight: float = Field(1.0, ge=0)
    """Ear point weight relative to the level's landmark weight."""

    edge_weight: float = Field(1.0, ge=0)
    """Weight of one silhouette target (per keyframe that sees the vertex on its contour)."""
    edge_recompute_every: int = Field(2, ge=1, le=100)
    """Recompute silhouette vertices and their edge targets every this many steps."""
    edge_first_level: int = Field(1, ge=0, le=MAX_LEVELS)
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
    edge_boundary_rings: int = Field(4, ge=0, le=100)
    """Template vertices this many edges or fewer from the template's open border never give
    silhouettes (the border is not a real contour)."""

    relax_folds: bool = True
    """Where the fitted mesh folds over, spikes or cuts through itself (a noisy cloud, a wrong
    ear point), replace its deformation there by a membrane until it is sound
    (``facecap_core/fitting/sanity.py``); the figures before and after go to ``fit.json``."""
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


class DepthMapConfig(StrictModel):
    """One keyframe's depth map: the search range from the coarse mesh, PatchMatch, and the
    per-map filter (``mvs.depth``)."""

    processing_width: int = Field(640, ge=64, le=4096)
    """Width (px) the keyframes are resized to before undistortion and matching."""
    depth_margin_mm: float = Field(8.0, gt=0, le=100)
    """Half-width of the depth search range around the coarse mesh."""
    head_dilation_px: int = Field(6, ge=0, le=100)
    """Pixels the coarse mesh's silhouette is grown by to form the computed region."""
    method: Literal["patchmatch", "sweep"] = "patchmatch"
    """How the depths are searched: ``patchmatch`` (the paper's: slanted planes, sparse
    bilateral window, ``patchmatch.py``) or ``sweep`` (fronto-parallel planes every
    ``sweep_step_mm`` around the coarse depth, dense box window, ``sweep.py``): a fifth of
    the depth stage's time, as accurate or more on rendered faces, less consistent on real
    photos and on the real head scan (docs/mvs.md, "Which depth search"). Both use the
    window radius, the best-views aggregation and the filter below; the PatchMatch fields
    only PatchMatch."""
    sweep_step_mm: float = Field(0.5, gt=0, le=10)
    """Spacing of the sweep's planes (a parabola through the best one and its neighbours
    gives the depth between them)."""
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
    seed: int = Field(0, ge=0, le=2**32 - 1)
    """Seed of the random hypotheses (results are reproducible per keyframe)."""

    max_cost: float = Field(0.5, gt=0, le=2)
    """Depths whose aggregated cost (1 - NCC) exceeds this are rejected."""
    coarse_max_distance_mm: float = Field(6.0, gt=0)
    """Depths farther than this from the coarse mesh (along the ray) are rejected."""


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


class MVSConfig(StrictModel):
    """Dense multi-view stereo: view selection, PatchMatch depth maps, filtering, fusion.
    Each part is its own stage with its own cache key: a changed fusion setting
    recomputes no depth map."""

    views: ViewSelectionConfig = ViewSelectionConfig()
    """View selection."""
    depth: DepthMapConfig = DepthMapConfig()
    """Depth maps (one stage run per keyframe)."""
    fusion: FusionConfig = FusionConfig()
    """Consistency filter and fusion."""
    workers: int = Field(2, ge=1, le=16)
    """Depth maps computed at once by one capture run (threads; the kernels release the
    GIL). It changes no result, so no artifact depends on it."""


class LandmarkConfig(StrictModel):
    """68-point landmarks per keyframe, their gate, and 3D triangulation
    (``facecap_core/landmarks/stage.py``; Agrawal et al. 2020, "Landmark constraints")."""

    min_detector_score: float = Field(0.5, ge=0.1, le=1)
    """Weakest face detection kept (MediaPipe's face detector score, 0.1-1: 0.8-0.9 on faces
    turned up to 50°; ``facecap_core/face.py``)."""
    gate_max_yaw_deg: float = Field(40.0, gt=0, le=90)
    """Gate: largest yaw of the camera around the head (from the first triangulation): the
    detector's points grow less certain beyond it."""
    gate_max_reprojection: float = Field(0.02, gt=0, le=1)
    """Gate: largest median reprojection error of a keyframe's inner points against the
    landmarks triangulated from all views, as a fraction of its face box size (the square
    root of the box area; ~0.005 for a good detection)."""
    convention_correction: bool = True
    """Move the triangulated points from the detector's image convention to 3D landmarks on
    the face (calibrated per-landmark offsets, ``facecap_core/landmarks/convention.py``)."""
    max_point_spread: float = Field(0.03, gt=0)
    """A 3D landmark is dropped (null) when its standard deviation along its least certain
    direction, for the median reprojection error, exceeds this fraction of the eye-centre
    distance (~2 mm): its inlier views are too alike."""
    min_views: int = Field(3, ge=2, le=100)
    """Fewest gated keyframes wanted; with fewer the gate widens to the best-agreeing
    detections (recorded in landmarks2d.json)."""
    outlier_threshold: float = Field(0.02, gt=0, le=1)
    """A view's observation of a point is an outlier above this reprojection error, as a
    fraction of that view's face box size."""
    huber: float = Field(0.01, gt=0, le=1)
    """Huber threshold of the robust refinement, same unit as ``outlier_threshold``."""
    min_parallax_deg: float = Field(2.0, ge=0, le=45)
    """Two views start a point's hypothesis only when their rays meet at this angle or more."""
    ear_min_yaw_deg: float = Field(45.0, ge=0, le=180)
    """Ears are searched in keyframes at least this far from frontal (profile side) ..."""
    ear_max_yaw_deg: float = Field(100.0, ge=0, le=180)
    """... and at most this far."""
    min_yaw_span_deg: float = Field(MIN_YAW_SPAN_DEG, ge=0, le=360)
    """Fewest degrees of yaw around the head that the registered keyframes must span (the
    face's sides are seen from ±20° on; with less, depth from the frontal views alone is too
    ill-conditioned for a metric face). A full capture spans about 180°."""
    irises: bool = True
    """Measure the irises (pupil centres, horizontal iris diameter) in the frontal keyframes
    from the face mesh's iris points (``facecap_core/landmarks/iris.py``): the coarse stage's
    IPD and iris-size scale cues."""
    iris_max_yaw_deg: float = Field(15.0, gt=0, le=60)
    """Irises are measured in gated keyframes at most this far from frontal: beyond, the iris
    is foreshortened and MediaPipe's diameter less certain (on the calibration renders, 15°
    gave a 4.7 % spread of the measured diameter and 0.2 % of the pupil distance; 35°: 4.8 %
    and 0.5 %)."""
    min_eye_opening: float = Field(0.2, ge=0, le=1)
    """An eye is measured only when its lids are this far apart, as a fraction of its
    corner-to-corner width (the eye aspect ratio of blink detection, from the face mesh's lid
    points): the lids of a half-closed eye cut the iris. Measured: 0.26-0.30 on rendered open
    eyes (ICT identity 11, calibration renders), 0.06-0.17 on the closed eyes of
    ``photo_set_31``."""
    ear_min_views: int = Field(3, ge=2, le=100)
    """Fewest keyframes with an ear detection for that ear's points to be triangulated."""
    ear_outlier_threshold: float = Field(0.1, gt=0, le=1)
    """An ear point's observation is an outlier above this reprojection error, as a fraction
    of the ear box diagonal (the ear predictor's error is ~0.05 of it)."""
    ear_huber: float = Field(0.03, gt=0, le=1)
    """Huber threshold of the ears' robust refinement, same unit."""

    @model_validator(mode="after")
    def _check_ranges(self):
        if self.ear_min_yaw_deg > self.ear_max_yaw_deg:
            raise ValueError("ear_min_yaw_deg exceeds ear_max_yaw_deg")
        if self.huber > self.outlier_threshold:
            raise ValueError("huber must not exceed outlier_threshold")
        return self


class CoarseConfig(StrictModel):
    """Metric scale and the coarse template fitted to the 3D landmarks
    (``facecap_core/coarse.py``)."""

    scale_method: Literal["template", "fixed"] = "template"
    """How millimetres are obtained: ``template``: the scale that makes the 3D landmarks
    (and ear points) match the template's landmarks at the template's physical size (a
    population-mean prior); ``fixed``: ``fixed_scale`` (e.g. from a known distance)."""
    fixed_scale: float = Field(1.0, gt=0)
    """Millimetres per camera unit with ``scale_method: fixed``."""
    landmark_size: float = Field(1.0858, gt=0.5, lt=2)
    """Size of an average face's inner-landmark configuration relative to the template's
    landmark vertices (robust similarity scale, template mm to mm): the mean over 200 random
    ICT identities (``benchmarks/bench_landmarks.py --calibrate`` prints it)."""
    scale_cauchy_mm: float = Field(10.0, gt=0)
    """Cauchy scale of the robust similarity that measures the landmark configuration's size
    (template mm; wide: every landmark counts, a stray one does not)."""
    landmark_size_spread: float = Field(0.05, gt=0, lt=1)
    """Relative spread (1σ) of that size over faces: the landmark cue's uncertainty (5.8 %
    RMS measured over 30 held-out ICT identities, 0.7 % on the james scan; ``tests/
    test_coarse.py``)."""
    ipd_mm: float | None = Field(None, ge=40, le=90)
    """The subject's interpupillary distance in mm as an optician measures it ("far PD"),
    when known: the scale then comes mainly from the distance between the triangulated eye
    centres (``--ipd-mm`` on the command line)."""
    ipd_ratio: float = Field(0.9800, gt=0.5, lt=1.5)
    """Pupil distance over the distance between the triangulated centres of the two eyes'
    six landmarks: the mean over the captures of ICT identities 1000-1007 (the rendered
    pupils against the landmark stage's output with exact cameras; ``benchmarks/
    bench_scale.py --calibrate``). Used for ``ipd_mm`` when the pupils were not measured."""
    ipd_spread: float = Field(0.02, gt=0, lt=1)
    """Relative 1σ of the IPD cue against the eye landmarks: the spread of that ratio over
    the calibration captures (1.1 % over 8, rounded up: a spread from 8 faces is itself
    uncertain by a quarter)."""
    pupil_ratio: float = Field(1.0055, gt=0.5, lt=1.5)
    """Pupil distance over the distance between the pupils as the landmark stage triangulates
    them: the mean over the captures of ICT identities 1000-1007 (``benchmarks/
    bench_scale.py --calibrate``). With pupils, ``ipd_mm`` uses them instead of the eye
    landmarks."""
    pupil_ipd_spread: float = Field(0.006, gt=0, lt=1)
    """Relative 1σ of the IPD cue from the triangulated pupils: the spread of ``pupil_ratio``
    over the calibration captures (0.22 % over 8), widened to 0.6 %: a spread from 8 faces is
    itself uncertain by a quarter, rendered pupils are sharper than real ones, and a subject
    who fixates a near point while the camera moves converges the eyes (a far gaze, or eyes
    that follow the camera, give the far PD)."""
    iris_cue: bool = True
    """Use the iris size as a scale cue when the landmark stage measured the irises: an
    adult's horizontal visible iris diameter is ``iris_diameter_mm`` give or take 4 %, a
    tighter prior than the face's size."""
    iris_diameter_mm: float = Field(11.7, gt=8, lt=16)
    """Mean horizontal visible iris diameter of adults (11.7 ± 0.5 mm, 1σ)."""
    iris_ratio: float = Field(0.9838, gt=0.5, lt=1.5)
    """True iris diameter over the landmark stage's measurement (MediaPipe's iris edges at
    the pupils' depth): the mean over the captures of ICT identities 1000-1007, whose renders
    paint each subject's own iris diameter (``benchmarks/bench_scale.py --calibrate``)."""
    iris_spread: float = Field(0.065, gt=0, lt=1)
    """Relative 1σ of the iris cue: the population's 4.3 % (0.5 / 11.7) and the measurement's
    3.7 % (the spread of ``iris_ratio`` over the calibration captures, 640x360 renders with
    irises ~12 px wide; 4.5 % before the face mesh gave the 68 points too), added in
    quadrature (5.5 %) and rounded up to the earlier 6.5 %."""
    ear_width_cue: bool = False
    """Use the ear-to-ear width as a scale cue. Off: it is not calibrated (``ear_width_size``
    is the template's own width) and real-skin ear points can be far off."""
    ear_width_size: float = Field(1.0, gt=0.5, lt=2)
    """Ear-to-ear width of an average head relative to the template's."""
    ear_width_spread: float = Field(0.05, gt=0, lt=1)
    """Relative spread of the ear-to-ear width over heads (weights the ear estimate)."""
    ear_weight: float = Field(1.0, ge=0)
    """Weight of one ear point against one face landmark in the similarity fit of the coarse
    mesh (0 ignores ears)."""
    cue_agreement_sigmas: float = Field(3.0, gt=0)
    """A scale cue further than this many combined standard deviations from the others'
    estimate is dropped (and reported), not averaged in."""
    robust_iterations: int = Field(5, ge=0, le=50)
    """Reweighting rounds of the robust (Cauchy) similarity fit."""
    robust_scale_mm: float = Field(3.0, gt=0)
    """Cauchy scale of the robust similarity fit, in template millimetres."""
    deformation: Literal["rbf", "nicp", "none"] = "rbf"
    """Landmark-driven deformation after the similarity: a smooth radial-basis displacement
    field (``rbf``), the landmarks-only optimal-step NICP (``nicp``), or none."""
    rbf_kernel_mm: float = Field(60.0, gt=0)
    """Width of the Gaussian displacement kernel of ``rbf`` (large: stiff, global bends)."""
    rbf_smoothing: float = Field(0.3, ge=0)
    """Regularisation of ``rbf`` (0: the landmarks are met exactly; larger: stiffer)."""
    nicp_stiffness: list[float] = Field(default_factory=lambda: [10.0, 5.0, 2.0], min_length=1,
                                        max_length=MAX_LEVELS)
    """Stiffness levels of ``nicp`` (high: the coarse mesh stays smooth); each level's
    landmark weight equals its stiffness, as in the fitting stage's schedule."""


class EarTrainingConfig(StrictModel):
    """Training set (renders of ICT identities) and training of the ear detector (dlib HOG)
    and ear-contour shape predictor (dlib ERT) (``facecap/ear_training/``)."""

    ict_model: Path | None = None
    """ICT Face Model Light ``.npz``; default ``$FACECAP_ICT_MODEL``."""
    contour_points: int = Field(12, ge=4, le=40)
    """Points on each ear's outer contour (template vertices, helix root to lobe)."""
    contour_arc_deg: tuple[float, float] = (130.0, -115.0)
    """Start and end of the contour as angles around the ear's centre seen from the side
    (0 = straight back, 90 = up, -90 = down), swept clockwise over the back of the ear."""
    identities: int = Field(80, ge=1, le=5000)
    """ICT identities rendered."""
    first_identity_seed: int = Field(100, ge=2, le=2**32 - 1)
    """Seed of the first identity (seeds 0 and 1 are held out for evaluation)."""
    identity_sigma: float = Field(1.0, ge=0, le=3)
    """Spread of the identity coefficients, in model standard deviations."""
    views_per_identity: int = Field(15, ge=1, le=1000)
    """Usable views kept per identity (sides drawn at random; right ears are mirrored)."""
    image_size: int = Field(360, ge=96, le=2048)
    """Square render size in pixels."""
    yaw_deg: tuple[float, float] = (30.0, 100.0)
    """Range of the camera's yaw around the head (0 = frontal, 90 = profile)."""
    elevation_deg: tuple[float, float] = (-15.0, 20.0)
    """Range of the camera's elevation above the eye plane."""
    roll_deg: float = Field(10.0, ge=0, le=45)
    """Largest camera roll either way."""
    distance_mm: tuple[float, float] = (300.0, 550.0)
    """Range of the camera's distance to the head's centre (perspective as in a capture)."""
    ear_height_px: tuple[float, float] = (75.0, 170.0)
    """Range of the ear contour's image height; the focal length is set to give it."""
    min_visible_fraction: float = Field(0.6, ge=0, le=1)
    """A view is kept when at least this fraction of its contour points is visible."""
    hair_probability: float = Field(0.6, ge=0, le=1)
    """Fraction of views with hair painted around the ears (random hairline, colour)."""
    rooms: int = Field(6, ge=1, le=100)
    """Random textured rooms (backgrounds) shared among the identities."""
    box_aspect: float = Field(0.75, gt=0.2, le=2)
    """Width / height of the ear boxes (fixed: HOG scans one window shape)."""
    box_padding: float = Field(0.15, ge=0, le=1)
    """Margin added on each side of the contour's extent, as a fraction of the box height."""
    detector_window_px: int = Field(80, ge=24, le=256)
    """Height of the HOG detection window (its width follows ``box_aspect``)."""
    detector_c: float = Field(30.0, gt=0)
    """SVM regularisation C of the HOG detector (larger: fits the training set harder)."""
    detector_epsilon: float = Field(0.01, gt=0)
    """Stopping tolerance of the detector's SVM solver."""
    predictor_cascade_depth: int = Field(10, ge=1, le=30)
    """Cascade levels of the shape predictor."""
    predictor_tree_depth: int = Field(4, ge=1, le=8)
    """Depth of each regression tree."""
    predictor_trees_per_level: int = Field(120, ge=1, le=2000)
    """Regression trees per cascade level (with the depth, sets the model file's size)."""
    predictor_nu: float = Field(0.1, gt=0, le=1)
    """Shrinkage (learning rate) of the tree ensemble."""
    predictor_oversampling: int = Field(20, ge=1, le=200)
    """Random initial shapes per training sample."""
    predictor_translation_jitter: float = Field(0.1, ge=0, le=1)
    """Random shifts of the training boxes (fraction of the box size): robustness to the
    detector's box placement."""
    predictor_feature_pool_size: int = Field(400, ge=10, le=5000)
    """Pixel samples per cascade level from which split features are drawn."""
    predictor_test_splits: int = Field(20, ge=1, le=500)
    """Random splits tried per tree node."""
    threads: int = Field(2, ge=1, le=256)
    """Threads for dlib's training."""
    seed: int = Field(0, ge=0, le=2**32 - 1)
    """Seed of every random draw (views, rooms, lights, noise, the predictor's trainer)."""

    @model_validator(mode="after")
    def _check_ranges(self):
        for name in ("yaw_deg", "elevation_deg", "distance_mm", "ear_height_px"):
            lo, hi = getattr(self, name)
            if lo > hi:
                raise ValueError(f"{name}: lower bound {lo} exceeds upper bound {hi}")
        if self.contour_arc_deg[0] <= self.contour_arc_deg[1]:
            raise ValueError("contour_arc_deg: the start angle must exceed the end angle")
        return self


class PipelineConfig(StrictModel):
    """Every stage's settings for one reconstruction (``facecap reconstruct --config``).

    A YAML file holds any subset: ``{mvs: {depth: {iterations: 4}}, fitting: {use_edges: false}}``;
    what it leaves out keeps its default. Each stage's artifact key hashes its own section
    only, so changing one section recomputes that stage and the ones after it."""

    keyframes: KeyframeConfig = Field(default_factory=KeyframeConfig)
    """Tracking and keyframe selection."""
    poses: PoseConfig = Field(default_factory=PoseConfig)
    """Camera poses and intrinsics."""
    landmarks: LandmarkConfig = Field(default_factory=LandmarkConfig)
    """68-point and ear landmarks, triangulation."""
    coarse: CoarseConfig = Field(default_factory=CoarseConfig)
    """Coarse template fit and metric scale."""
    mvs: MVSConfig = Field(default_factory=MVSConfig)
    """View selection, depth maps, fusion."""
    fitting: FittingConfig = Field(default_factory=FittingConfig)
    """Non-rigid template fitting and texture."""


def load_pipeline_config(source: str | Path | PipelineConfig | dict | None = None,
                         overrides: dict | None = None) -> PipelineConfig:
    """The pipeline config from a YAML file, a config given as such (a flow parameter) or
    the defaults, with ``overrides``."""
    if isinstance(source, PipelineConfig):
        source = source.model_dump(mode="json", exclude_unset=True)
    if source is None or isinstance(source, dict):
        return build(PipelineConfig, {**(source or {}), **(overrides or {})},
                     source="pipeline config")
    return load_yaml(PipelineConfig, source, overrides)
