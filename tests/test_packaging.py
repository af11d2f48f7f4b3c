"""What ``pip install facecap`` puts into site-packages: one namespace, every module."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
INSTALLED_AS = {"facecap_core": "facecap_core", "facecap": "facecap", "tasks": "facecap/tasks",
                "pages": "facecap/pages", "flows": "facecap/flows", "deploy": "facecap/deploy"}
"""The repository's folders and where the wheel puts them."""


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> zipfile.ZipFile:
    """The wheel of the package's files, built from a copy (setuptools builds in the source
    folder, which must stay as it was)."""
    source, out = tmp_path_factory.mktemp("source"), tmp_path_factory.mktemp("wheel")
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, source / name)
    for folder in INSTALLED_AS:
        shutil.copytree(ROOT / folder, source / folder,
                        ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps",
                    "--no-build-isolation", "-w", str(out), str(source)],
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
            if path.is_file() and path.suffix in (".py", ".js", ".json", ".npz", ".svm", ".dat",
                                                  ".j2"):
                relative = path.relative_to(ROOT / folder).as_posix()
                if folder == "facecap_core" or "__pycache__" not in relative:
                    expected.add(f"{installed}/{relative}")
    expected = {n for n in expected if "__pycache__" not in n and "/prefect.yaml" not in n}
    assert expected - names == set()
    assert "facecap/pages/viewer/three.bundle.min.js" in names
    assert "facecap/pages/templates/capture.html.j2" in names
    assert "facecap_core/data/ict_face_model_trimmed.npz" in names


@pytest.fixture(scope="module")
def installed(wheel, tmp_path_factory) -> Path:
    """The wheel installed as a copy (no editable finder) into a folder of its own."""
    target = tmp_path_factory.mktemp("site")
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target",
                    str(target), wheel.filename], check=True, capture_output=True)
    return target


def _python(installed: Path, cwd: Path, code: str) -> subprocess.CompletedProcess:
    """``code`` run with the installed copy and the environment's other packages, but none of
    this environment's .pth files (``-S``: its editable install of facecap is not seen)."""
    import sysconfig

    path = [str(installed), sysconfig.get_paths()["purelib"]]
    if cwd == ROOT:
        path.insert(0, str(ROOT))  # the working directory comes first, as for Prefect's worker
    env = {"PATH": os.environ["PATH"], "PYTHONPATH": os.pathsep.join(path),
           "HOME": os.environ.get("HOME", "/tmp")}
    return subprocess.run([sys.executable, "-S", "-c", code], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=300)


def test_an_installed_copy_runs_the_flows_from_a_checkout_and_from_anywhere(installed, tmp_path):
    """A worker whose working directory is a checkout (the image's /opt/facecap, where the
    entrypoints are) imports the flows though the checkout's ``facecap/`` folder, which holds
    the command line only, comes first on sys.path; elsewhere the installed copy serves, and
    the checkout-only names do not exist."""
    code = ("import facecap.flows.capture, facecap.flows.dataset, facecap.flows.evaluate, "
            "facecap.deploy.serve; print(facecap.flows.capture.__file__)")
    in_checkout = _python(installed, ROOT, code)
    assert in_checkout.returncode == 0, in_checkout.stderr[-2000:]
    assert Path(in_checkout.stdout.strip()) == ROOT / "flows" / "capture.py"
    elsewhere = _python(installed, tmp_path, code + "\nimport tasks")
    assert Path(elsewhere.stdout.strip()) == installed / "facecap" / "flows" / "capture.py"
    assert "No module named 'tasks'" in elsewhere.stderr


def test_nothing_imports_the_folders_by_their_checkout_names():
    """``import tasks`` works in a checkout only (and would load a second copy of a module
    beside ``facecap.tasks``): the tests, benchmarks and tools use the installed names, in
    their code and in the scripts they run (strings). This file names them on purpose."""
    import re

    pattern = re.compile(r"(?:^\s*|\\n|[\"'(;]\s*)(?:from|import) (?:[\w.]+,\s*)*(?:tasks|flows|deploy)\b(?![\w/])")
    found = [f"{path.relative_to(ROOT)}:{n}" for folder in ("tests", "benchmarks", "tools")
             for path in (ROOT / folder).rglob("*.py") if path != Path(__file__).resolve()
             for n, line in enumerate(path.read_text().splitlines(), 1)
             if pattern.search(line.split("#")[0])]
    assert found == []
    assert pattern.search('script = "import sys\\nfrom flows.local_server import x"')
    assert pattern.search("    import tasks.stages as stages")
    assert pattern.search('script = ("import logging, tasks.stages\\n"')
    assert not pattern.search("from facecap.tasks import graph")
