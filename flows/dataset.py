"""``reconstruct-dataset``: every capture of a dataset folder (layout in
:mod:`facecap_core.dataset`), one ``reconstruct-capture`` subflow each, then a
cross-capture consistency report for subjects with several captures.

A capture that fails (bad video, no face) is reported and the others go on; the flow
ends Failed if any capture failed, so the UI shows it.
"""

from __future__ import annotations

import json
from itertools import combinations
from pathlib import Path

from prefect import flow, get_run_logger

from facecap_core.dataset import SUMMARY_NAMES, CaptureEntry, mesh_consistency, scan_dataset
from facecap_core.errors import FacecapError, InputError
from flows.capture import as_user_sees_it, reconstruct_capture
from flows.service import guard


def _run_name() -> str:
    from prefect.runtime import flow_run

    return f"dataset {Path(flow_run.parameters.get('root', 'dataset')).name}"


def check_dataset_output(entries: list[CaptureEntry], out: Path) -> None:
    """No subject's results folder may take the name of a summary the flows write into OUT:
    the summary would fail after every capture had run, or overwrite a subject's results."""
    for entry in entries:
        if entry.subject in SUMMARY_NAMES:
            raise InputError(f"the subject folder {entry.video.parent} is named like the "
                             f"summary {out / entry.subject} the dataset run writes; rename "
                             "the subject folder")


def consistency_report(out: Path, done: dict[tuple[str, str], Path]) -> list[dict]:
    """Vertex-to-vertex agreement of every pair of captures of one subject."""
    from facecap_core.meshio import load_mesh

    by_subject: dict[str, list[tuple[str, Path]]] = {}
    for (subject, capture), folder in done.items():
        if (folder / "mesh.ply").is_file():
            by_subject.setdefault(subject, []).append((capture, folder / "mesh.ply"))
    rows = []
    for subject, meshes in sorted(by_subject.items()):
        for (ca, pa), (cb, pb) in combinations(sorted(meshes), 2):
            figures = mesh_consistency(load_mesh(pa).vertices, load_mesh(pb).vertices)
            rows.append({"subject": subject, "capture_a": ca, "capture_b": cb,
                         **{k: round(v, 3) for k, v in figures.items()}})
    if rows:
        (out / "consistency.json").write_text(json.dumps(rows, indent=1))
    return rows


@flow(name="reconstruct-dataset", flow_run_name=_run_name, log_prints=True)
def reconstruct_dataset(root: str, out: str, config: str | None = None,
                        store: str | None = None) -> dict:
    """Reconstruct every capture under ``root`` into ``out/<subject>/<capture>/``."""
    from prefect.artifacts import create_table_artifact

    logger = get_run_logger()
    store = guard(out, store, dataset=root, config=config)  # a served run: only what it may touch
    entries = scan_dataset(root)
    out_root = Path(out)
    check_dataset_output(entries, out_root)
    out_root.mkdir(parents=True, exist_ok=True)
    done, failed = {}, {}
    for entry in entries:
        folder = entry.out_dir(out_root)
        try:
            reconstruct_capture(str(entry.video), str(folder), config=config,
                                scan=str(entry.scan) if entry.scan else None,
                                scan_landmarks=(str(entry.scan_landmarks)
                                                if entry.scan and entry.scan_landmarks else None),
                                store=store)
            done[(entry.subject, entry.capture)] = folder
        except FacecapError as exc:
            failed[f"{entry.subject}/{entry.capture}"] = as_user_sees_it(str(exc), entry.video)
            # exc_info marks it as bad input: the CLI prints it once, in its summary line.
            logger.error(f"{entry.subject}/{entry.capture}: {exc}", exc_info=exc)
    rows = consistency_report(out_root, done)
    if rows:
        create_table_artifact(rows, key="cross-capture-consistency",
                              description="same subject, two captures: vertex-to-vertex mm")
    summary = {"captures": len(entries), "done": [f"{s}/{c}" for s, c in done],
               "failed": failed, "consistency": rows}
    (out_root / "dataset.json").write_text(json.dumps(summary, indent=1))
    if failed:
        raise FacecapError(f"{len(failed)} of {len(entries)} captures failed: "
                           + "; ".join(f"{k}: {v}" for k, v in failed.items()))
    return summary
