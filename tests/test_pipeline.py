"""One stage run alone on folders: ``python -m facecap_core.pipeline``."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from facecap.synthetic import synthesize
from facecap.synthetic.config import SynthConfig
from facecap_core import keyframes
from facecap_core.pipeline import run_alone

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def video_artifact(tmp_path_factory, ict_model) -> Path:
    """A capture's input artifact as the store keeps it: a folder holding ``video.mp4``."""
    folder = tmp_path_factory.mktemp("capture")
    config = SynthConfig(subject="ict:0", ict_model=ict_model, width=320, height=180, fps=10,
                         duration_s=4.0)
    capture = synthesize(config, folder / "render", progress=False)
    artifact = folder / "video"
    artifact.mkdir()
    shutil.copy(capture.video, artifact / "video.mp4")
    return artifact


def test_a_stage_runs_alone_on_folders_with_its_section_of_the_config(video_artifact, tmp_path):
    """The keyframe stage run alone writes what the stage writes; a config file's section
    reaches it (wider keyframe spacing, fewer keyframes)."""
    alone = run_alone(["keyframes", "--input", f"video={video_artifact}",
                       "--out", str(tmp_path / "alone")])
    direct = keyframes.main(video_artifact / "video.mp4", tmp_path / "direct")

    def selection(path: Path) -> dict:  # all but the timings
        doc = json.loads(path.read_text())
        return {k: v for k, v in doc.items() if k not in ("seconds", "cpu_seconds")}

    assert selection(alone / keyframes.KEYFRAMES_JSON) == selection(direct)
    (tmp_path / "wide.yaml").write_text("keyframes: {keyframe_angle_deg: 12}\n")
    wide = run_alone(["keyframes", "--input", f"video={video_artifact}", "--config",
                      str(tmp_path / "wide.yaml"), "--out", str(tmp_path / "wide")])
    count = {name: len(selection(folder / keyframes.KEYFRAMES_JSON)["frame_indices"])
             for name, folder in (("default", alone), ("wide", wide))}
    assert count["wide"] < count["default"], count


@pytest.mark.parametrize("argv, says", [
    (["poses", "--input", "video=."], "--input keyframes=FOLDER"),
    (["keyframes", "--input", "video"], "give NAME=FOLDER"),
    (["depth", "--input", "frames=.", "--input", "coarse=.", "--input", "views=."],
     "--index is for a per-keyframe stage"),
    (["stitching"], "invalid choice"),
], ids=["a missing input", "an input without a folder", "depth without --index",
        "no such stage"])
def test_what_the_stage_cannot_run_on_is_one_line_and_exit_2(argv, says, tmp_path):
    proc = subprocess.run([sys.executable, "-m", "facecap_core.pipeline", *argv, "--out",
                           str(tmp_path / "out")], capture_output=True, text=True, cwd=tmp_path)
    assert proc.returncode == 2
    assert says in proc.stderr.strip().splitlines()[-1], proc.stderr
