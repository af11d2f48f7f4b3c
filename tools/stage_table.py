"""The artifact table of ``docs/service.md``, made from the stage rows.

    python tools/stage_table.py            # print the table
    python tools/stage_table.py --write    # put it into docs/service.md between its markers

Every line but the first (the raw inputs) is one row of :data:`facecap_core.pipeline.STAGES`:
its name, the inputs it reads (and which stage makes each), its config section and the
files it writes (``Stage.outputs``, checked on every run). ``tests/test_graph.py`` checks
that the page holds what this prints.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # run from a checkout: facecap_core beside this folder

from facecap_core.pipeline import STAGES  # noqa: E402 - after the path above
from facecap_core.stage import Stage  # noqa: E402

PAGE = ROOT / "docs" / "service.md"
BEGIN = "<!-- stage table: made by tools/stage_table.py from the stage rows; do not edit -->"
END = "<!-- end of stage table -->"
INGEST = ("| ingest | the capture, the scan, its landmarks | – | `video.mp4` or `photos/`, "
          "the scan's file, the landmarks' file (content key `input-…`) |")


def _name(stage: Stage) -> str:
    return f"{stage.name}[i]" if stage.per_keyframe else stage.name


def _input(stage: Stage, name: str, by_name: dict[str, Stage]) -> str:
    source = by_name.get(stage.source(name))
    said = name.replace("_", " ")
    if source is not None and source.name != name:
        said += f" ({_name(source)})"
    elif source is not None and source.per_keyframe:
        said = f"every {_name(source)}"
    return said + (" if given" if name in stage.optional else "")


def _file(name: str) -> str:
    """A name of Stage.outputs as the page shows it: ``frame_<index>.png``."""
    return "`" + re.sub(r"\{(\w+)(:[^}]*)?\}", r"<\1>", name) + "`"


def table(stages: tuple[Stage, ...] = STAGES) -> str:
    """The markdown table: one line per stage, after the raw inputs' line."""
    by_name = {stage.name: stage for stage in stages}
    lines = ["| stage | inputs | config section | files |", "|---|---|---|---|", INGEST]
    for stage in stages:
        inputs = ", ".join(_input(stage, n, by_name) for n in stage.inputs + stage.optional)
        section = f"`{stage.section}`" if stage.section else "–"
        if stage.per_keyframe:
            section += ", params `{index: i}`"
        files = [_file(n) for n in stage.outputs]
        files += [f"{_file(n)} (when it has any)" for n in stage.optional_outputs]
        lines.append(f"| {_name(stage)} | {inputs} | {section} | {', '.join(files)} |")
    return "\n".join(lines) + "\n"


def page_table(text: str) -> str:
    """The table between the page's markers."""
    start, end = text.index(BEGIN) + len(BEGIN) + 1, text.index(END)
    return text[start:end]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--write", action="store_true",
                        help=f"put the table into {PAGE.relative_to(ROOT)}")
    args = parser.parse_args(argv)
    made = table()
    if not args.write:
        print(made, end="")
        return
    text = PAGE.read_text()
    PAGE.write_text(text.replace(page_table(text), made))


if __name__ == "__main__":
    main()
