"""Size and layering figures of the product code, from its AST and its imports.

    python tools/code_metrics.py            # the figures
    python tools/code_metrics.py --list     # and what each one counts, by file and line

Counts, over the installed packages (``facecap_core``, ``facecap``, ``tasks``, ``flows``,
``deploy``): imports against the layers (:data:`LAYERS`), import circles between modules
(every import, at the top or in a function), imports inside functions, files over 450
lines, functions over 80 lines. ``tests/test_graph.py`` holds the layers and the circles
at zero.
"""

from __future__ import annotations

import argparse
import ast
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("facecap_core", "facecap", "tasks", "pages", "flows", "deploy")
LAYERS = (
    # The shared helpers: every facecap_core module that is not in a stage below (camera,
    # geometry, meshio, render, template, face, video, photos, config, the non-rigid
    # registration, ...): they import only each other.
    ("facecap_core", 0),
    # The stages, in pipeline order: a stage imports helpers and earlier stages only.
    ("facecap_core.keyframes", 1),
    ("facecap_core.pose", 2),
    ("facecap_core.landmarks", 3),
    ("facecap_core.coarse", 4),
    ("facecap_core.mvs", 5),
    ("facecap_core.fitting", 6),
    ("facecap_core.texture", 6),  # the fitting stage's vertex colours
    ("facecap_core.evaluation", 7),
    ("facecap_core.baselines", 8),
    # The pipeline: the stages' rows in order and their settings assembled.
    ("facecap_core.pipeline", 9),
    # Above the science: the tasks over the store, the flows, their deployments.
    ("tasks", 10),
    # The results pages and the server of their links: over the tasks' store, under the
    # flows and the command line that make and serve them.
    ("pages", 10.5),
    ("flows", 11),
    ("deploy", 12),
    # The synthetic world and the ear training: beside the orchestration, never imported by
    # it (only the command line's synth, demo and train-ears commands, the tests and the
    # benchmarks use them).
    ("facecap.synthetic", 13),
    ("facecap.ear_training", 13),
    # The command line, on top.
    ("facecap", 14),
)
"""(module prefix, layer): a module's layer is that of its longest prefix here; a stage the
list lacks takes its place from the pipeline's order (:func:`layers`)."""

FORBIDDEN = {"facecap_core": ("prefect",),
             "facecap.synthetic": ("tasks", "pages", "flows", "deploy"),
             "facecap.ear_training": ("tasks", "pages", "flows", "deploy"),
             "pages": ("flows", "deploy")}
"""Besides the layers: what a package never imports (a third-party name, or a module of the
repository's, by prefix)."""
OUTPUT_DISCIPLINE = ("tasks.outputs", "tasks.scratch", "tasks.runner")
"""What of the orchestration the synthetic world and the ear training may import all the
same: the results writer, the scratch folder and the store's address, so that ``synth`` and
``train-ears`` write their results as ``reconstruct`` does (never through a link, never over
an input, never in the store)."""

UNINSTALLED = ("tasks", "pages", "flows", "deploy")
"""Top-level names that exist only in a checkout (installed as ``facecap.tasks``, ...): an
import of one of them would load a second copy of the module, or fail once installed."""

LONG_FILE = 450
LONG_FUNCTION = 80
INNER_REASON = "# Imported where used:"
"""How a module states why it imports inside functions (an optional or heavy dependency, a
setting read at import), at the top level; or a comment on the import's line or the one above."""
LONG_REASON = "# Long on purpose:"
"""How a function over :data:`LONG_FUNCTION` lines states its reason, at its top."""


def module_name(path: Path) -> str:
    """``tasks/store/base.py`` → ``tasks.store.base``; a package's ``__init__`` is the package."""
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def product_files() -> list[Path]:
    return sorted(p for package in PACKAGES if (ROOT / package).is_dir()
                  for p in (ROOT / package).rglob("*.py"))


def _canonical(name: str) -> str:
    """The repository's folders are installed under ``facecap.``: one name for one module."""
    for package in UNINSTALLED:
        if name == f"facecap.{package}" or name.startswith(f"facecap.{package}."):
            return name[len("facecap."):]
    return name


def imported_modules(node: ast.AST, importer: str, is_package: bool, known: set[str]) -> list[str]:
    """The project modules one import statement loads (``from a import b`` loads ``a.b``
    where that is a module, else ``a``)."""
    if isinstance(node, ast.Import):
        names = [a.name for a in node.names]
    else:
        base = node.module or ""
        if node.level:
            parent = importer.split(".")
            parent = parent if is_package else parent[:-1]
            parent = parent[:len(parent) - node.level + 1]
            base = ".".join(parent + ([base] if base else []))
        names = [f"{base}.{a.name}" if f"{_canonical(base)}.{a.name}" in known else base
                 for a in node.names]
    out = []
    for name in map(_canonical, names):
        while name and name not in known:
            name = name.rpartition(".")[0]
        if name:
            out.append(name)
    return out


def analyse() -> dict:
    files = product_files()
    known = {module_name(p) for p in files}
    graph: dict[str, set[str]] = {m: set() for m in known}
    third_party: dict[str, set[str]] = {m: set() for m in known}
    inner_imports, long_files, long_functions = [], [], []
    for path in files:
        text = path.read_text()
        tree = ast.parse(text)
        name = module_name(path)
        rel = path.relative_to(ROOT)
        lines = text.count("\n")
        if lines > LONG_FILE:
            long_files.append((str(rel), lines))
        lines_of = text.split("\n")
        module_reason = any(line.startswith(INNER_REASON) for line in lines_of)
        functions = [n for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))]
        for f in functions:
            length = f.end_lineno - f.lineno + 1
            if length > LONG_FUNCTION:
                top = lines_of[f.lineno:f.body[0].end_lineno + 2]
                said = any(line.strip().startswith(LONG_REASON) for line in top)
                long_functions.append((f"{rel}:{f.lineno} {f.name}", length, said))
            for node in ast.walk(f):
                if isinstance(node, (ast.Import, ast.ImportFrom)):
                    said = module_reason or any("#" in lines_of[i] for i in (
                        node.lineno - 1, node.lineno - 2))
                    inner_imports.append((f"{rel}:{node.lineno}", said))
        typing_only = {id(n) for block in ast.walk(tree) if _is_type_checking(block)
                       for n in ast.walk(block)}
        for node in ast.walk(tree):
            if id(node) in typing_only:
                continue
            if isinstance(node, ast.Import):
                third_party[name].update(a.name.split(".")[0] for a in node.names)
            elif isinstance(node, ast.ImportFrom) and not node.level:
                third_party[name].add((node.module or "").split(".")[0])
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                graph[name].update(m for m in imported_modules(node, name, path.name == "__init__.py", known)
                                   if m != name and not name.startswith(m + "."))
    return {"layers": layer_violations(graph, third_party), "circles": circles(graph),
            "inner_imports": sorted(set(inner_imports)),
            "long_files": long_files, "long_functions": long_functions}


def _is_type_checking(node: ast.AST) -> bool:
    """``if TYPE_CHECKING:``: imports for annotations only, never run."""
    return isinstance(node, ast.If) and (
        getattr(node.test, "id", None) == "TYPE_CHECKING"
        or getattr(node.test, "attr", None) == "TYPE_CHECKING")


def pipeline_rows() -> list[str]:
    """The stage modules in the order ``facecap_core/pipeline.py`` lists their rows (read from
    its ``STAGES`` and its imports, without importing it); a module named ``stage`` stands for
    its package."""
    tree = ast.parse((ROOT / "facecap_core" / "pipeline.py").read_text())
    names = {}
    for node in tree.body:
        if isinstance(node, ast.ImportFrom) and node.module:
            for a in node.names:
                names[a.asname or a.name] = f"{node.module}.{a.name}"
    rows = next(node.value.elts for node in tree.body if isinstance(node, ast.AnnAssign | ast.Assign)
                and getattr(getattr(node, "target", None) or node.targets[0], "id", "") == "STAGES")
    modules = [names[row.value.id] for row in rows]
    return [m.rpartition(".")[0] if m.endswith(".stage") else m for m in modules]


def _under(module: str, prefix: str) -> bool:
    return module == prefix or module.startswith(prefix + ".")


def _longest_prefix(module: str, prefixes) -> str:
    return max((p for p in prefixes if _under(module, p)), key=len)


def layers() -> dict[str, float]:
    """:data:`LAYERS`, and a stage it does not list (a new one) between the rows around it
    in the pipeline's order."""
    found = dict(LAYERS)
    rows = pipeline_rows()
    for i, module in enumerate(rows):
        if _longest_prefix(module, found) == "facecap_core":  # listed among the helpers only
            before = max((layer(m, found) for m in rows[:i]), default=0)
            after = min((n for n in (layer(m, found) for m in rows[i + 1:]) if n > before),
                        default=before + 1)
            found[module] = (before + after) / 2
    return found


def layer(module: str, known: dict[str, float] | None = None) -> float:
    known = known or layers()
    return known[_longest_prefix(module, known)]


def layer_violations(graph: dict[str, set[str]], third_party: dict[str, set[str]]) -> list[str]:
    """``importer -> imported`` for each import that points up the layers or that
    :data:`FORBIDDEN` names."""
    known = layers()
    found = [f"{m} -> {d}" for m in sorted(graph) for d in sorted(graph[m])
             if layer(d, known) > layer(m, known)]
    found += [f"{m} -> {t}" for m in sorted(graph) for t in sorted(third_party[m] & set(UNINSTALLED))]
    for package, banned in FORBIDDEN.items():
        found += [f"{m} -> {t}" for m in sorted(graph)
                  if _under(m, package)
                  for t in sorted(third_party[m] & set(banned))]
        found += [f"{m} -> {d}" for m in sorted(graph) if _under(m, package)
                  for d in sorted(graph[m])
                  if any(_under(d, b) for b in banned)
                  and not (package != "facecap_core"
                           and any(_under(d, a) for a in OUTPUT_DISCIPLINE))]
    return found


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan's algorithm)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10 * len(graph)))
    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(found)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--list", action="store_true", help="list what each figure counts")
    args = parser.parse_args()
    figures = analyse()
    print(f"imports against the layers: {len(figures['layers'])}")
    print(f"import circles:            {len(figures['circles'])}")
    unsaid = sum(not said for _, said in figures["inner_imports"])
    print(f"imports inside functions:  {len(figures['inner_imports'])} ({unsaid} without a "
          "stated reason)")
    print(f"files over {LONG_FILE} lines:     {len(figures['long_files'])}")
    unsaid = sum(not said for *_, said in figures["long_functions"])
    print(f"functions over {LONG_FUNCTION} lines:  {len(figures['long_functions'])} "
          f"({unsaid} without a reason at their top)")
    if args.list:
        for v in figures["layers"]:
            print("against the layers:", v)
        for c in figures["circles"]:
            print("circle:", " ↔ ".join(c))
        for f, said in figures["inner_imports"]:
            print("inner import:", f, "(reason stated)" if said else "")
        for f, n in figures["long_files"]:
            print(f"long file: {f} ({n})")
        for f, n, said in figures["long_functions"]:
            print(f"long function: {f} ({n}{', reason stated' if said else ''})")


if __name__ == "__main__":
    main()
