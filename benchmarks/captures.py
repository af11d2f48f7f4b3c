"""The synthetic captures the benchmarks score, rendered once into a captures folder and
reused by every benchmark that asks for the same one."""

from __future__ import annotations

from pathlib import Path

from facecap.synthetic import synthesize
from facecap.synthetic.config import SynthConfig


def capture_for(subject: str, captures: Path, ict_model: str | Path | None = None,
                **settings) -> Path:
    """The folder of ``subject``'s capture under ``captures``, rendered the first time.
    ``settings``: :class:`SynthConfig`'s ``width``, ``height``, ``fps`` and ``duration_s``
    (its defaults otherwise), which name the folder (``ict_0_1280x720_60fps_8s``); None
    for ``ict_model`` is ``$FACECAP_ICT_MODEL`` or the packaged model."""
    config = SynthConfig(subject=subject, ict_model=ict_model, **settings)
    folder = captures / (f"{subject.replace(':', '_')}_{config.width}x{config.height}_"
                         f"{config.fps:g}fps_{config.duration_s:g}s")
    if not (folder / "gt" / "render.json").is_file():
        print(f"rendering {subject} into {folder} ...", flush=True)
        synthesize(config, folder, progress=False)
    return folder
