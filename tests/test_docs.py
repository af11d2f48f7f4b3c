"""The documentation holds together: README links every page of ``docs/``, the experiments
index lists every experiment log, and no relative link of README or ``docs/`` points to a
missing file.

Only markdown links are checked, not the paths quoted as code (those name modules that may
move). ``python tests/test_docs.py`` lists the quoted repository paths that do not exist,
to fix by hand.
"""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
README = ROOT / "README.md"
EXPERIMENTS = DOCS / "experiments"
EXPERIMENTS_INDEX = EXPERIMENTS / "README.md"

LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
"""A markdown link or image: ``[words](target)``, ``![alt](target "title")``."""
FENCE = re.compile(r"^(```|~~~).*?^\1", re.S | re.M)
INLINE_CODE = re.compile(r"`[^`\n]*`")


def pages() -> list[Path]:
    """README and every markdown page under docs/."""
    return [README, *sorted(DOCS.rglob("*.md"))]


def link_targets(page: Path) -> list[str]:
    """The targets of the page's markdown links, outside code."""
    text = INLINE_CODE.sub("", FENCE.sub("", page.read_text()))
    return LINK.findall(text)


def linked_files(page: Path) -> set[Path]:
    """The local files the page links to (anchors and web addresses left out)."""
    files = set()
    for target in link_targets(page):
        if re.match(r"[a-z][a-z0-9+.-]*:", target) or target.startswith("#"):
            continue  # https:, mailto:, an anchor on the same page
        files.add((page.parent / target.split("#")[0]).resolve())
    return files


def test_readme_links_every_docs_page():
    """Each page of docs/ has its line in README's Documentation section (the experiment
    logs are listed by their own index, which README links)."""
    linked = linked_files(README)
    wanted = [*sorted(DOCS.glob("*.md")), EXPERIMENTS_INDEX]
    missing = [str(page.relative_to(ROOT)) for page in wanted if page.resolve() not in linked]
    assert not missing, f"README.md does not link {', '.join(missing)}: add a line to its " \
                        "Documentation section"


def test_the_experiments_index_lists_every_log():
    linked = linked_files(EXPERIMENTS_INDEX)
    logs = [log for log in sorted(EXPERIMENTS.glob("*.md")) if log != EXPERIMENTS_INDEX]
    missing = [log.name for log in logs if log.resolve() not in linked]
    assert not missing, f"docs/experiments/README.md does not list {', '.join(missing)}"


def test_experiment_logs_are_named_by_date_and_topic():
    logs = [log.name for log in EXPERIMENTS.glob("*.md") if log != EXPERIMENTS_INDEX]
    misnamed = [name for name in logs if not re.fullmatch(r"\d{4}-\d\d-\d\d-[a-z0-9-]+\.md", name)]
    assert not misnamed, f"name experiment logs YYYY-MM-DD-<topic>.md: {', '.join(misnamed)}"


def test_relative_links_point_to_files_that_exist():
    broken = [f"{page.relative_to(ROOT)}: {target}"
              for page in pages() for target in link_targets(page)
              if not re.match(r"[a-z][a-z0-9+.-]*:", target) and not target.startswith("#")
              and not (page.parent / target.split("#")[0]).exists()]
    assert not broken, "links to missing files:\n" + "\n".join(broken)


def test_the_link_check_sees_links_and_skips_code(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("See [the fit](fitting.md#method) and ![a view](images/a.jpg \"A\").\n"
                    "`[not](a-link.md)` and [the web](https://example.org).\n\n"
                    "```\n[nor](this.md)\n```\n")
    assert link_targets(page) == ["fitting.md#method", "images/a.jpg", "https://example.org"]
    assert linked_files(page) == {(tmp_path / "fitting.md").resolve(),
                                  (tmp_path / "images/a.jpg").resolve()}


def stale_paths() -> list[str]:
    """Paths quoted as code in README and docs/ (``tasks/store/``) that start with a folder
    or file of the repository's top level and do not exist; output folders (``out/``) left
    out."""
    top = {p.name for p in ROOT.iterdir() if not p.name.startswith(".")} - {"out"}
    stale = []
    for page in pages():
        for number, line in enumerate(page.read_text().splitlines(), 1):
            for code in re.findall(r"`([^`\n]+)`", line):
                for word in re.split(r"[\s,;()]+", code):
                    word = word.strip(".:")
                    match = re.match(r"([\w.-]+)/[\w./{}<>*-]*$", word)
                    if not match or match[1] not in top:
                        continue
                    path = re.split(r"[{<*]", word)[0]
                    if not (ROOT / path).exists():
                        stale.append(f"{page.relative_to(ROOT)}:{number}: {word}")
    return stale


if __name__ == "__main__":
    print("\n".join(stale_paths()) or "every quoted repository path exists")
