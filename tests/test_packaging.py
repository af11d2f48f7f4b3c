"""What ``pip install facecap`` puts into site-packages: one namespace, every module."""

from __future__ import annotations

import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
INSTALLED_AS = {"facecap_core": "facecap_core", "facecap": "facecap", "tasks": "facecap/tasks",
                "flows": "facecap/flows", "deploy": "facecap/deploy"}
"""The repository's folders and where the wheel puts them."""


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> zipfile.ZipFile:
    out = tmp_path_factory.mktemp("wheel")
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps",
                    "--no-build-isolation", "-w", str(out), str(ROOT)],
                   check=True, capture_output=True, cwd=out)
    (path,) = out.glob("facecap-*.whl")
    with zipfile.ZipFile(path) as archive:
        yield archive


def test_the_wheel_adds_facecap_and_facecap_core_only(wheel):
    """No top-level ``tasks``, ``flows`` or ``deploy`` to collide with a user's own (invoke's
    or Celery's ``tasks.py``, a ``deploy`` module)."""
    tops = {name.split("/")[0] for name in wheel.namelist()}
    assert {t for t in tops if not t.endswith(".dist-info")} == {"facecap", "facecap_core"}
    entry_points = next(n for n in wheel.namelist() if n.endswith(".dist-info/entry_points.txt"))
    assert "facecap = facecap.cli:main" in wheel.read(entry_points).decode()


def test_the_wheel_holds_every_module_and_data_file(wheel):
    """The package list in pyproject.toml is written out (the folders are renamed): a new
    module or data folder left out of it would be missing from the install."""
    names = set(wheel.namelist())
    expected = set()
    for folder, installed in INSTALLED_AS.items():
        for path in (ROOT / folder).rglob("*"):
            if path.is_file() and path.suffix in (".py", ".js", ".json", ".npz", ".svm", ".dat"):
                relative = path.relative_to(ROOT / folder).as_posix()
                if folder == "facecap_core" or "__pycache__" not in relative:
                    expected.add(f"{installed}/{relative}")
    expected = {n for n in expected if "__pycache__" not in n and "/prefect.yaml" not in n}
    assert expected - names == set()
    assert "facecap/flows/viewer/three.bundle.min.js" in names
    assert "facecap_core/data/ict_face_model_trimmed.npz" in names


def test_nothing_imports_the_folders_by_their_checkout_names():
    """``import tasks`` works in a checkout only (and would load a second copy of a module
    beside ``facecap.tasks``): the tests, benchmarks and tools use the installed names."""
    import ast

    found = []
    for folder in ("tests", "benchmarks", "tools"):
        for path in (ROOT / folder).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text())):
                names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                         else [node.module or ""] if isinstance(node, ast.ImportFrom)
                         and not node.level else [])
                found += [f"{path.relative_to(ROOT)}:{node.lineno} {n}" for n in names
                          if n.split(".")[0] in ("tasks", "flows", "deploy")]
    assert found == []
