"""Every setting is read by its stage: changed to another valid value, it changes the files
the stage writes, on a small rendered capture (or its row lists it as key-neutral, with its
reason, and then the stage's artifact key does not change with it).

``tests/test_graph.py`` checks that a setting changes the keys it should and that code names
it; this runs the stage. A field the stage ignores would still recompute the stage and every
one after it, for the same files.

A run of the suite checks :data:`SAMPLE` fields drawn at random (``FACECAP_SETTINGS_FIELDS=all``:
every one). Each stage runs on the artifacts of the stages before it, computed once at :data:`BASE`
(settings that keep the capture small and the stages quick, each of them a valid setting
itself); a field is changed from there. Where a field acts only under another setting
(``coarse.fixed_scale`` with ``scale_method: fixed``), :data:`CONTEXT` gives that setting to
both runs.
"""

from __future__ import annotations

import copy
import hashlib
import json
import os
import random
import shutil
from pathlib import Path

import pytest
from pydantic import BaseModel

from facecap.tasks.graph import stage_key
from facecap_core.errors import FacecapError
from facecap_core.pipeline import STAGES, PipelineConfig, section_model
from facecap_core.stage import Stage
from tests.test_graph import leaf_fields, other_value

pytestmark = pytest.mark.slow

BASE = {
    # Fewer keyframes (about 20 of this capture's 90 frames): enough for the camera solve.
    "keyframes": {"keyframe_angle_deg": 10.0},
    "mvs": {"depth": {"processing_width": 160, "window_radius": 2, "iterations": 2}},
    # Two levels of two steps: each term still acts, in a fraction of the time.
    "fitting": {"stiffness": [20.0, 5.0], "landmark_weight": [20.0, 5.0],
                "iterations_per_level": 2},
}
"""The settings the stages run at, as a PipelineConfig's data."""

CONTEXT: dict[str, dict] = {
    "coarse.fixed_scale": {"coarse.scale_method": "fixed"},
    "coarse.pupil_ratio": {"coarse.ipd_mm": 63.0},
    "coarse.pupil_ipd_spread": {"coarse.ipd_mm": 63.0},
    "coarse.ear_width_size": {"coarse.ear_width_cue": True},
    "coarse.ear_width_spread": {"coarse.ear_width_cue": True},
    "coarse.nicp_stiffness": {"coarse.deformation": "nicp"},
    "mvs.depth.sweep_step_mm": {"mvs.depth.method": "sweep"},
    "mvs.depth.fine_iterations": {"mvs.depth.levels": 2},
    "mvs.depth.sweep_iterations": {"mvs.depth.start": "sweep"},
    "mvs.depth.start_normal_sigma_px": {"mvs.depth.start": "sweep"},
    # The render's shutter is global: a readout chosen from the candidates is 0 s.
    "poses.pba.rolling_shutter": {"poses.pba.readout_s": 0.02},
    "poses.pba.readout_s": {"poses.pba.rolling_shutter": True},
    # Settings of the search for photometric points, which the sparse points replace.
    **{f"poses.pba.{name}": {"poses.pba.points_from_sparse": False} for name in (
        "cell", "min_gradient", "search_level", "search_samples", "min_search_quality")},
    "poses.pba.readout_candidates": {"poses.pba.rolling_shutter": True},
}
"""Settings (dotted path: value) under which a field acts, given to both of its runs."""

VALUES = {
    # The capture is 640 wide: a wider setting reads it at its own size.
    "keyframes.track_width": 320,
    "poses.sfm_width": 480,
    "poses.match_overlap": 3,
    "poses.pba.max_width": 480,
    # A check: a value that refuses the capture.
    "keyframes.min_frames": 1000,
    "keyframes.min_keyframes": 100,
    "keyframes.min_shared_tracks": 5000,
    "poses.min_registered": 100,
    # Thresholds this capture's views and points are well inside of: stricter ones.
    "keyframes.angle_slack": 0.9,
    "landmarks.min_detector_score": 0.99,
    "landmarks.gate_max_yaw_deg": 5.0,
    "landmarks.gate_max_reprojection": 0.001,
    "landmarks.max_point_spread": 0.001,
    "landmarks.min_views": 12,
    "landmarks.min_parallax_deg": 30.0,
    "landmarks.ear_max_yaw_deg": 60.0,
    # No keyframe of the sweep lies between 45° and 46°; several lie between 20° and 45°.
    "landmarks.ear_min_yaw_deg": 20.0,
    "landmarks.min_yaw_span_deg": 300.0,  # the sweep spans about 180°
    "landmarks.iris_max_yaw_deg": 3.0,
    "landmarks.min_eye_opening": 0.9,
    "landmarks.ear_outlier_threshold": 0.005,
    "landmarks.ear_huber": 0.001,
    "landmarks.ear_min_views": 12,  # (ears3d.json says the setting: its points should change)
    "coarse.cue_agreement_sigmas": 0.1,
    "mvs.views.max_reference_views": 4,  # the view selection picks 5 of its 21 keyframes
    "mvs.fusion.max_reprojection_px": 0.1,  # 160 px wide depth maps agree within a pixel
    # Stopping rules: values that stop earlier than the base's schedule does.
    "fitting.convergence_mm": 5.0,
    "poses.pba.iterations": 1,
    "poses.pba.search_level": 0,  # the default pyramid has levels 0 and 1
    "poses.pba.readout_candidates": [0.02],
    "evaluation.max_iterations": 2,
    "evaluation.tolerance": 0.01,
    # Clean renders' clouds are less noisy than the default: a value they exceed.
    "fitting.cloud_noise_mm": 0.01,
    "fitting.solver": "scipy",  # "auto" is CHOLMOD where cvxopt is installed
    "fitting.canny_thresholds": [60, 150],  # a step of one leaves the edges where they are
    "fitting.edge_boundary_rings": 20,
    # The schedule's two lists have one length: each changed alone.
    "fitting.stiffness": [15.0, 5.0],
    "fitting.landmark_weight": [15.0, 5.0],
}
"""Fields' other values where the next valid one does nothing on this capture."""

NOT_ON_THIS_CAPTURE = {
    "coarse.ipd_ratio": "the scale from a given IPD uses it where the capture's pupils are not "
                        "measured; this capture's are",
    "coarse.ipd_spread": "as coarse.ipd_ratio",
    "poses.min_registered_fraction": "refuses a capture of which too few keyframes register; "
                                     "all of this capture's do",
    "poses.threads": "more threads move the cameras only through the order in which COLMAP's "
                     "threaded matching finishes (up to 0.2 % of the focal length on a 720p "
                     "sweep); this capture's 20 keyframes give the same cameras from 1 and 2",
}
"""Fields that act only on a capture unlike this one, and why (run each where it acts)."""

VOLATILE = ("seconds", "wall_seconds", "cpu_seconds", "timing", "wall_s", "cloud_s", "solve_s",
            "config")
"""JSON keys left out of the comparison: the times, which differ between two runs of the same
settings, and the settings a stage's report repeats, which differ with every setting."""


def set_path(data: dict, path: str, value) -> None:
    *parents, name = path.split(".")
    for part in parents:
        data = data.setdefault(part, {})
    data[name] = value


def stage_of(path: str) -> Stage | None:
    """The stage whose section holds the field at dotted ``path``."""
    found = [s for s in STAGES if s.section and path.startswith(f"{s.section}.")]
    return max(found, key=lambda s: len(s.section)) if found else None


ALL_FIELDS = [(path, field) for path, field in leaf_fields(PipelineConfig) if stage_of(path)]
SAMPLE = 8
"""Fields a run of the suite checks, drawn anew each run (all of them take 12-15 minutes of
the 2-core machine): ``FACECAP_SETTINGS_FIELDS=all`` checks every one, a comma-separated list of
dotted paths those (what a failure prints), ``FACECAP_SETTINGS_SEED`` fixes the draw."""


def drawn_fields() -> list:
    """The fields this run checks (:data:`SAMPLE`), never those of
    :data:`NOT_ON_THIS_CAPTURE`."""
    fields = [(p, f) for p, f in ALL_FIELDS if p not in NOT_ON_THIS_CAPTURE]
    chosen = os.environ.get("FACECAP_SETTINGS_FIELDS", "")
    if chosen == "all":
        return fields
    if chosen:
        return [(p, f) for p, f in fields if p in chosen.split(",")]
    seed = int(os.environ.get("FACECAP_SETTINGS_SEED") or random.SystemRandom().randrange(2**32))
    print(f"settings checked this run: FACECAP_SETTINGS_SEED={seed}")
    return random.Random(seed).sample(fields, SAMPLE)


FIELDS = drawn_fields()


def without_volatile(value):
    if isinstance(value, dict):
        return {k: without_volatile(v) for k, v in value.items() if k not in VOLATILE}
    if isinstance(value, list):
        return [without_volatile(v) for v in value]
    return value


def digest(folder: Path) -> dict[str, str]:
    """{file: digest} of what a stage wrote, times left out of its JSON files."""
    found = {}
    for path in sorted(p for p in folder.rglob("*") if p.is_file()):
        data = path.read_bytes()
        if path.suffix == ".json":
            data = json.dumps(without_volatile(json.loads(data)), sort_keys=True).encode()
        found[str(path.relative_to(folder))] = hashlib.sha256(data).hexdigest()
    return found


class Chain:
    """The stages' artifact folders on one capture at :data:`BASE`, each computed when a
    stage first needs it."""

    def __init__(self, root: Path, capture):
        self.root, self.capture = root, capture
        self.config = PipelineConfig.model_validate(BASE)
        self.folders: dict[str, Path] = {}
        for name, source in (("video", capture.video), ("scan", capture.gt_mesh),
                             ("scan_landmarks", capture.gt_landmarks)):
            folder = root / name
            folder.mkdir()
            shutil.copy(source, folder / ("video.mp4" if name == "video" else Path(source).name))
            self.folders[name] = folder
        self.runs: dict[tuple, dict[str, str]] = {}

    def inputs(self, stage: Stage) -> dict[str, Path]:
        return {name: self.folder(stage.source(name)) for name in stage.inputs + stage.optional}

    def folder(self, name: str) -> Path:
        if name not in self.folders:
            stage = next(s for s in STAGES if s.name == name)
            inputs = self.inputs(stage)
            folder = self.root / name
            shutil.rmtree(folder, ignore_errors=True)  # what a failed run left
            folder.mkdir()
            for params in self.params(stage, inputs, every=True):
                stage.run(inputs, folder, stage.settings(self.config), params)
            self.folders[name] = folder
        return self.folders[name]

    @staticmethod
    def params(stage: Stage, inputs, every: bool = False) -> list[dict]:
        """A per-keyframe stage's runs: all keyframes for the chain, the middle one for a
        field's run."""
        if stage.per_keyframe is None:
            return [{}]
        indices = stage.per_keyframe(inputs)
        return [{"index": i} for i in indices] if every else [
            {"index": indices[len(indices) // 2]}]

    def outputs(self, stage: Stage, config: PipelineConfig, again: bool = False
                ) -> dict[str, str]:
        """Digests of the files ``stage`` writes at ``config`` on the chain's inputs (run
        once per settings, unless ``again``)."""
        section = stage.settings(config)
        run_key = (stage.name, section.model_dump_json())
        if run_key not in self.runs or again:
            inputs = self.inputs(stage)
            out = self.root / f"run-{len(self.runs)}"
            out.mkdir()
            try:
                for params in self.params(stage, inputs):
                    stage.run(inputs, out, section, params)
                self.runs[run_key] = digest(out)
            except FacecapError as exc:  # a check that refuses the input: what it says
                self.runs[run_key] = {"refused": str(exc)}
            finally:
                shutil.rmtree(out)
        return self.runs[run_key]


@pytest.fixture(scope="module")
def chain(tmp_path_factory, ict4_sweep) -> Chain:
    return Chain(tmp_path_factory.mktemp("settings-used"), ict4_sweep)


def configs(path: str, field) -> tuple[PipelineConfig, PipelineConfig, object]:
    """The settings of the field's two runs: :data:`BASE` with its context, and that with the
    field at another valid value; and that value."""
    data = copy.deepcopy(BASE)
    for where, value in CONTEXT.get(path, {}).items():
        set_path(data, where, value)
    before = PipelineConfig.model_validate(data)
    *parents, name = path.split(".")
    model: type[BaseModel] = section_model(".".join(parents)) if parents else PipelineConfig
    current = before
    for part in parents:
        current = getattr(current, part)
    model_field = copy.copy(model.model_fields[name])  # its default: the base's value
    model_field.default, model_field.default_factory = getattr(current, name), None
    value = VALUES[path] if path in VALUES else other_value(model, name, model_field)
    set_path(data, path, value)
    return before, PipelineConfig.model_validate(data), value


SET = [stage for stage in STAGES if stage.section
       and any(stage_of(path) is stage for path, _ in FIELDS)]
"""The stages of the fields this run checks."""


def test_the_fields_left_out_are_fields():
    """:data:`NOT_ON_THIS_CAPTURE` names settings that exist (a renamed one would hide)."""
    assert set(NOT_ON_THIS_CAPTURE) <= {path for path, _ in ALL_FIELDS}


@pytest.mark.parametrize("stage", SET, ids=[stage.name for stage in SET])
def test_a_stage_writes_the_same_files_twice(chain, stage):
    """Each stage, run twice at the same settings, writes the same files (times aside): else
    a file that changed with a setting would not show that the stage read it."""
    first = chain.outputs(stage, chain.config)
    assert "refused" not in first, first
    assert chain.outputs(stage, chain.config, again=True) == first


@pytest.mark.parametrize("path, field", FIELDS, ids=[path for path, _ in FIELDS])
def test_a_changed_setting_changes_what_its_stage_writes(chain, path, field):
    stage = stage_of(path)
    before, after, value = configs(path, field)
    name = path[len(stage.section) + 1:]
    inputs = {n: "k" * 64 for n in stage.inputs}
    same_key = (stage_key(stage, inputs, stage.settings(before))
                == stage_key(stage, inputs, stage.settings(after)))
    if name in stage.key_neutral:
        assert stage.key_neutral[name].strip(), f"{path}: key-neutral without its reason"
        assert same_key, f"{path} is key-neutral, yet changes the {stage.name} key"
        assert chain.outputs(stage, before) == chain.outputs(stage, after), (
            f"{path} is key-neutral, yet at {value!r} changes what the {stage.name} stage writes")
        return
    assert not same_key, path
    assert "refused" not in chain.outputs(stage, before), chain.outputs(stage, before)
    assert chain.outputs(stage, before) != chain.outputs(stage, after), (
        f"{path} at {value!r} changes nothing the {stage.name} stage writes: remove it if "
        f"nothing reads it, else list it in the row's key_neutral with the reason")
