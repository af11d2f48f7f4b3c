"""What a stage declares about itself: its row of the pipeline.

Each stage module ends with ``STAGE = Stage(...)``: its name, its algorithm version, the
artifacts it reads, the settings it reads, the files it writes and its ``run``;
:data:`facecap_core.pipeline.STAGES` lists the rows in the order they run, and the tasks,
the flows, the run report and the UI read them from there. A stage reads another's files
only through that stage's module (``inputs["fusion"] / fusion.CLOUD``), whose row lists them.
"""

from __future__ import annotations

from collections.abc import Callable
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


@dataclass(frozen=True)
class Stage:
    """One row of the pipeline."""

    name: str
    """Stage name: the artifact key's prefix, the task's name, the report's row."""
    step: str
    """The ``--until`` step the stage belongs to (several stages may share one)."""
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
    """Files it writes (a ``{index}`` field for per-keyframe stages)."""
    exported: tuple[str, ...] = ()
    """Those of its files copied into the user's output folder."""
    optional: tuple[str, ...] = ()
    """Inputs it reads when they are given."""
    per_keyframe: Callable[[Folders], list[int]] | None = None
    """For a stage run once per keyframe: the keyframe indices, read from its inputs; each
    run gets ``params={"index": i}`` and its report row is :meth:`row_name`."""
    version_suffix: Callable[[], str] | None = field(default=None, repr=False)
    """Part of the version that is not code: the digest of a trained model the stage reads."""
    figures: Callable[[Path], dict] | None = field(default=None, repr=False)
    """Headline figures of its artifact folder for the run report and the UI."""

    def full_version(self) -> str:
        return f"{self.version}+{self.version_suffix()}" if self.version_suffix else self.version

    def row_name(self, params: dict | None = None) -> str:
        """The run's row in the report and its artifact's input name for the next stage:
        ``depth_00012`` for keyframe 12 of a per-keyframe stage, else the stage's name."""
        return f"{self.name}_{params['index']:05d}" if params else self.name

    def is_row(self, name: str) -> bool:
        """Whether ``name`` is one of this stage's rows (:meth:`row_name`)."""
        return name == self.name or (self.per_keyframe is not None
                                     and name.startswith(f"{self.name}_"))

    def settings(self, pipeline: BaseModel) -> BaseModel | None:
        """The section of ``pipeline`` (a PipelineConfig) that this stage reads."""
        if self.section is None:
            return None
        value: Any = pipeline
        for part in self.section.split("."):
            value = getattr(value, part)
        return value
