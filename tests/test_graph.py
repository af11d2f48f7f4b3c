"""The stage graph: every setting invalidates exactly the artifacts that depend on it.

A change of one config field, any field of any section, must give new keys to the stages
that read its section and to every stage after them, and the same keys to all others (a
field a stage reads but its key ignores would serve a stale artifact; a key that hashes
another stage's settings would recompute for nothing). The expected sets are written out
here from the pipeline's data flow, not derived from the table under test.
"""

from __future__ import annotations

import ast
import dataclasses
import typing
from pathlib import Path

import pytest
from pydantic import BaseModel, Field, ValidationError

from facecap.flows.capture import _inputs
from facecap.tasks.graph import (
    BY_NAME,
    STAGES,
    STEPS,
    config_data,
    producer,
    stage_key,
    stages_until,
)
from facecap.tasks.store import artifact_key
from facecap_core.config import KEY_NEUTRAL, StrictModel
from facecap_core.pipeline import PipelineConfig, section_model
from facecap_core.pose.cameras_json import CameraIntrinsics, Cameras, keyframe_poses
from facecap_core.pose.stage import PoseConfig

AFTER_COARSE = {"views", "depth", "fusion", "fitting", "evaluation"}
RECOMPUTED = {
    "keyframes": {"keyframes", "poses", "frames", "landmarks", "coarse", *AFTER_COARSE},
    "poses": {"poses", "frames", "landmarks", "coarse", *AFTER_COARSE},
    "landmarks": {"landmarks", "coarse", *AFTER_COARSE},
    "coarse": {"coarse", *AFTER_COARSE},
    "mvs.views": AFTER_COARSE,
    "mvs.depth": {"depth", "fusion", "fitting", "evaluation"},
    "mvs.fusion": {"fusion", "fitting", "evaluation"},
    "fitting": {"fitting", "evaluation"},
    "evaluation": {"evaluation"},
}
"""Stages with new keys when a field of a section changes."""
KNOWN = set().union(*RECOMPUTED.values())
KEYFRAMES = [0, 7, 12]
RAW = {"video": "input-" + "1" * 32, "scan": "input-" + "2" * 32,
       "scan_landmarks": "input-" + "3" * 32}


def plan(cfg: PipelineConfig) -> dict[str, str]:
    """{report row: artifact key} of a whole run, as the capture flow assembles them (the
    depth maps of three fixed keyframes)."""
    keys, rows = dict(RAW), {}
    for stage in STAGES:
        inputs = _inputs(stage, keys)
        assert inputs is not None, stage.name
        config = stage.settings(cfg)
        if stage.per_keyframe:
            for i in KEYFRAMES:
                row = stage.row_name({"index": i})
                rows[row] = keys[row] = stage_key(stage, inputs, config, {"index": i})
        else:
            rows[stage.name] = keys[stage.name] = stage_key(stage, inputs, config)
    return rows


def leaf_fields(model: type[BaseModel], prefix: str = ""):
    for name, field in model.model_fields.items():
        if isinstance(field.annotation, type) and issubclass(field.annotation, BaseModel):
            yield from leaf_fields(field.annotation, f"{prefix}{name}.")
        else:
            yield f"{prefix}{name}", field


def other_value(model: type[BaseModel], name: str, field):
    """A valid value of the field other than its default."""
    default = field.get_default(call_default_factory=True)
    choices = typing.get_args(field.annotation)
    if isinstance(default, bool):
        candidates = [not default]
    elif isinstance(default, int | float):
        # Larger steps last: a field may have a floor above its default's neighbours
        # (mvs.depth.pixel_views: 0 or at least num_best_views).
        candidates = [default + 1, default * 1.1, default - 1, default * 0.9, default / 2,
                      *(default + 2 ** k for k in range(1, 7))]
    elif isinstance(default, list | tuple):
        candidates = [[v * 0.9 if isinstance(v, float) else v - 1 for v in default]]
    elif default is None:
        candidates = [1.0, 1, True, 63.0, 0.01]  # 63 mm: an interpupillary distance; 10 ms
    else:
        candidates = [c for c in choices if c != default] + ["full", "nicp"]
    for candidate in candidates:
        try:
            value = getattr(model.model_validate({name: candidate}), name)
        except ValidationError:
            continue
        if value != default:
            return candidate
    raise AssertionError(f"no other valid value found for {name} (default {default!r})")


def section_of(path: str) -> str | None:
    sections = [s.section for s in STAGES if s.section and path.startswith(f"{s.section}.")]
    return max(sections, key=len) if sections else None


FIELDS = list(leaf_fields(PipelineConfig))


def with_field(path: str, value) -> PipelineConfig:
    """The default pipeline settings with the field at the dotted ``path`` set to ``value``."""
    *parents, name = path.split(".")
    data = PipelineConfig().model_dump(mode="json")
    node = data
    for part in parents:
        node = node[part]
    node[name] = value
    return PipelineConfig.model_validate(data)


CODE = ("facecap_core", "flows", "tasks")
"""Where a setting is read: the stages and the orchestration."""


def names_read(files) -> set[str]:
    """The names the code in ``files`` reads: attributes (``config.name``), ``getattr(x,
    "name")``, ``data["name"]`` and ``data.get("name")``; not what a docstring or a comment
    says."""
    found = set()
    for path in files:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Load):
                found.add(node.attr)
            elif isinstance(node, ast.Subscript) and isinstance(node.slice, ast.Constant):
                found.add(node.slice.value)
            elif isinstance(node, ast.Call) and _is_getattr(node):
                found.add(_constant(node.args[1]))
            elif isinstance(node, ast.Call) and node.args and \
                    getattr(node.func, "attr", None) == "get":
                found.add(_constant(node.args[0]))
    return {name for name in found if isinstance(name, str)}


def _constant(node: ast.AST):
    return node.value if isinstance(node, ast.Constant) else None


def _is_getattr(call: ast.Call) -> bool:
    return getattr(call.func, "id", None) in ("getattr", "hasattr") and len(call.args) >= 2


def test_every_config_field_is_read_by_one_stage_or_changes_no_result():
    """Every setting sits in the section of one stage, whose key hashes it, and code reads
    it by name (``config.name``, ``getattr(config, "name")``, ``data["name"]``) somewhere
    other than its declaration: a field no code names is read nowhere, yet changing it would
    recompute its stage and every one after it. ``mvs.workers`` (how many depth maps run at
    once) is in no stage's section: the capture flow reads it and it changes no result."""
    root = Path(__file__).resolve().parents[1]
    read = names_read(p for folder in CODE for p in (root / folder).rglob("*.py"))
    outside = [path for path, _ in FIELDS if section_of(path) is None]
    assert outside == ["mvs.workers"]
    unread = [path for path, _ in FIELDS if path.rsplit(".", 1)[-1] not in read]
    assert unread == [], f"settings no code reads: {unread}"


def test_a_removed_setting_is_refused_by_name():
    """keyframes.sharpness_window was read nowhere and is gone: a config that still names
    it is refused in one line naming it, as every unknown key."""
    from facecap_core.errors import InputError
    from facecap_core.pipeline import load_pipeline_config

    with pytest.raises(InputError, match=r"keyframes\.sharpness_window: Extra inputs are not "
                                         r"permitted; correct or remove these settings"):
        load_pipeline_config({"keyframes": {"sharpness_window": 6}})


@pytest.mark.parametrize("path, field", FIELDS, ids=[path for path, _ in FIELDS])
def test_a_changed_field_recomputes_exactly_what_depends_on_it(path, field):
    section = section_of(path)
    # A setting its stage's row lists as key-neutral changes no file: it recomputes nothing.
    neutral = section is not None and any(
        stage.section == section and path[len(section) + 1:] in stage.key_neutral
        for stage in STAGES)
    *parents, name = path.split(".")
    model = section_model(".".join(parents)) if parents else PipelineConfig
    value = other_value(model, name, field)
    changed_cfg = with_field(path, value)
    before, after = plan(PipelineConfig()), plan(changed_cfg)
    changed = {row.split("_")[0] if row.startswith("depth_") else row
               for row in before if before[row] != after[row]}
    assert changed & KNOWN == (set() if neutral else RECOMPUTED.get(section, set())), (path, value)
    # Every stage, one added since too: new keys exactly when what its row says it reads
    # changed (its section, or an input's artifact).
    for stage in STAGES:
        reads_changed = (section is not None and stage.section == section and not neutral) or any(
            stage.source(name) in changed for name in stage.inputs + stage.optional)
        assert (stage.name in changed) == reads_changed, (stage.name, path)


class _Before(StrictModel):
    depth: float = 1.0


class _Added(_Before):
    """_Before with a setting added since, which at False does what the stage did before."""

    hold: bool = Field(False, json_schema_extra={KEY_NEUTRAL: False})


class _DefaultChanged(_Before):
    hold: bool = Field(True, json_schema_extra={KEY_NEUTRAL: False})


class _Section(StrictModel):
    inner: _Added = _Added()


def test_a_setting_added_at_its_neutral_value_keeps_the_keys():
    inputs = {"keyframes": "k" * 64}
    key = stage_key("poses", inputs, _Before())
    assert stage_key("poses", inputs, _Added()) == key
    assert stage_key("poses", inputs, _Added(hold=True)) != key
    assert stage_key("poses", inputs, _Added(depth=2.0)) != key
    # A default moved off the neutral value is a change: the stores compute again.
    assert stage_key("poses", inputs, _DefaultChanged()) != key
    assert config_data(_Section()) == {"inner": {"depth": 1.0}}
    assert config_data(_Section(inner=_Added(hold=True))) == {"inner": {"depth": 1.0,
                                                                        "hold": True}}
    # The pose settings' principal-point hold came after the pose stage had results: off,
    # the pose key is the one of the same settings without the field.
    before = PoseConfig().model_dump(mode="json")
    del before["pba"]["hold_principal_point"]
    assert stage_key("poses", inputs, PoseConfig()) == artifact_key(
        "poses", inputs, before, BY_NAME["poses"].full_version())
    held = PoseConfig(pba={"hold_principal_point": True})
    assert config_data(held)["pba"]["hold_principal_point"] is True


@pytest.mark.parametrize("path, field", [(p, f) for p, f in FIELDS if KEY_NEUTRAL in
                                         (f.json_schema_extra or {})])
def test_every_key_neutral_setting_is_left_out_at_its_value(path, field):
    """Every marked setting of the pipeline's settings is left out at its value (a marker
    on a setting of a nested list of models would not be found here nor by config_data:
    there are none)."""
    *parents, name = path.split(".")
    keyed = config_data(with_field(path, field.json_schema_extra[KEY_NEUTRAL]))
    for part in parents:
        keyed = keyed[part]
    assert name not in keyed


def test_a_key_neutral_setting_keeps_the_key_at_any_value():
    """A setting a row lists as key-neutral is hashed at its default: the key is the one
    without the mark, whatever its value; the stored record says what the key hashed."""
    stage = dataclasses.replace(BY_NAME["poses"], key_neutral={
        "threads": "threads of the matching", "pba.iterations": "a nested one"})
    inputs = {"keyframes": "k" * 64}
    key = stage_key(stage, inputs, PoseConfig())
    assert key == stage_key("poses", inputs, PoseConfig())
    assert stage_key(stage, inputs, PoseConfig(threads=3, pba={"iterations": 3})) == key
    assert stage_key(stage, inputs, PoseConfig(min_registered=6)) != key
    assert config_data(PoseConfig(threads=3), stage.key_neutral) == config_data(PoseConfig())


def test_until_runs_a_prefix_of_the_graph():
    # The report's and the UI's names, in this order (a stage added since sits among them).
    named = ("keyframes", "poses", "frames", "landmarks", "coarse", "views", "depth", "fusion",
             "fitting", "evaluation")
    assert [step for step in STEPS if step in named] == list(named)
    assert len(set(STEPS)) == len(STEPS)
    assert [s.name for s in stages_until("landmarks")] == ["keyframes", "poses", "frames",
                                                           "landmarks"]
    assert [s.name for s in stages_until("views")][-2:] == ["coarse", "views"]
    assert stages_until("mvs") == stages_until("fusion")  # the earlier name still works
    assert [s.name for s in stages_until("evaluation")] == [s.name for s in STAGES]
    with pytest.raises(ValueError, match="unknown step"):
        stages_until("everything")


def test_a_stage_without_its_input_is_skipped_and_fan_out_items_are_gathered():
    keys = {"fitting": "fitting-" + "0" * 32}
    assert _inputs(BY_NAME["evaluation"], keys) is None  # no scan given
    keys.update({"frames": "f", "coarse": "c", "depth_00003": "d3", "depth_00009": "d9"})
    assert _inputs(BY_NAME["fusion"], keys) == {"frames": "f", "coarse": "c",
                                                "depth_00003": "d3", "depth_00009": "d9"}


def test_what_the_flows_and_tasks_know_of_a_stage_is_in_its_row(tmp_path):
    """Every input is a raw input or an earlier stage (by its row's ``sources`` where named
    otherwise), every stage states its share of the work for the progress bar, and the
    coarse stage's log line gives its metric scale through its row."""
    import json

    from facecap.tasks.stages import _headline
    from facecap.tasks.store import open_store

    seen = set()
    for stage in STAGES:
        for name in stage.inputs + stage.optional:
            assert stage.source(name) in seen | set(RAW), (stage.name, name)
        assert stage.work_seconds > 0, stage.name
        seen.add(stage.name)
    assert BY_NAME["evaluation"].source("mesh") == producer("mesh") == "fitting"
    shares = {s.name: s.work_seconds / sum(t.work_seconds for t in STAGES) for s in STAGES}
    assert shares["poses"] + shares["depth"] > 0.6  # the poses and the depth maps: most of it
    store = open_store(str(tmp_path / "store"))
    key = artifact_key("coarse", {}, {}, "1")
    scale = {"metric_scale": 90.9, "sigma_pct": 4.0, "used": ["landmarks", "iris"],
             "dropped": []}
    identity = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    cameras = Cameras(units="mm", metric_scale=90.9, intrinsics=CameraIntrinsics(
        width=640, height=360, fx=500.0, fy=500.0, cx=320.0, cy=180.0),
                      keyframes=keyframe_poses([0], [identity], [[0.0, 0.0, 1.0]]))
    store.put(key, {"cameras.json": cameras.to_json().encode(),
                    "coarse.json": json.dumps({"scale": scale}).encode()},
              stage="coarse", inputs={}, config={}, version="1")
    assert _headline(BY_NAME["coarse"], str(tmp_path / "store"), key) == (
        ": metric scale 90.9 mm per camera unit, ±4.0 % (1σ) from landmarks + iris")
    assert _headline(BY_NAME["fusion"], str(tmp_path / "store"), key) == ""


def _tool(name: str):
    """``tools/NAME.py`` as a module."""
    import importlib.util

    path = Path(__file__).resolve().parents[1] / "tools" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_service_page_s_artifact_table_is_the_rows():
    """docs/service.md's stage table is what tools/stage_table.py makes of the rows (run it
    with --write after changing a row); a stage added since shows there by itself."""
    from dataclasses import replace

    tool = _tool("stage_table")
    assert tool.page_table(tool.PAGE.read_text()) == tool.table(), (
        "docs/service.md's stage table is out of date: python tools/stage_table.py --write")
    checksum = replace(BY_NAME["views"], name="checksum", inputs=("mesh",), section=None,
                       sources={"mesh": "fitting"},
                       outputs=("checksum.txt",))
    made = tool.table((*STAGES, checksum))
    assert made.splitlines()[-1] == "| checksum | mesh (fitting) | – | `checksum.txt` |"


def _code_metrics():
    """``tools/code_metrics.py``, which draws the import graph and its layers."""
    return _tool("code_metrics")


def test_dependencies_point_one_way():
    """cli → deploy → flows → tasks → facecap_core's stages in pipeline order → its shared
    helpers; the synthetic world and the ear training beside the orchestration, which never
    imports them; the science never imports Prefect; no circle. Imports inside functions
    and under ``if TYPE_CHECKING:`` count too (tests/test_code_metrics.py)."""
    metrics = _code_metrics()
    figures = metrics.analyse()
    assert figures["layers"] == []
    assert figures["circles"] == []
    # The checks see what they are for: an import up the layers, a forbidden one, a circle.
    graph = {"facecap_core.camera": {"facecap_core.mvs.depth"}, "facecap_core.mvs.depth": set(),
             "tasks.graph": {"facecap.synthetic"},
             "facecap.synthetic": {"tasks.graph", "tasks.outputs"}}
    third_party = {"facecap_core.camera": set(), "facecap_core.mvs.depth": {"prefect"},
                   "tasks.graph": {"flows"}, "facecap.synthetic": set()}
    assert metrics.layer_violations(graph, third_party) == [
        "facecap_core.camera -> facecap_core.mvs.depth", "tasks.graph -> facecap.synthetic",
        "tasks.graph -> flows", "facecap_core.mvs.depth -> prefect",
        "facecap.synthetic -> tasks.graph"]
    assert metrics.circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_a_long_function_says_why_at_its_top():
    """No function over 80 lines without its reason (``# Long on purpose: ...``) at its top."""
    long_functions = _code_metrics().analyse()["long_functions"]
    assert long_functions  # the kernels are long, and say why
    assert [name for name, _, said in long_functions if not said] == []


def test_an_import_inside_a_function_says_why():
    """An import inside a function says why it is there (an optional or heavy dependency, a
    setting read at import, a circle): a comment of a few words beside it or above it, not a
    linter's directive; a module's banner (``# Imported where used: ...``) speaks only for the
    third-party modules it names."""
    inner = _code_metrics().analyse()["inner_imports"]
    assert inner  # the command line's, at least
    assert [where for where, said in inner if not said] == []


LONG_FILES: dict[str, str] = {}
"""{file: why it may stay over the limit for now}: each one is being split; once it is no
longer over the limit the test fails until it leaves this list."""


def test_no_file_is_over_the_limit():
    """No file of the packages over 600 lines, but those :data:`LONG_FILES` names, each of
    which still is."""
    metrics = _code_metrics()
    assert metrics.LONG_FILE == 600
    long_files = dict(metrics.analyse()["long_files"])
    assert sorted(set(long_files) - set(LONG_FILES)) == [], "files over 600 lines"
    assert sorted(set(LONG_FILES) - set(long_files)) == [], (
        "no longer over 600 lines: remove them from LONG_FILES")


def test_a_recalibrated_landmark_table_is_a_new_landmark_stage(tmp_path, monkeypatch):
    """The landmark stage's version names its calibrated tables: a store never hands out
    landmarks made with another vertex table or convention offsets."""
    from facecap_core.landmarks import stage

    before = stage.STAGE.full_version()
    for name in ("MESH_TO_68_FILE", "OFFSETS_FILE"):
        table = tmp_path / f"{name}.json"
        table.write_bytes(getattr(stage, name).read_bytes() + b" ")
        with monkeypatch.context() as m:
            m.setattr(stage, name, table)
            assert stage.STAGE.full_version() != before
    assert stage.STAGE.full_version() == before
