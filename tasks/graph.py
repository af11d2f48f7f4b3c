"""The stage graph in one table: per stage its inputs, the config section it reads, the
files it writes, its algorithm version and the function that computes it.

Tasks, flows, the CLI's ``--until``, the run report and the UI read :data:`STAGES`; adding a
stage is one row here plus its module in ``facecap_core``. A stage's artifact key hashes its
inputs' keys, the whole config section it reads (nothing else of the config, so a setting of
another stage never invalidates it) and its version; bump a version when the algorithm
changes its output.
"""

from __future__ import annotations

import hashlib
import importlib
from collections.abc import Callable
from dataclasses import dataclass, field
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

from pydantic import BaseModel

from facecap.tasks.store import artifact_key
from facecap_core import coarse, evaluation, frames, keyframes, pose
from facecap_core import config as cfg
from facecap_core.camera import CAMERAS_JSON
from facecap_core.coarse import COARSE_JSON, COARSE_PLY
from facecap_core.evaluation import EVALUATION_JSON, PROTOCOLS
from facecap_core.face import MESH_TO_68_FILE
from facecap_core.fitting.run import FIT_JSON, MESH_LANDMARKS, MESH_OBJ, MESH_PLY
from facecap_core.frames import FRAMES_JSON
from facecap_core.keyframes import KEYFRAMES_JSON, TRACKS_NPZ
from facecap_core.landmarks import stage
from facecap_core.landmarks.convention import OFFSETS_FILE
from facecap_core.landmarks.ears import model_digest
from facecap_core.landmarks.stage import EARS_3D, LANDMARKS_2D, LANDMARKS_3D
from facecap_core.mvs import depth, fusion, views
from facecap_core.mvs.fusion import CLOUD, FUSION
from facecap_core.mvs.views import VIEWS, read_views
from facecap_core.pose.stage import COLMAP_MODEL, POINTS, SPARSE

VIDEO = "video.mp4"
PHOTOS = "photos"
RAW_INPUTS = ("video", "scan", "scan_landmarks")
"""Artifacts no stage makes: the capture (a video or a photo folder) and the scan files."""

Folders = dict[str, Path]
Compute = Callable[[Folders, Path, BaseModel | None, dict], None]


@dataclass(frozen=True)
class Stage:
    """One row of the stage graph."""

    name: str
    """Stage name: the artifact key's prefix, the task's name, the report's row."""
    step: str
    """The ``--until`` step the stage belongs to (several stages may share one)."""
    version: str
    """Algorithm version, part of every artifact key: bump it when the output changes."""
    inputs: tuple[str, ...]
    """Artifacts it reads: earlier stages or :data:`RAW_INPUTS`, all required."""
    section: str | None
    """Dotted path of the :class:`PipelineConfig` section it reads (``"mvs.depth"``), or
    None for a stage without settings."""
    compute: Compute
    """``compute(folders, out_dir, config, params)``: reads the input folders (by input
    name), writes its files into ``out_dir``."""
    outputs: tuple[str, ...]
    """Files it writes (a ``{index}`` field for per-keyframe stages)."""
    exported: tuple[str, ...] = ()
    """Those of its files copied into the user's output folder."""
    optional: tuple[str, ...] = ()
    """Inputs it reads when they are given."""
    per_keyframe: Callable[[Folders], list[int]] | None = None
    """For a stage computed once per keyframe: the keyframe indices, read from its inputs;
    each run gets ``params={"index": i}`` and its report row is ``<name>_<index:05d>``."""
    version_suffix: Callable[[], str] | None = field(default=None, repr=False)
    """Part of the version that is not code: the digest of a trained model the stage reads."""
    figures: Callable[[Path], dict] | None = field(default=None, repr=False)
    """Headline figures of its artifact folder for the run report and the UI."""

    def key(self, inputs: dict[str, str], config: dict | None, params: dict | None = None
            ) -> str:
        return artifact_key(self.name, inputs, config or {}, self.full_version(), params)

    def full_version(self) -> str:
        return f"{self.version}+{self.version_suffix()}" if self.version_suffix else self.version

    def config_model(self, data: dict | None) -> BaseModel | None:
        """The section's config model from its JSON data (strict: unknown keys fail)."""
        if self.section is None:
            return None
        return cfg.build(section_model(self.section), dict(data or {}), source=self.section)

    def config_data(self, pipeline: cfg.PipelineConfig) -> dict:
        """The JSON data of the section this stage reads ({} without one)."""
        if self.section is None:
            return {}
        value: Any = pipeline
        for part in self.section.split("."):
            value = getattr(value, part)
        return value.model_dump(mode="json")

    def row_name(self, params: dict | None) -> str:
        return f"{self.name}_{params['index']:05d}" if params else self.name


def section_model(section: str) -> type[BaseModel]:
    """The config model at a dotted path of :class:`PipelineConfig`."""
    model: type[BaseModel] = cfg.PipelineConfig
    for part in section.split("."):
        model = model.model_fields[part].annotation
    return model


def capture_input_name(path: str | Path) -> str:
    """Name of a capture in its input artifact: ``video.mp4``, or ``photos`` for a folder."""
    return PHOTOS if Path(path).is_dir() else VIDEO


def _capture(folder: Path) -> Path:
    """The capture inside its input artifact: the video file or the photo folder."""
    return folder / PHOTOS if (folder / PHOTOS).is_dir() else folder / VIDEO


# -- stage bodies ----------------------------------------------------------------------------


def compute_keyframes(f: Folders, out: Path, config, params: dict) -> None:
    keyframes.main(_capture(f["video"]), out, config)


def compute_poses(f: Folders, out: Path, config, params: dict) -> None:
    pose.main(_capture(f["video"]), f["keyframes"] / KEYFRAMES_JSON, out, config)


def compute_frames(f: Folders, out: Path, config, params: dict) -> None:
    frames.main(_capture(f["video"]), f["poses"] / CAMERAS_JSON, out)


def compute_landmarks(f: Folders, out: Path, config, params: dict) -> None:
    stage.main(_capture(f["video"]), f["poses"] / CAMERAS_JSON, out, config)


def compute_coarse(f: Folders, out: Path, config, params: dict) -> None:
    coarse.main(f["landmarks"], f["poses"] / CAMERAS_JSON, out, config=config)


def compute_views(f: Folders, out: Path, config, params: dict) -> None:
    views.main(f["frames"], f["coarse"] / CAMERAS_JSON, f["coarse"] / COARSE_PLY, out,
               config, f["poses"] / SPARSE)


def compute_depth(f: Folders, out: Path, config, params: dict) -> None:
    depth.main(params["index"], f["frames"], f["coarse"] / CAMERAS_JSON, f["views"] / VIEWS,
               f["coarse"] / COARSE_PLY, out, config)


def compute_fusion(f: Folders, out: Path, config, params: dict) -> None:
    maps = sorted(p for name, folder in f.items() if name.startswith("depth_")
                  for p in folder.glob("depth_*.npz"))
    fusion.main(maps, f["frames"], f["coarse"] / CAMERAS_JSON, out, config)


def compute_fitting(f: Folders, out: Path, config, params: dict) -> None:
    from facecap_core.fitting.stage import main

    main(f["fusion"] / CLOUD, f["coarse"], f["frames"], out, config)


def compute_evaluation(f: Folders, out: Path, config, params: dict) -> None:
    evaluation.main(f["mesh"], f["scan"], out, scan_landmarks=f.get("scan_landmarks"))


def _reference_keyframes(f: Folders) -> list[int]:
    return sorted(read_views(f["views"] / VIEWS))


def _figures(module: str) -> Callable[[Path], dict]:
    """The ``figures(folder)`` function of a stage module, imported when called."""
    def figures(folder: Path) -> dict:
        return importlib.import_module(f"facecap_core.{module}").figures(folder)
    return figures


def _landmark_models() -> str:
    """The models and tables the landmark stage ran, as part of its version: the ear model
    (retrained, or replaced through $FACECAP_EAR_MODELS), the face mesh's (mediapipe is
    installed apart from the other dependencies, so its version is not fixed by the
    package's), and the calibrated tables that turn mesh vertices into 3D landmarks (a
    recalibration changes every landmark)."""


    try:
        mesh = f"mediapipe-{version('mediapipe')}"
    except PackageNotFoundError:
        mesh = "no-mediapipe"
    tables = hashlib.sha256(MESH_TO_68_FILE.read_bytes() + OFFSETS_FILE.read_bytes())
    return f"ears-{model_digest()}-{mesh}-tables-{tables.hexdigest()[:12]}"


# -- the table -------------------------------------------------------------------------------

STAGES: tuple[Stage, ...] = (
    Stage("keyframes", "keyframes", "2", ("video",), "keyframes", compute_keyframes,
          (KEYFRAMES_JSON, TRACKS_NPZ)),
    Stage("poses", "poses", "3", ("video", "keyframes"), "poses", compute_poses,
          (CAMERAS_JSON, POINTS, SPARSE, *COLMAP_MODEL),
          exported=(CAMERAS_JSON, POINTS, *COLMAP_MODEL), figures=_figures("pose.stage")),
    Stage("frames", "landmarks", "1", ("video", "poses"), None, compute_frames,
          (FRAMES_JSON, "frame_{index:06d}.png")),
    Stage("landmarks", "landmarks", "7", ("video", "poses"), "landmarks", compute_landmarks,
          (LANDMARKS_2D, LANDMARKS_3D, EARS_3D),
          version_suffix=_landmark_models),
    Stage("coarse", "coarse", "5", ("landmarks", "poses"), "coarse", compute_coarse,
          (CAMERAS_JSON, LANDMARKS_3D, EARS_3D, COARSE_PLY, COARSE_JSON),
          exported=(CAMERAS_JSON, LANDMARKS_3D, EARS_3D, COARSE_PLY, COARSE_JSON),
          figures=_figures("coarse")),
    Stage("views", "mvs", "1", ("frames", "coarse", "poses"), "mvs.views", compute_views,
          (VIEWS,)),
    Stage("depth", "mvs", "1", ("frames", "coarse", "views"), "mvs.depth", compute_depth,
          ("depth_{index:05d}.npz", "depth_{index:05d}.json"),
          per_keyframe=_reference_keyframes),
    Stage("fusion", "mvs", "2", ("frames", "coarse", "depth"), "mvs.fusion", compute_fusion,
          (CLOUD, FUSION), exported=(CLOUD,)),
    Stage("fitting", "fitting", "6", ("fusion", "coarse", "frames"), "fitting",
          compute_fitting, (MESH_PLY, MESH_OBJ, MESH_LANDMARKS, FIT_JSON),
          exported=(MESH_PLY, MESH_OBJ, FIT_JSON), figures=_figures("fitting.stage")),
    Stage("evaluation", "evaluation", "3", ("mesh", "scan"), None, compute_evaluation,
          (EVALUATION_JSON, *(f"heatmap_{p}.png" for p in PROTOCOLS)),
          exported=(EVALUATION_JSON, *(f"heatmap_{p}.png" for p in PROTOCOLS)),
          optional=("scan_landmarks",), figures=_figures("evaluation.stage")),
)
"""The stages in the order they run."""

BY_NAME = {stage.name: stage for stage in STAGES}
INPUT_VERSION = "1"
"""Version of the raw-input artifacts (a copy of the user's file)."""
ALIASES = {"mesh": "fitting"}
"""Input names that differ from the stage that makes them."""
STEPS = tuple(stage.name for stage in STAGES)
"""What ``--until`` can stop after, in order: the stages, as the report, the stage table and
the task runs name them."""
UNTIL_ALIASES = {"mvs": "fusion"}
"""Earlier names ``--until`` still takes: ``mvs`` was views, depth and fusion together."""
EXPORTED = {stage.name: stage.exported for stage in STAGES if stage.exported}
OUTPUT_NAMES = frozenset(n for names in EXPORTED.values() for n in names) | {
    "report.json", "preview.png", "index.html", "mesh.glb"}
"""Every file a run may write into the user's output folder."""


def producer(input_name: str) -> str:
    """The stage (or raw input) an input name refers to."""
    return ALIASES.get(input_name, input_name)


def stages_until(until: str) -> list[Stage]:
    """The stages a run stopping after stage ``until`` (or an alias) runs."""
    until = UNTIL_ALIASES.get(until, until)
    if until not in STEPS:
        raise ValueError(f"unknown step {until!r}; one of {', '.join(STEPS)}")
    return list(STAGES[: STEPS.index(until) + 1])


def stage_key(name: str, inputs: dict[str, str], config: dict | None,
              params: dict | None = None) -> str:
    """The artifact key of a stage call."""
    if name not in BY_NAME:
        raise ValueError(f"unknown stage {name!r}")
    return BY_NAME[name].key(inputs, config, params)

