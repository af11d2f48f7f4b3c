"""The stage graph over the store: the artifact key of every stage run, and what the flows,
the CLI's ``--until``, the run report and the UI derive from the pipeline's rows
(:data:`facecap_core.pipeline.STAGES`, each declared by its stage's module).

A stage's artifact key hashes its inputs' keys, the config section it reads (nothing else
of the config, so a setting of another stage never invalidates it) and its version;
bump a stage's version when its algorithm changes its output. A setting added to a stage
that already has results names the value at which the stage does what it did without it
(:data:`facecap_core.config.KEY_NEUTRAL`): at that value it is left out of the key. A
setting that changes none of the stage's files (its row's ``key_neutral``) is hashed at its
default whatever its value.
"""

from __future__ import annotations

from collections.abc import Iterable

from pydantic import BaseModel

from facecap.tasks.store import artifact_key
from facecap_core.config import KEY_NEUTRAL
from facecap_core.pipeline import STAGES
from facecap_core.stage import PHOTOS, VIDEO, Stage, capture_input_name

__all__ = ["ALIASES", "BY_NAME", "EXPORTED", "INPUT_VERSION", "OUTPUT_NAMES", "PHOTOS",
           "RAW_INPUTS", "STAGES", "STEPS", "UNTIL_ALIASES", "VIDEO", "Stage",
           "capture_input_name", "config_data", "is_keyframe_row", "producer", "stage_key", "stages_until"]

RAW_INPUTS = ("video", "scan", "scan_landmarks")
"""Artifacts no stage makes: the capture (a video or a photo folder) and the scan files."""


def config_data(config: BaseModel | dict | None, key_neutral: Iterable[str] = ()) -> dict:
    """A stage's settings as the JSON data its key hashes ({} without settings); a setting
    at its :data:`KEY_NEUTRAL` value is left out, and one of ``key_neutral`` (dotted names
    in the section) is its default (a mapping is hashed as given)."""
    if config is None:
        return {}
    if not isinstance(config, BaseModel):
        return dict(config)
    neutral = [name.split(".") for name in key_neutral]
    if neutral:
        defaults = type(config)().model_dump(mode="json")
        config = type(config).model_validate(_with_defaults(
            config.model_dump(mode="json"), defaults, neutral))
    data = config.model_dump(mode="json")
    for name, field in type(config).model_fields.items():
        value = getattr(config, name)
        extra = field.json_schema_extra if isinstance(field.json_schema_extra, dict) else {}
        if KEY_NEUTRAL in extra and value == extra[KEY_NEUTRAL]:
            data.pop(name, None)
        elif isinstance(value, BaseModel):
            data[name] = config_data(value)
    return data


def _with_defaults(data: dict, defaults: dict, names: list[list[str]]) -> dict:
    """``data`` with the settings at ``names`` (each a path of keys) as in ``defaults``; a
    name the settings lack is none of theirs (another model given for the stage's)."""
    for *parents, name in names:
        node, default = data, defaults
        for part in parents:
            node, default = node.get(part), default.get(part)
            if not isinstance(node, dict):
                break
        else:
            if name in node:
                node[name] = default[name]
    return data


BY_NAME = {stage.name: stage for stage in STAGES}
INPUT_VERSION = "1"
"""Version of the raw-input artifacts (a copy of the user's file)."""
ALIASES = {name: source for stage in STAGES for name, source in stage.sources.items()}
"""Input names that differ from the stage that makes them (the rows' ``sources``)."""
STEPS = tuple(stage.name for stage in STAGES)
"""What ``--until`` can stop after, in order: the stages, as the report, the stage table and
the task runs name them."""
UNTIL_ALIASES = {"mvs": "fusion"}
"""Earlier names ``--until`` still takes: ``mvs`` was views, depth and fusion together."""
EXPORTED = {stage.name: stage.exported for stage in STAGES if stage.exported}
OUTPUT_NAMES = frozenset(n for names in EXPORTED.values() for n in names) | {
    "report.json", "preview.png", "index.html", "mesh.glb"}
"""Every file a run may write into the user's output folder."""


def is_keyframe_row(row: str) -> bool:
    """Whether a run report's row is one keyframe's run of a per-keyframe stage
    (``depth_00012``), which reports summarise per stage."""
    return any(stage.is_row(row) and row != stage.name for stage in STAGES)


def producer(input_name: str, stage: Stage | None = None) -> str:
    """The stage (or raw input) an input name refers to: as ``stage`` reads it, or as any
    row names it."""
    return stage.source(input_name) if stage else ALIASES.get(input_name, input_name)


def stages_until(until: str) -> list[Stage]:
    """The stages a run stopping after stage ``until`` (or an alias) runs."""
    until = UNTIL_ALIASES.get(until, until)
    if until not in STEPS:
        raise ValueError(f"unknown step {until!r}; one of {', '.join(STEPS)}")
    return list(STAGES[: STEPS.index(until) + 1])


def stage_key(stage: Stage | str, inputs: dict[str, str], config: BaseModel | dict | None,
              params: dict | None = None) -> str:
    """The artifact key of a stage run: its inputs' keys, its settings, its version and its
    per-keyframe parameters. Give the settings as their model, as the flows do: a mapping is
    hashed as given, key-neutral settings included."""
    if isinstance(stage, str):
        if stage not in BY_NAME:
            raise ValueError(f"unknown stage {stage!r}")
        stage = BY_NAME[stage]
    return artifact_key(stage.name, inputs, config_data(config, stage.key_neutral),
                        stage.full_version(), params)

