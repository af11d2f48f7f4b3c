"""What a stage declares about itself: its row of the pipeline.

Each stage module ends with ``STAGE = Stage(...)``: its name, its algorithm version, the
artifacts it reads, the settings it reads, the files it writes and its ``run``;
:data:`facecap_core.pipeline.STAGES` lists the rows in the order they run, and the tasks,
the flows, the run report and the UI read them from there. A stage reads another's files
only through that stage's module (``inputs["fusion"] / fusion.CLOUD``), whose row lists them.
"""

from __future__ import annotations

import re
import string
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pydantic import BaseModel

Folders = dict[str, Path]
"""A stage's input folders by input name (``{"frames": Path, "coarse": Path, ...}``)."""
Run = Callable[[Folders, Path, Any, dict], None]

VIDEO = "video.mp4"
PHOTOS = "photos"


def capture_in(folder: Path) -> Path:
    """The capture inside its input artifact: the video file or the photo folder."""
    return folder / PHOTOS if (folder / PHOTOS).is_dir() else folder / VIDEO


def capture_input_name(path: str | Path) -> str:
    """Name of a capture in its input artifact: ``video.mp4``, or ``photos`` for a folder."""
    return PHOTOS if Path(path).is_dir() else VIDEO


class OutputMismatch(RuntimeError):
    """A stage run wrote other files than its row lists: a bug of the stage or of its row."""


def output_pattern(name: str, params: dict | None = None) -> re.Pattern:
    """The files an entry of :attr:`Stage.outputs` stands for. A field the run's params
    give is filled in (``depth_{index:05d}.npz`` with ``{"index": 12}``: ``depth_00012.npz``);
    a field they do not give matches any value, digits for an integer format
    (``frame_{index:06d}.png``: one PNG per keyframe)."""
    params = params or {}
    parts = []
    for literal, field_name, spec, _ in string.Formatter().parse(name):
        parts.append(re.escape(literal))
        if field_name is None:
            continue
        if field_name in params:
            parts.append(re.escape(format(params[field_name], spec or "")))
        elif spec.endswith("d"):
            width = int(spec[:-1].lstrip("0") or 0)
            parts.append(rf"\d{{{max(width, 1)},}}")
        else:
            parts.append(r"[^/]+")
    return re.compile("".join(parts))


@dataclass(frozen=True)
class Stage:
    """One row of the pipeline."""

    name: str
    """Stage name: the artifact key's prefix, the task's name, the report's row."""
    version: str
    """Algorithm version, part of every artifact key: bump it when the output changes."""
    inputs: tuple[str, ...]
    """Artifacts it reads: earlier stages or the raw inputs (``video``, ``scan``, ...),
    all required."""
    section: str | None
    """Dotted path of the :class:`~facecap_core.pipeline.PipelineConfig` section it reads
    (``"mvs.depth"``), or None for a stage without settings."""
    run: Run
    """``run(inputs, out_dir, config, params)``: reads the input folders (by input name)
    and its settings (the section's model, None without one), writes its files into
    ``out_dir``."""
    outputs: tuple[str, ...]
    """Files it writes, exactly (the runner checks every run: :meth:`check_outputs`), as
    paths in its artifact folder. A name with a format field stands for the files the
    field's values name: filled from the run's params (``depth_{index:05d}.npz`` of a
    per-keyframe stage: one file), or, a field the params do not give, one or more files
    (``frame_{index:06d}.png``: one per keyframe). A fixed set of names is listed one by
    one (``heatmap_similarity.png``, ``heatmap_metric.png``)."""
    work_seconds: float
    """Its share of a capture's work, for the run's progress bar: its seconds on an 8 s
    720p capture on 2 cores (``docs/benchmarks.md``), all keyframes' runs together for a
    per-keyframe stage."""
    exported: tuple[str, ...] = ()
    """Those of its files copied into the user's output folder."""
    optional_outputs: tuple[str, ...] = ()
    """Files it writes only when it has something to put in them (the pose stage's
    ``points.ply``: none without sparse points); named as :attr:`outputs`."""
    optional: tuple[str, ...] = ()
    """Inputs it reads when they are given."""
    key_neutral: dict[str, str] = field(default_factory=dict, hash=False)
    """Settings of its section that change none of its files, ``{dotted name in the section:
    why}`` (the pose stage's ``extraction_threads``: how many threads extract the SIFT
    features). Its artifact key hashes each at its default whatever the value, so a changed
    one reuses the stored artifact (``facecap.tasks.graph.config_data``)."""
    sources: dict[str, str] = field(default_factory=dict, hash=False)
    """Inputs named otherwise than the stage that makes them: ``{input name: stage}`` (the
    evaluation's ``mesh`` is the fitting stage's artifact); see :meth:`source`."""
    per_keyframe: Callable[[Folders], list[int]] | None = None
    """For a stage run once per keyframe: the keyframe indices, read from its inputs; each
    run gets ``params={"index": i}`` and its report row is :meth:`row_name`."""
    version_suffix: Callable[[], str] | None = field(default=None, repr=False)
    """Part of the version that is not code: the digest of a trained model the stage reads."""
    figures: Callable[[Path], dict] | None = field(default=None, repr=False)
    """Headline figures of its artifact folder for the run report and the UI."""
    headline: Callable[[Path], str] | None = field(default=None, repr=False)
    """What its task's log line adds after "computed"/"reused", from its artifact folder
    (the coarse stage: ``: metric scale 90.9 mm per camera unit, ...``), or "" for nothing."""

    def full_version(self) -> str:
        return f"{self.version}+{self.version_suffix()}" if self.version_suffix else self.version

    def source(self, input_name: str) -> str:
        """The stage (or raw input) whose artifact its input ``input_name`` is."""
        return self.sources.get(input_name, input_name)

    def row_name(self, params: dict | None = None) -> str:
        """The run's row in the report and its artifact's input name for the next stage:
        ``depth_00012`` for keyframe 12 of a per-keyframe stage, else the stage's name."""
        return f"{self.name}_{params['index']:05d}" if params else self.name

    def is_row(self, name: str) -> bool:
        """Whether ``name`` is one of this stage's rows (:meth:`row_name`)."""
        return name == self.name or (self.per_keyframe is not None
                                     and name.startswith(f"{self.name}_"))

    def check_outputs(self, files: Iterable[str], params: dict | None = None) -> None:
        """Raise :class:`OutputMismatch` unless ``files`` (the paths a run wrote, relative
        to its folder) are exactly what the row lists: every file listed in
        :attr:`outputs` or :attr:`optional_outputs`, every entry of :attr:`outputs`
        written."""
        files = sorted(set(files))
        listed = [(name, output_pattern(name, params)) for name in self.outputs]
        maybe = [output_pattern(name, params) for name in self.optional_outputs]
        unlisted = [f for f in files
                    if not any(p.fullmatch(f) for _, p in listed) and
                    not any(p.fullmatch(f) for p in maybe)]
        missing = [name for name, p in listed if not any(p.fullmatch(f) for f in files)]
        if unlisted or missing:
            said = [f"wrote {', '.join(unlisted)}, which its row does not list"] if unlisted else []
            if missing:
                said.append(f"did not write {', '.join(missing)}, which its row lists")
            raise OutputMismatch(f"the {self.name} stage {' and '.join(said)} "
                                 f"(Stage.outputs in its module)")

    def settings(self, pipeline: BaseModel) -> BaseModel | None:
        """The section of ``pipeline`` (a PipelineConfig) that this stage reads."""
        if self.section is None:
            return None
        value: Any = pipeline
        for part in self.section.split("."):
            value = getattr(value, part)
        return value
