"""The synthetic captures the benchmarks score, rendered once into a captures folder and
reused by every benchmark that asks for the same one."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from facecap.synthetic import load_gt_cameras, synthesize
from facecap.synthetic.config import SynthConfig
from facecap_core.camera import Intrinsics, camera_center
from facecap_core.geometry import umeyama


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


def true_frames(gt_dir: Path) -> tuple[Intrinsics, dict[int, dict]]:
    """A rendered capture's true intrinsics and cameras by frame index (``gt/cameras.json``)."""
    intr, frames = load_gt_cameras(gt_dir / "cameras.json")
    return intr, {int(f["index"]): f for f in frames}


def truth_to_run(cams, frames: dict[int, dict], indices) -> tuple[float, np.ndarray, np.ndarray]:
    """The similarity (s, R, t) that best maps the true centres of the keyframes ``indices``
    (``frames``: :func:`true_frames`) onto a run's (``cams``: ``read_cameras_json``): the
    truth moved into the run's frame, its figures holding the pose stage's errors, not its
    gauge."""
    est = np.array([camera_center(*cams.pose(i)) for i in indices])
    true = np.array([camera_center(frames[i]["R"], frames[i]["t"]) for i in indices])
    return umeyama(true, est, with_scale=True)
