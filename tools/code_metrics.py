"""Size and layering figures of the product code, from its AST and its imports.

    python tools/code_metrics.py            # the figures
    python tools/code_metrics.py --list     # and what each one counts, by file and line

Counts, over the installed packages (``facecap_core``, ``facecap``, ``tasks``, ``pages``,
``flows``, ``deploy``): imports against the layers (:data:`LAYERS`), import circles between modules
(every import: at the top, in a function, or under ``if TYPE_CHECKING:``), imports inside
functions and whether each states its reason, files over :data:`LONG_FILE` lines, functions
over :data:`LONG_FUNCTION` lines. ``tests/test_graph.py`` holds every figure at zero (the long
files but the ones it lists, each with its reason).
"""

from __future__ import annotations

import argparse
import ast
import io
import re
import sys
import tokenize
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
    # The kernels compiled at install: it names every stage's numba kernel.
    ("facecap_core.precompile", 9),
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

LONG_FILE = 600
LONG_FUNCTION = 80
INNER_REASON = "# Imported where used:"
"""A module's banner, at the top level, for the third-party dependencies it imports inside
functions (an optional or heavy one, one whose settings are read at import): it names each
one it covers (``pycolmap``, ``pillow-heif``, ``Prefect``...). Any other import inside a
function, and every one of the project's own modules, states its reason in a comment on its
line or on the lines just above it; a comment above a run of imports speaks for the run."""
LONG_REASON = "# Long on purpose:"
"""How a function over :data:`LONG_FUNCTION` lines states its reason, at its top."""
REASON_WORDS = 3
"""Fewest words of a reason (a comment that only tells a linter something is none)."""
DIRECTIVE = re.compile(r"\s*(noqa\b|type:\s*ignore|pragma\b|fmt:|isort:|ruff:|pylint:|mypy:)",
                       re.IGNORECASE)
"""A comment, or the part of one between two ``#``, meant for a tool, not for a reader."""


def module_name(path: Path, root: Path = ROOT) -> str:
    """``tasks/store/base.py`` → ``tasks.store.base``; a package's ``__init__`` is the package."""
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def product_files(root: Path = ROOT) -> list[Path]:
    return sorted(p for package in PACKAGES if (root / package).is_dir()
                  for p in (root / package).rglob("*.py"))


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


def analyse(root: Path = ROOT) -> dict:
    files = product_files(root)
    graph, third_party = import_graph(files, root)
    inner, long_files, long_functions = [], [], []
    for path in files:
        text = path.read_text()
        tree = ast.parse(text)
        rel = str(path.relative_to(root))
        inner += inner_imports(tree, text, rel)
        long_functions += functions_over(tree, text, rel)
        lines = text.count("\n")
        if lines > LONG_FILE:
            long_files.append((rel, lines))
    return {"layers": layer_violations(graph, third_party), "circles": circles(graph),
            "inner_imports": sorted(set(inner)),
            "long_files": long_files, "long_functions": long_functions}


def import_graph(files: list[Path], root: Path = ROOT) -> tuple[dict[str, set[str]],
                                                                 dict[str, set[str]]]:
    """{module: the project modules it imports} and {module: the top-level names it imports},
    from every import statement: at the top, in a function, or under ``if TYPE_CHECKING:``
    (never run, yet the annotation ties the two modules all the same: a circle is a circle,
    and a layer crossed for a type is crossed)."""
    known = {module_name(p, root) for p in files}
    graph: dict[str, set[str]] = {m: set() for m in known}
    third_party: dict[str, set[str]] = {m: set() for m in known}
    for path in files:
        name = module_name(path, root)
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                third_party[name].update(a.name.split(".")[0] for a in node.names)
            elif isinstance(node, ast.ImportFrom) and not node.level:
                third_party[name].add((node.module or "").split(".")[0])
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                graph[name].update(m for m in imported_modules(node, name, path.name == "__init__.py", known)
                                   if m != name and not name.startswith(m + "."))
    return graph, third_party


def comments(text: str) -> dict[int, str]:
    """{line number: its comment, without the ``#``}, from the tokens (a ``#`` in a string is
    no comment)."""
    return {token.start[0]: token.string[1:]
            for token in tokenize.generate_tokens(io.StringIO(text).readline)
            if token.type == tokenize.COMMENT}


def is_reason(comment: str) -> bool:
    """Whether a comment says something to a reader: at least :data:`REASON_WORDS` words once
    its linter directives (``noqa``, ``type: ignore``, ``pragma``...) are left out."""
    said = " ".join(part for part in comment.split("#") if not DIRECTIVE.match(part))
    return len(re.findall(r"[^\W\d_]{2,}", said)) >= REASON_WORDS


def _comment_lines(start: int, step: int, notes: dict[int, str], lines: list[str]) -> list[int]:
    """The run of comment-only lines from line ``start`` on, going by ``step`` (1 or -1)."""
    run = []
    i = start
    while i in notes and lines[i - 1].lstrip().startswith("#"):
        run.append(i)
        i += step
    return sorted(run)


def _banner(notes: dict[int, str], lines: list[str]) -> str:
    """The module's :data:`INNER_REASON` comment at the top level, with the comment lines
    that continue it."""
    marker = INNER_REASON[1:]
    start = next((i for i, note in sorted(notes.items())
                  if note.startswith(marker) and lines[i - 1].startswith("#")), None)
    if start is None:
        return ""
    return " ".join(notes[i] for i in _comment_lines(start, 1, notes, lines))[len(marker):]


def banner_names(banner: str) -> set[str]:
    """The words of a banner as module names: lowercase, ``pillow-heif`` as ``pillow_heif``."""
    return {w.lower().replace("-", "_") for w in re.findall(r"[A-Za-z_][\w-]*", banner)}


def _covered_by(named: set[str], node: ast.Import | ast.ImportFrom) -> bool:
    """Whether a banner's ``named`` modules hold every one ``node`` imports: third-party ones
    only (the project's own modules each say their own reason: a circle, what they load)."""
    if isinstance(node, ast.ImportFrom):
        tops = [(node.module or "").split(".")[0] if not node.level else ""]
    else:
        tops = [a.name.split(".")[0] for a in node.names]
    return all(top and top not in PACKAGES and top.lower() in named for top in tops)


def inner_imports(tree: ast.Module, text: str, where: str) -> list[tuple[str, bool]]:
    """(``file:line``, whether its reason is stated) for each import inside a function.

    Its reason (:func:`is_reason`) is a comment on its lines or on the comment lines just
    above it (not a function's :data:`LONG_REASON`); an import right after another in the same
    block shares that one's. Else the module's banner (:data:`INNER_REASON`, itself a reason)
    names the third-party module it imports."""
    notes = comments(text)
    lines = text.split("\n")
    banner = _banner(notes, lines)
    named = banner_names(banner) if is_reason(banner) else set()
    found = []
    for block in _function_blocks(tree):
        said_before = False
        for node in block:
            if not isinstance(node, (ast.Import, ast.ImportFrom)):
                said_before = False
                continue
            own = " ".join(notes.get(i, "") for i in range(node.lineno, node.end_lineno + 1))
            above = " ".join(notes[i] for i in _comment_lines(node.lineno - 1, -1, notes, lines)
                             if not lines[i - 1].strip().startswith(LONG_REASON))
            said_before = said_before or is_reason(own) or is_reason(above)
            found.append((f"{where}:{node.lineno}", said_before or _covered_by(named, node)))
    return found


def _function_blocks(tree: ast.Module):
    """Every list of statements inside a function (its body, an ``if``'s branches, an
    ``except``'s...), each once."""
    def blocks(node: ast.AST, inside: bool):
        inside = inside or isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
        for field in ("body", "orelse", "finalbody", "handlers", "cases"):
            children = getattr(node, field, None)
            if not isinstance(children, list):
                continue
            if inside and children and isinstance(children[0], ast.stmt):
                yield children
            for child in children:
                yield from blocks(child, inside)

    yield from blocks(tree, False)


def functions_over(tree: ast.Module, text: str, where: str) -> list[tuple[str, int, bool]]:
    """(``file:line name``, length, whether it states its reason) for each function over
    :data:`LONG_FUNCTION` lines: a :data:`LONG_REASON` comment at its top, itself a reason."""
    lines = text.split("\n")
    found = []
    for f in ast.walk(tree):
        if not isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        length = f.end_lineno - f.lineno + 1
        if length > LONG_FUNCTION:
            top = [line.strip() for line in lines[f.lineno:f.body[0].end_lineno + 2]]
            said = any(line.startswith(LONG_REASON) and is_reason(line[len(LONG_REASON):])
                       for line in top)
            found.append((f"{where}:{f.lineno} {f.name}", length, said))
    return found


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
