"""The pipeline: its stages in the order they run, and their settings assembled into the
one config of a run.

Adding a stage is its module (its settings model, its ``run`` and its ``STAGE`` row,
:mod:`facecap_core.stage`) and its line in :data:`STAGES` here; a stage with settings also
names its section in :class:`PipelineConfig`.

One stage runs alone on folders, without Prefect or the store (to debug it, or to try a
setting on one capture's artifacts)::

    python -m facecap_core.pipeline depth --input frames=F --input coarse=C --input views=V \
        --index 12 --config pipeline.yaml --out OUT

Each input is a folder laid out as the store keeps that artifact (the capture's holds
``video.mp4`` or ``photos/``); the stage writes its files into ``OUT``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pydantic import BaseModel, Field

from facecap_core import coarse, frames, keyframes
from facecap_core.coarse import CoarseConfig
from facecap_core.config import StrictModel, build, load_yaml
from facecap_core.errors import FacecapError
from facecap_core.evaluation import stage as evaluation_stage
from facecap_core.evaluation.settings import EvaluationConfig
from facecap_core.fitting import stage as fitting_stage
from facecap_core.fitting.settings import FittingConfig
from facecap_core.keyframes import KeyframeConfig
from facecap_core.landmarks import stage as landmark_stage
from facecap_core.landmarks.stage import LandmarkConfig
from facecap_core.mvs import depth, fusion, views
from facecap_core.mvs.depth import DepthMapConfig
from facecap_core.mvs.fusion import FusionConfig
from facecap_core.mvs.views import ViewSelectionConfig
from facecap_core.pose import stage as pose_stage
from facecap_core.pose.stage import PoseConfig
from facecap_core.stage import Stage


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
    evaluation: EvaluationConfig = Field(default_factory=EvaluationConfig)
    """The scoring protocol against a scan (a run given one)."""


def section_model(section: str) -> type[BaseModel]:
    """The settings model at a dotted path of :class:`PipelineConfig` (``"mvs.depth"``)."""
    model: type[BaseModel] = PipelineConfig
    for part in section.split("."):
        model = model.model_fields[part].annotation
    return model


def load_pipeline_config(source: str | Path | PipelineConfig | dict | None = None,
                         overrides: dict | None = None) -> PipelineConfig:
    """The pipeline config from a YAML file, a config given as such (a flow parameter) or
    the defaults, with ``overrides``."""
    if isinstance(source, PipelineConfig):
        if not overrides:
            return source  # validated where it was made
        source = source.model_dump(mode="json", exclude_unset=True)
    if source is None or isinstance(source, dict):
        return build(PipelineConfig, {**(source or {}), **(overrides or {})},
                     source="pipeline config")
    return load_yaml(PipelineConfig, source, overrides)


STAGES: tuple[Stage, ...] = (
    keyframes.STAGE,
    pose_stage.STAGE,
    frames.STAGE,
    landmark_stage.STAGE,
    coarse.STAGE,
    views.STAGE,
    depth.STAGE,
    fusion.STAGE,
    fitting_stage.STAGE,
    evaluation_stage.STAGE,
)
"""The stages in the order they run."""


def run_alone(argv: list[str] | None = None) -> Path:
    """``python -m facecap_core.pipeline``: one stage on folders; returns its output folder."""
    parser = argparse.ArgumentParser(
        prog="python -m facecap_core.pipeline",
        description="Run one stage alone on folders laid out as the store keeps artifacts.")
    parser.add_argument("stage", choices=[stage.name for stage in STAGES])
    parser.add_argument("--input", action="append", default=[], metavar="NAME=FOLDER",
                        help="an input artifact's folder (repeat for each input)")
    parser.add_argument("--out", required=True, help="the folder the stage writes into")
    parser.add_argument("--config", help="a PipelineConfig YAML (the stage reads its section)")
    parser.add_argument("--index", type=int, help="the keyframe, for a per-keyframe stage")
    args = parser.parse_args(argv)
    stage = next(s for s in STAGES if s.name == args.stage)
    inputs = {}
    for item in args.input:
        name, sep, folder = item.partition("=")
        if not sep or not name or not Path(folder).is_dir():
            parser.error(f"--input {item}: give NAME=FOLDER with an existing folder")
        inputs[name] = Path(folder)
    missing = [name for name in stage.inputs if name not in inputs]
    if missing:
        parser.error(f"the {stage.name} stage reads {', '.join(missing)}: give "
                     + " ".join(f"--input {name}=FOLDER" for name in missing))
    if (args.index is None) != (stage.per_keyframe is None):
        parser.error(f"--index is for a per-keyframe stage, which {stage.name} "
                     f"{'is' if stage.per_keyframe else 'is not'}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    params = {"index": args.index} if stage.per_keyframe else {}
    stage.run(inputs, out, stage.settings(load_pipeline_config(args.config)), params)
    return out


if __name__ == "__main__":
    try:
        print(run_alone())
    except FacecapError as exc:
        print(f"python -m facecap_core.pipeline: error: {exc}", file=sys.stderr)
        sys.exit(2)
