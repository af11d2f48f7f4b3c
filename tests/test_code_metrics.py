"""tools/code_metrics.py sees what it is for, on small modules written for the purpose: an
import under ``if TYPE_CHECKING:`` ties two modules, a linter directive is no reason, a
module's banner covers only what it names, a file over the limit is counted."""

from __future__ import annotations

import ast
import importlib.util
import textwrap
from pathlib import Path

import pytest

TOOL = Path(__file__).resolve().parents[1] / "tools" / "code_metrics.py"


@pytest.fixture(scope="module")
def metrics():
    spec = importlib.util.spec_from_file_location("code_metrics", TOOL)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def write(root: Path, files: dict[str, str]) -> Path:
    """The modules ``{path: source}`` under ``root`` (packages get an empty ``__init__``)."""
    for name, source in files.items():
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        for folder in path.relative_to(root).parents[:-1]:
            (root / folder / "__init__.py").touch()
        path.write_text(textwrap.dedent(source))
    return root


def reasons(metrics, source: str) -> list[bool]:
    """Whether each import inside a function of ``source`` states its reason."""
    source = textwrap.dedent(source)
    return [said for _, said in metrics.inner_imports(ast.parse(source), source, "m.py")]


def test_an_import_for_annotations_only_makes_a_circle_and_crosses_layers(metrics, tmp_path):
    root = write(tmp_path, {
        "facecap_core/a.py": "from facecap_core.b import B\n",
        "facecap_core/b.py": """\
            from typing import TYPE_CHECKING

            if TYPE_CHECKING:
                from facecap_core.a import A
            """,
        "facecap_core/camera.py": """\
            import typing

            if typing.TYPE_CHECKING:
                from facecap_core.mvs.depth import DepthConfig
            """,
        "facecap_core/mvs/depth.py": "DepthConfig = dict\n",
    })
    graph, third_party = metrics.import_graph(metrics.product_files(root), root)
    assert metrics.circles(graph) == [["facecap_core.a", "facecap_core.b"]]
    assert metrics.layer_violations(graph, third_party) == [
        "facecap_core.camera -> facecap_core.mvs.depth"]


def test_a_linter_directive_or_a_word_or_two_is_no_reason(metrics):
    assert reasons(metrics, """\
        def f():
            import cvxopt  # noqa: F401
            x = 1
            import dlib  # type: ignore[import]
            x = 2
            import pycolmap  # pragma: no cover
            x = 3
            # noqa
            import prefect
            x = 4
            import httpx  # optional
            x = 5
            import botocore  # noqa: F401  # only with an S3 store
            x = 6
            # COLMAP's logging is set up first, then it loads.
            import pycolmap
        """) == [False, False, False, False, False, True, True]


def test_a_comment_above_a_run_of_imports_speaks_for_the_run(metrics):
    assert reasons(metrics, """\
        def f():
            # Prefect reads its settings when first imported.
            from prefect import flow

            from facecap.flows.capture import run
            x = 1
            from facecap.flows.dataset import other
        """) == [True, True, False]


def test_a_long_function_s_reason_is_not_its_first_import_s(metrics):
    assert reasons(metrics, """\
        def f():
            # Long on purpose: a declaration, every option in the order --help shows them.
            from facecap.tasks.graph import STEPS
        """) == [False]


def test_a_banner_covers_only_the_third_party_modules_it_names(metrics):
    assert reasons(metrics, """\
        # Imported where used: pillow-heif and dlib are optional, and facecap_core.camera is
        # named here too.


        def f():
            from pillow_heif import register_heif_opener
            x = 1
            import dlib.image
            x = 2
            import cv2
            x = 3
            from facecap_core.camera import CameraSet
        """) == [True, True, False, False]
    # A banner that names nothing, or too little to be a reason, covers nothing.
    assert reasons(metrics, """\
        # Imported where used: dlib


        def f():
            import dlib
        """) == [False]


def test_a_long_function_needs_a_reason_of_words(metrics):
    body = "\n".join(f"    x{i} = {i}" for i in range(90))
    for top, said in (("# Long on purpose: one kernel, its loops unrolled for numba.", True),
                      ("# Long on purpose: yes", False), ("# noqa", False)):
        source = f"def f():\n    {top}\n{body}\n"
        assert metrics.functions_over(ast.parse(source), source, "m.py") == [
            ("m.py:1 f", 92, said)]


def test_a_file_over_the_limit_is_counted(metrics, tmp_path):
    limit = metrics.LONG_FILE
    root = write(tmp_path, {"facecap_core/long.py": "x = 1\n" * (limit + 1),
                            "facecap_core/short.py": "x = 1\n" * limit})
    assert metrics.analyse(root)["long_files"] == [("facecap_core/long.py", limit + 1)]
