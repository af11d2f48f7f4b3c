"""``evaluate-dataset``: score every reconstruction that has a scan, compare the table with
the previous evaluation and flag regressions. Scheduled nightly by ``facecap serve``.

Each evaluation is kept as ``OUT/evaluations/<UTC time>.json``; the newest older one is the
baseline. A capture regresses when its accuracy or completion median (similarity protocol)
grows by more than ``tolerance_mm`` and ``tolerance_rel``.
"""

from __future__ import annotations

import json
import re
from datetime import UTC, datetime
from pathlib import Path

from prefect import flow, get_run_logger
from prefect.artifacts import create_markdown_artifact, create_table_artifact
from prefect.events import emit_event
from prefect.runtime import flow_run

from facecap.flows.service import guard
from facecap.flows.ui import publish_dataset_page
from facecap.pages.dataset import rewrite_dataset_page
from facecap.tasks.outputs import check_output_place, write_results
from facecap.tasks.own_files import OwnFileError, read_json
from facecap.tasks.runner import run_leases
from facecap.tasks.stages import call_ingest, call_stage
from facecap.tasks.store import open_store
from facecap_core.dataset import inside, scan_dataset
from facecap_core.errors import InputError
from facecap_core.evaluation import paper_table
from facecap_core.settings import time_limit


def _run_name() -> str:
    return f"evaluate {Path(flow_run.parameters.get('root', 'dataset')).name}"


def regressions(current: dict, previous: dict, tolerance_mm: float,
                tolerance_rel: float, without_mesh: list[str] = ()) -> list[dict]:
    """Captures whose medians got worse than the previous evaluation's by both tolerances,
    and captures the previous evaluation scored that have a scan but no mesh now (a failed
    or cut-short reconstruction: ``now_mm`` None)."""
    flagged = [{"capture": name, "measure": "mesh missing",
                "previous_mm": round(previous[name]["accuracy"]["median"], 3), "now_mm": None}
               for name in without_mesh if name in previous]
    for name, now in current.items():
        before = previous.get(name)
        if not before:
            continue
        for side in ("accuracy", "completion"):
            a, b = now[side]["median"], before[side]["median"]
            if a - b > tolerance_mm and a > b * (1 + tolerance_rel):
                flagged.append({"capture": name, "measure": f"{side} median",
                                "previous_mm": round(b, 3), "now_mm": round(a, 3)})
    return flagged


STAMP = re.compile(r"\d{8}T\d{6,12}Z")
"""The name (UTC time) of an evaluation in ``OUT/evaluations``; other files there are not
evaluations and are ignored."""


def previous_evaluation(folder: Path, before: str) -> dict:
    """The captures' scores of the newest evaluation older than ``before`` ({} if none)."""
    older = sorted(p for p in folder.glob("*.json") if STAMP.fullmatch(p.stem) and p.stem < before)
    if not older:
        return {}
    try:
        doc = read_json(older[-1])  # never through a link, a FIFO, a JSON bomb
        # A capture without a mesh then keeps its last score, the baseline for its return.
        captures = {**doc.get("carried", {}), **doc["captures"]}
        for record in captures.values():
            for side in ("accuracy", "completion"):
                float(record[side]["median"])
    except (OSError, OwnFileError, TypeError, KeyError, AttributeError, ValueError) as exc:
        # What the file is (a FIFO, nested too deep) says it best; a record's value, its type.
        why = exc.problem if isinstance(exc, OwnFileError) else type(exc).__name__
        raise InputError(f"{older[-1]} is not an evaluation facecap wrote ({why}); move it out "
                         "of the folder or delete it") from None
    return captures


def check_history(out: Path) -> dict:
    """The baseline the next evaluation of ``out`` compares with, read before any scoring:
    a damaged history fails at once."""
    return previous_evaluation(out / "evaluations", "99999999T999999999999Z")


def preflight(root: str, out: str, store: str) -> None:
    """What ``facecap evaluate-dataset`` checks before its server starts: the dataset, the
    place of the results folder (where the history goes), that it is a folder, and the
    history in it."""
    scan_dataset(root)
    check_output_place(out, store, (root,))
    if Path(out).exists() and not Path(out).is_dir():
        raise InputError(f"the results folder {out} is a file; give the folder the dataset's "
                         "runs wrote (--out)")
    check_history(Path(out))


@flow(name="evaluate-dataset", flow_run_name=_run_name, log_prints=True,
      timeout_seconds=time_limit("evaluation_timeout_s"))
def evaluate_dataset(root: str, out: str, store: str | None = None,
                     tolerance_mm: float = 0.05, tolerance_rel: float = 0.05) -> dict:
    """Score ``out/<subject>/<capture>/mesh.ply`` against ``root/<subject>/scan.*``.

    Args:
        root: The dataset folder, with a scan.ply and scan_landmarks.json per subject.
        out: The results folder of the dataset's reconstructions.
        store: The artifact store; default the deployment's, FACECAP_STORE.
        tolerance_mm: A median that grows by more than this many mm (and by more than
            tolerance_rel) since the last evaluation is a regression.
        tolerance_rel: The relative growth a regression needs as well (0.05 = 5 %).
    """

    logger = get_run_logger()
    store = guard(out, store, dataset=root)  # a served run: only what it may touch
    check_output_place(out, store, (root,))
    out_root = Path(out)
    entries = scan_dataset(root)
    previous = check_history(out_root)  # a damaged history fails before any scoring
    current, skipped, without_mesh = {}, [], []
    with run_leases():  # what the scoring reads stays in the store until it is done
        for entry in entries:
            mesh = entry.out_dir(out_root) / "mesh.ply"
            name = entry.name
            if entry.scan is None or entry.scan_landmarks is None or not mesh.is_file():
                skipped.append(name)
                if entry.scan is not None and not mesh.is_file():
                    without_mesh.append(name)
                continue
            mesh = inside(out_root, mesh, "results folder")  # not a link to elsewhere
            inputs = {"mesh": call_ingest(store, mesh, "mesh.ply", name),
                      "scan": call_ingest(store, entry.scan, entry.scan.name, name),
                      "scan_landmarks": call_ingest(store, entry.scan_landmarks,
                                                    entry.scan_landmarks.name, name)}
            key, _ = call_stage("evaluation", store, inputs, None, name)

            doc = json.loads((open_store(store).get(key) / "evaluation.json").read_text())
            current[name] = doc["similarity"]
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%S%fZ")
    flagged = regressions(current, previous, tolerance_mm, tolerance_rel, without_mesh)
    write_results(out_root, {f"evaluations/{stamp}.json": json.dumps(
        {"time": stamp, "dataset": Path(root).resolve().name,  # the dataset page's title
         "captures": current, "skipped": skipped, "regressions": flagged,
         "carried": {name: previous[name] for name in without_mesh if name in previous}},
        indent=1).encode()})
    rewrite_dataset_page(out_root)  # with this evaluation in each capture's history
    rows = [{"capture": name, "accuracy_mean": round(s["accuracy"]["mean"], 3),
             "accuracy_median": round(s["accuracy"]["median"], 3),
             "completion_mean": round(s["completion"]["mean"], 3),
             "completion_median": round(s["completion"]["median"], 3),
             "scale_error_pct": scale_error_pct(s),
             "regressed": any(f["capture"] == name for f in flagged)}
            for name, s in sorted(current.items())]
    if rows:
        create_table_artifact(rows, key="evaluation", description="similarity protocol, mm")
        table = _table(current)
        create_markdown_artifact(table + ("\n\n**Regressions:** " + ", ".join(
            f"{f['capture']} {f['measure']} {f['previous_mm']} → {f['now_mm'] or '–'} mm"
            for f in flagged) if flagged else "\n\nNo regression."),
            key="evaluation-table", description="paper-style table")
    if flagged:
        logger.warning(f"{len(flagged)} regression(s): {flagged}")
        emit_event(event="facecap.evaluation.regressed",
                   resource={"prefect.resource.id": f"facecap.dataset.{Path(root).name}"},
                   payload={"regressions": flagged})
    publish_dataset_page(out_root, store)  # after the event: a link never holds up an alert
    logger.info(f"scored {len(current)} captures, skipped {len(skipped)} without scan or mesh")
    return {"captures": current, "skipped": skipped, "regressions": flagged}


def scale_error_pct(similarity_record: dict) -> float:
    """How far the mesh's millimetres are off (%): the similarity protocol's alignment scales
    the mesh by ``scale`` onto the scan, so the mesh is ``1 / scale`` times its true size."""
    return round(100 * (1 / similarity_record["scale"] - 1), 2)


def _table(current: dict) -> str:
    return paper_table([("facecap (similarity)", list(current.values()))])
