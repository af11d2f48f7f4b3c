"""facecap's settings (``facecap_core/settings.py``): every ``FACECAP_*`` variable, read in one
place, documented in ``docs/deploy.md``, and one rule for empty values and ``~``."""

from __future__ import annotations

import re
import shutil
import uuid
from pathlib import Path

import pytest

from facecap_core.errors import InputError
from facecap_core.settings import FacecapSettings, env_name, settings

ROOT = Path(__file__).resolve().parents[1]
SETTINGS_HEADING = "### facecap's settings"
VARIABLES = {env_name(field) for field in FacecapSettings.model_fields}


@pytest.fixture(autouse=True)
def clean_environment(monkeypatch):
    """No FACECAP_* variable of the machine running the tests leaks in."""
    for variable in VARIABLES:
        monkeypatch.delenv(variable, raising=False)


# --------------------------------------------------------------------------- documentation


def table_rows(markdown: str, heading: str) -> list[list[str]]:
    """The cells of the first table after ``heading`` (header and rule left out)."""
    after = markdown.split(heading + "\n", 1)[1]
    lines = re.split(r"\n#+ ", after, maxsplit=1)[0].splitlines()
    table = [line for line in lines if line.startswith("|")]
    return [[cell.strip() for cell in row.strip("|").split("|")] for row in table[2:]]


def named_variables(cell: str) -> set[str]:
    return set(re.findall(r"`(FACECAP_[A-Z0-9_]+)`", cell))


def test_the_deploy_docs_list_exactly_the_settings():
    docs = (ROOT / "docs" / "deploy.md").read_text()
    rows = table_rows(docs, SETTINGS_HEADING)
    documented = [cell for row in rows for cell in named_variables(row[0])]
    assert sorted(documented) == sorted(VARIABLES)  # each once, none missing, none extra
    for row in rows:  # a number given as the default is the code's default
        field = FacecapSettings.model_fields[row[0].strip("`")[len("FACECAP_"):].lower()]
        if isinstance(field.default, int | float):
            assert row[1] == f"`{field.default:g}`", row


def test_the_stack_variables_table_holds_no_setting():
    docs = (ROOT / "docs" / "deploy.md").read_text()
    rows = table_rows(docs, "## Environment variables")
    stack = set().union(*(named_variables(row[0]) for row in rows))
    assert stack and not stack & VARIABLES  # each variable is documented in one place


def test_every_variable_the_code_names_is_a_setting():
    """A FACECAP_* variable named in the code is a setting, so it is validated and
    documented (``FACECAP_MAX_...`` abbreviates the limits)."""
    named = set()
    for package in ("facecap_core", "facecap", "tasks", "pages", "flows", "deploy"):
        for source in (ROOT / package).rglob("*.py"):
            named |= set(re.findall(r"FACECAP_[A-Z0-9_]*[A-Z0-9]", source.read_text()))
    unknown = {name for name in named
               if name not in VARIABLES and not any(v.startswith(name + "_") for v in VARIABLES)}
    assert not unknown


# --------------------------------------------------------------------------- FACECAP_HOME


@pytest.fixture(scope="module")
def template_assets() -> Path:
    """The template assets of the machine's cache, copied into each test's home."""
    from facecap_core import assets

    return assets.menpo3d_data()


@pytest.mark.parametrize("value", ["~/.cache/facecap", "", None],
                         ids=["tilde", "empty", "unset"])
def test_facecap_home_resolves_one_way_everywhere(value, tmp_path, monkeypatch,
                                                  template_assets):
    """``~`` expanded, an empty value and no value all mean ``~/.cache/facecap``, for the
    default store, the assets, the locks of a remote store and the copies of its artifacts."""
    from facecap.tasks.runner import default_store_url, key_lock
    from facecap.tasks.store import open_store
    from facecap.tasks.store.remote import cache_root
    from facecap_core import assets

    monkeypatch.setenv("HOME", str(tmp_path))
    if value is not None:
        monkeypatch.setenv("FACECAP_HOME", value)
    home = tmp_path / ".cache" / "facecap"
    shutil.copytree(template_assets, home / "assets" / template_assets.name)

    def no_download(dest):  # assets looked for in another folder would be downloaded
        raise AssertionError("the assets were looked for outside FACECAP_HOME")

    monkeypatch.setattr(assets, "_download_sdist", no_download)

    assert settings().home == home
    assert default_store_url() == str(home / "store")
    assert assets.default_template_files()[0] == home / "assets" / "menpo3d-0.8.6" / "template.ply"
    assert cache_root() == home / "store-cache"
    with key_lock(open_store(f"memory://facecap-test-{uuid.uuid4().hex}"), "input-" + "0" * 32):
        assert (home / "locks" / ("input-" + "0" * 32 + ".lock")).is_file()


def test_facecap_home_expands_tilde_and_is_read_again_when_it_changes(tmp_path, monkeypatch):
    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.setenv("FACECAP_HOME", "~/first")
    assert settings().home == tmp_path / "first"
    monkeypatch.setenv("FACECAP_HOME", "~/second")
    assert settings().home == tmp_path / "second"


def test_an_empty_value_is_the_default_for_every_setting(monkeypatch):
    for variable in VARIABLES:
        monkeypatch.setenv(variable, "")
    assert settings() == FacecapSettings.model_construct()  # the defaults, unvalidated
    assert settings().max_frames == 36_000 and settings().store is None


# --------------------------------------------------------------------------- parsing


def test_input_roots_parse_as_a_list_of_paths(tmp_path, monkeypatch):
    from facecap.flows.service import ServicePolicy

    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.setenv("FACECAP_INPUT_ROOTS", f"~/videos::{tmp_path / 'scans'}:")
    assert settings().input_roots == (tmp_path / "videos", tmp_path / "scans")
    assert ServicePolicy.from_env().input_roots == (tmp_path.resolve() / "videos",
                                                    tmp_path.resolve() / "scans")


def test_the_timeouts_have_their_defaults_and_read_the_environment(monkeypatch):
    assert (settings().capture_timeout_s, settings().stage_timeout_s) == (21600, 7200)
    monkeypatch.setenv("FACECAP_CAPTURE_TIMEOUT_S", "90.5")
    monkeypatch.setenv("FACECAP_STAGE_TIMEOUT_S", "30")
    assert (settings().capture_timeout_s, settings().stage_timeout_s) == (90.5, 30)


@pytest.mark.parametrize("variable", ["FACECAP_CAPTURE_TIMEOUT_S", "FACECAP_STAGE_TIMEOUT_S",
                                      "FACECAP_EVALUATION_TIMEOUT_S"])
def test_a_time_limit_is_one_the_clocks_can_keep(variable, monkeypatch, capfd):
    """1e308 s is a finite number no timer can wait for: refused at the edge, naming its
    variable, as one line of the command that reads it."""
    from facecap.cli import main

    monkeypatch.setenv(variable, "1e308")
    with pytest.raises(InputError, match=f"invalid {variable}='1e308'.*less than or equal "
                                         "to 2592000"):
        settings()
    assert main(["store", "prune", "--older-than-days", "1", "--dry-run"]) == 2
    err = capfd.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"facecap: error: invalid {variable}")


INVALID = {
    "FACECAP_MAX_FRAMES": ("many", "valid integer"),
    "FACECAP_MAX_FILE_MB": ("-1", "greater than 0"),
    "FACECAP_MAX_SIDE_PX": ("50", "greater than or equal to 120"),
    "FACECAP_CAPTURE_TIMEOUT_S": ("0", "greater than 0"),
    "FACECAP_STAGE_TIMEOUT_S": ("inf", "finite number"),
    "FACECAP_FAULT": ("views:first", "STAGE[:N[:HOW]]"),
}


@pytest.mark.parametrize("variable", sorted(INVALID))
def test_an_invalid_value_names_its_variable(variable, monkeypatch):
    value, reason = INVALID[variable]
    monkeypatch.setenv(variable, value)
    with pytest.raises(InputError) as error:
        settings()
    message = str(error.value)
    assert "\n" not in message
    assert f"invalid {variable}={value!r}" in message and reason in message
    assert "correct it or unset it" in message


@pytest.mark.parametrize("home", ["/dev/null", "file", "file/sub", "read-only", "read-only/sub"])
def test_a_facecap_home_facecap_cannot_write_in_is_refused(home, tmp_path, monkeypatch):
    """Every command writes below FACECAP_HOME (assets, store, locks, crash logs): a file, a
    device or a folder it may not write in is named where the variable is read, not found
    by the first folder made under it. A folder still to be made is fine."""
    import os

    (tmp_path / "file").write_text("a file")
    (tmp_path / "read-only").mkdir()
    value = home if home.startswith("/") else str(tmp_path / home)
    real_access = os.access
    monkeypatch.setattr(os, "access", lambda path, mode, **kw: (  # tests run as root
        "read-only" not in str(path) and real_access(path, mode, **kw)))
    monkeypatch.setenv("FACECAP_HOME", value)
    with pytest.raises(InputError) as refused:
        settings()
    message = str(refused.value)
    assert message.startswith(f"invalid FACECAP_HOME={value!r} in the environment: "), message
    assert message.endswith("; set FACECAP_HOME to a writable folder, or unset it for the "
                            "default (~/.cache/facecap)"), message
    assert "\n" not in message
    monkeypatch.setenv("FACECAP_HOME", str(tmp_path / "new" / "home"))
    assert settings().home == tmp_path / "new" / "home"


# --------------------------------------------------------------------------- config files


def test_a_config_file_reads_yaml_as_pyyaml_does_but_base_60():
    """The config loader resolves every scalar as PyYAML's safe loader does, except YAML
    1.1's base-60 numbers: ``1:30`` stays a string (PyYAML reads 90), for a number field to
    refuse."""
    import yaml

    from facecap_core.config import parse_yaml

    same = ["1", "-1", "+7", "0", "017", "0b101", "0x1F", "1_000", "1.5", "1.", "-.5", ".5",
            "1.0e+5", "1.0e-05", ".inf", "-.Inf", ".nan", "2001-12-14", "true", "no", "on",
            "null", "~", "abc", "1.2.3", "6.0"]
    for scalar in same:
        assert repr(parse_yaml(f"v: {scalar}")) == repr(yaml.safe_load(f"v: {scalar}")), scalar
    for scalar in ["1:30", "-1:30", "1:30.5", "190:20:30"]:
        assert parse_yaml(f"v: {scalar}") == {"v": scalar}
    assert parse_yaml("") is None


def test_a_key_given_twice_is_named_by_its_path():
    """A key given twice in one mapping (PyYAML keeps the last silently) is refused with its
    dotted path and line; a merge key's keys may be overridden, and a document that refers
    to itself is checked once."""
    from facecap_core.config import DuplicateKeyError, parse_yaml

    with pytest.raises(DuplicateKeyError) as twice:
        parse_yaml("fitting:\n  levels:\n    - {stiffness: 1, 'stiffness': 2}\n")
    assert (twice.value.key, twice.value.line) == ("fitting.levels.0.stiffness", 3)
    assert parse_yaml("a: &base {x: 1}\nb: {<<: *base, x: 2}\n")["b"] == {"x": 2}
    assert parse_yaml("1: one\n'1': another\n") == {1: "one", "1": "another"}
    loop = parse_yaml("a: &loop [*loop]\n")["a"]
    assert loop[0] is loop


def _fields():
    """Every field of every settings model: the pipeline's (each stage declares its own),
    the synthetic capture's and the ear training's."""
    import facecap.ear_training.config  # noqa: F401
    import facecap.synthetic.config  # noqa: F401
    import facecap_core.pipeline  # noqa: F401 - imports every stage's settings model
    from facecap_core.config import StrictModel

    models, todo = [], list(StrictModel.__subclasses__())
    while todo:
        models.append(todo.pop())
        todo += models[-1].__subclasses__()
    assert len(models) >= 13
    return [(model, name, field) for model in sorted(models, key=lambda m: m.__name__)
            for name, field in model.model_fields.items()]


@pytest.mark.parametrize("model, name, field", _fields(),
                         ids=[f"{m.__name__}.{n}" for m, n, _ in _fields()])
def test_true_is_a_value_of_bool_settings_only(model, name, field):
    """A boolean given for a number (``iterations: true``, ``[1.0, on]``) is refused, though
    pydantic's lax mode reads it as 1; bool settings take it."""
    from facecap_core.config import build

    if field.annotation is bool:
        assert getattr(build(model, {name: True}), name) is True
        return
    values, default = [True], field.get_default(call_default_factory=True)
    if isinstance(default, list | tuple) and default:
        values.append([True, *default[1:]])
    for value in values:
        with pytest.raises(InputError, match=rf"{name}: "):
            build(model, {name: value})


def test_numbers_of_flow_parameters_and_json_are_taken_as_before():
    """What a served run's parameters and the UI give: ints for float fields, and the
    lists and strings that pydantic turns into tuples and paths."""
    import json

    from facecap.synthetic.config import SynthConfig
    from facecap_core.pipeline import PipelineConfig, load_pipeline_config

    values = {"mvs": {"depth": {"iterations": 3}}, "coarse": {"ipd_mm": 63, "iris_cue": False},
              "fitting": {"stiffness": [50, 10, 2], "landmark_weight": [5, 1, 1]}}
    for config in (load_pipeline_config(values),
                   PipelineConfig.model_validate_json(json.dumps(values))):
        assert config.coarse.ipd_mm == 63.0 and config.fitting.stiffness == [50.0, 10.0, 2.0]
        assert config.mvs.depth.iterations == 3 and config.coarse.iris_cue is False
    synth = SynthConfig.model_validate_json(json.dumps(
        {"fps": 30, "k1_range": [-1, 0], "ict_model": "/models/ict.npz", "bayer": True}))
    assert synth.k1_range == (-1.0, 0.0) and synth.ict_model == Path("/models/ict.npz")
