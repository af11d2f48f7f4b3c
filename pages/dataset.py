"""``OUT/index.html``: a dataset's results at a glance, one row per capture.

Written by the dataset flow when its captures are done and again by each nightly evaluation:
titled with the dataset's name (its ROOT folder's, which the runs record in OUT), a
thumbnail of each capture (its preview), its figures (keyframes, metric scale, surface,
accuracy), its status (done, failed and why, regressed; the warnings of its page, counted,
the worst in words), a link to its own page
(``<subject>/<capture>/index.html``, :mod:`facecap.pages.capture`) and the history of its
accuracy over the nightly evaluations as a small plot. The table sorts by any column (a click
on its heading). Self-contained like the capture pages: it opens from disk. The HTML is
``templates/dataset.html.j2``'s.
"""

from __future__ import annotations

import base64
from collections.abc import Callable
from pathlib import Path
from urllib.parse import quote

import cv2
import numpy as np

from facecap.pages.figures import finite_number, warnings
from facecap.pages.render import render
from facecap.pages.stored import PAGE_NAME, keep_page, stored_link
from facecap.tasks.lifecycle import report_keys
from facecap.tasks.outputs import write_results
from facecap.tasks.own_files import OwnFileError, read_json
from facecap_core.dataset import SUMMARY_NAMES
from facecap_core.evaluation import COLORBAR_HEIGHT

THUMB_WIDTH = 160


def _thumbnail(preview: Path) -> str:
    """The capture's preview, its front view cut out and shrunk, as a data URI ('' without,
    or where a link stands for it: the page shows only what lies in OUT)."""
    if preview.is_symlink() or not preview.is_file():  # a failed capture has none
        return ""
    image = cv2.imread(str(preview), cv2.IMREAD_COLOR)
    if image is None:
        return ""
    h, w = image.shape[:2]
    side = h - COLORBAR_HEIGHT
    if side > 0 and w % side == 0 and w // side >= 2:
        front = image[:side, :side]  # a heat map: square views over its colour bar
    elif w >= 3 * h:
        front = image[:, :h]  # the mesh's views side by side
    else:
        front = image
    h = int(round(front.shape[0] * THUMB_WIDTH / front.shape[1]))
    ok, png = cv2.imencode(".png", cv2.resize(front, (THUMB_WIDTH, h),
                                              interpolation=cv2.INTER_AREA))
    return "data:image/png;base64," + base64.b64encode(png.tobytes()).decode() if ok else ""


def dataset_name(out: Path) -> str:
    """The dataset's name for the page of ``out``: its ROOT folder's, as the dataset run
    recorded it in ``dataset.json`` or the latest evaluation in its record, else the results
    folder's own name (a folder neither wrote into)."""
    records = [out / "dataset.json", *sorted((out / "evaluations").glob("*.json"),
                                             reverse=True)[:1]]
    for path in records:
        try:
            name = _mapping(read_json(path)).get("dataset")
        except (OSError, OwnFileError):
            continue
        if isinstance(name, str) and name.strip():
            return name
    return out.resolve().name


def _history(out: Path) -> tuple[dict[str, list[float]], set[str]]:
    """Each capture's accuracy median (similarity, mm) over the nightly evaluations, oldest
    first, and the captures the latest one flagged as regressed."""
    series: dict[str, list[float]] = {}
    regressed: set[str] = set()
    files = sorted((out / "evaluations").glob("*.json"))
    for i, path in enumerate(files):
        try:
            doc = _mapping(read_json(path))
        except (OSError, OwnFileError):
            continue  # check_history refuses a damaged history before a run: not this page's
        for name, score in _mapping(doc.get("captures")).items():
            median = finite_number(_mapping(_mapping(score).get("accuracy")).get("median"))
            if median is not None:
                series.setdefault(name, []).append(median)
        if i == len(files) - 1:
            rows = doc.get("regressions") if isinstance(doc.get("regressions"), list) else []
            regressed = {row["capture"] for row in rows
                         if isinstance(row, dict) and isinstance(row.get("capture"), str)}
    return series, regressed


def _warnings(report: dict) -> list[str]:
    """The warnings the capture's page shows (:func:`facecap.pages.figures.warnings`, the
    worst first), or none where its figures are not what a run writes."""
    try:
        return [text for _, text in warnings({"figures": _mapping(report.get("figures"))})]
    except (TypeError, AttributeError, ValueError, KeyError):
        return []


def _mapping(value) -> dict:
    """``value`` if it is a JSON object, else an empty one: what a results folder holds is
    anyone's to write, so every value read from it is checked before use."""
    return value if isinstance(value, dict) else {}


def _count(value) -> int | None:
    """``value`` if it is a whole number of things (not a boolean), else None."""
    return value if isinstance(value, int) and not isinstance(value, bool) and value >= 0 else None


def _plain_name(name: object) -> bool:
    """A folder name of OUT as the dataset runs make them: no separator, not ``.``/``..``,
    not hidden."""
    return (isinstance(name, str) and bool(name) and "/" not in name and "\x00" not in name
            and not name.startswith("."))


def _sparkline(values: list[float]) -> dict | None:
    """What the inline plot of the values (newest on the right, the newest as a dot) draws:
    its size, the line's points and the dot's place (None without a value)."""
    if not values:
        return None
    w, h, pad = 120, 28, 3
    v = np.asarray(values, float)
    low, high = float(v.min()), float(v.max())
    span = high - low or 1.0
    xs = np.linspace(pad, w - pad, len(v)) if len(v) > 1 else np.array([w / 2])
    ys = h - pad - (v - low) / span * (h - 2 * pad)
    return {"width": w, "height": h, "count": len(v), "now": float(v[-1]),
            "points": " ".join(f"{x:.1f},{y:.1f}" for x, y in zip(xs, ys, strict=True)),
            "x": f"{xs[-1]:.1f}", "y": f"{ys[-1]:.1f}"}


def _relative_link(out: Path, subject: str, capture: str, report: dict
                   ) -> tuple[str | None, bool]:
    """The capture's page beside the dataset page, if it has one; its face may show."""
    if not (out / subject / capture / "index.html").is_file():
        return None, True
    return quote(f"{subject}/{capture}/index.html"), True


def build_dataset_page(out: Path, captures: list[tuple[str, str]],
                       failed: dict[str, str] | None = None,
                       link: Callable[[Path, str, str, dict], tuple[str | None, bool]]
                       = _relative_link, leave_out: str | None = None) -> bytes:
    """The page of the results folder ``out`` for the dataset's ``captures`` (subject,
    capture); ``failed`` maps ``subject/capture`` to why it failed; ``link(out, subject,
    capture, report)`` says the address of a capture's page (None: it has none; by default
    relative to ``out``) and whether its row may show the face (its thumbnail); the
    regressions of the subject ``leave_out`` are not counted (it is being forgotten)."""
    failed = failed or {}
    series, regressed = _history(out)
    if leave_out is not None:
        regressed = {name for name in regressed if name.split("/", 1)[0] != leave_out}
    rows = []
    for subject, capture in sorted(captures):
        name = f"{subject}/{capture}"
        folder = out / subject / capture
        # A link on the way (the subject's folder, the capture's, the report, the mesh) would
        # show what lies outside OUT: such a row shows nothing of it (_thumbnail passes over
        # a preview that is a link).
        inside = not any(p.is_symlink() for p in (out / subject, folder, folder / "report.json",
                                                  folder / "mesh.ply"))
        try:
            report = _mapping(read_json(folder / "report.json")) if inside else {}
        except (OSError, OwnFileError):  # a FIFO, a JSON bomb: the row shows nothing of it
            report = {}
        fig = _mapping(report.get("figures"))
        if name in failed:
            status, order = f"failed: {failed[name]}", 0
        elif name in regressed:
            status, order = "regressed", 1
        elif report and not (folder / "mesh.ply").is_file():
            # A run stopped before the mesh (--until): what it made is not a result.
            until = report.get("until") or "an earlier stage"
            status, order = f"stopped after {until}: no mesh", 3
        elif report:
            status, order = "done", 2
        else:
            status, order = "not run", 4
        warned = _warnings(report) if report and name not in failed else []
        href, face = link(out, subject, capture, report)
        accuracy = _mapping(_mapping(_mapping(fig.get("evaluation")).get("similarity"))
                            .get("accuracy"))
        median = finite_number(accuracy.get("median"))
        if median is None:
            median = (series.get(name) or [None])[-1]
        rows.append({
            "name": name, "href": href, "status": status, "order": order,
            "thumbnail": _thumbnail(folder / "preview.png") if face and inside else "",
            "keyframes": _count(fig.get("keyframes")),
            "scale": finite_number(fig.get("metric_scale")),
            "rough": finite_number(_mapping(fig.get("roughness")).get("bent_share_pct")),
            "median": median, "history": _sparkline(series.get(name, [])),
            "latest": (series.get(name) or [None])[-1],
            # The capture page's warnings (the worst first): counted, the worst in words.
            "warnings": warned})
    return render("dataset.html.j2", title=dataset_name(out), count=len(captures),
                  failed=len(failed), regressed=len(regressed), rows=rows,
                  warned=sum(bool(row["warnings"]) for row in rows),
                  thumb_width=THUMB_WIDTH)


def _dataset_contents(out: Path) -> tuple[list[tuple[str, str]], dict[str, str]]:
    """The captures with results in ``out`` and those ``dataset.json`` records as failed."""
    captures = sorted((subject.name, capture.name) for subject in out.iterdir()
                      if subject.is_dir() and not subject.is_symlink()
                      and subject.name not in SUMMARY_NAMES and _plain_name(subject.name)
                      for capture in subject.iterdir()
                      if _plain_name(capture.name) and not capture.is_symlink()
                      and (capture / "report.json").is_file())
    try:
        failed = _mapping(_mapping(read_json(out / "dataset.json")).get("failed"))
    except (OSError, OwnFileError):
        failed = {}
    # Only names of a capture's folder in OUT, with a reason in words: a name such as
    # '../x' would have the page show what lies outside OUT.
    failed = {name: why for name, why in failed.items()
              if name.count("/") == 1 and all(map(_plain_name, name.split("/")))
              and name.split("/")[0] not in SUMMARY_NAMES and isinstance(why, str)}
    captures += sorted({tuple(name.split("/")) for name in failed} - set(captures))
    return captures, failed


def dataset_page_without(out: Path, subject: str) -> bytes:
    """``OUT/index.html`` as it will be once ``subject`` is forgotten: without its rows,
    failures and regressions."""
    captures, failed = _dataset_contents(out)
    return build_dataset_page(out, [c for c in captures if c[0] != subject],
                              {k: v for k, v in failed.items() if k.split("/", 1)[0] != subject},
                              leave_out=subject)


def rewrite_dataset_page(out: Path) -> None:
    """``OUT/index.html`` from what ``out`` holds now (after a dataset run, an evaluation or
    ``facecap forget``): the captures with results there and the failures ``dataset.json``
    records."""
    write_results(out, {"index.html": build_dataset_page(out, *_dataset_contents(out))})


def store_dataset_page(out: Path, store) -> str:
    """Keep a copy of the dataset page in the store whose links open each capture's page
    from there (:func:`facecap.pages.stored.stored_link`, a day), for the link from the Prefect UI;
    returns its key. Made from the captures' stored pages: ``forget`` removes it with them."""
    inputs: dict[str, str] = {}

    def link(out: Path, subject: str, capture: str, report: dict) -> tuple[str | None, bool]:
        # What this store holds of the capture, whatever store the report names (a results
        # folder is anyone's to write: it must not make this store sign for another). A row
        # shows its face only where this copy is made from the capture's artifacts, so that
        # forget, which follows what an artifact was made from, removes the copy with them.
        page, stages = report_keys(report)
        held = [key for key in [page, *stages] if key and store.exists(key)]
        if not held:
            return None, False
        inputs[f"{subject}/{capture}"] = held[0]
        return (stored_link(store, page, PAGE_NAME) if page in held else None), True

    return keep_page(store, inputs, build_dataset_page(out, *_dataset_contents(out), link=link))
