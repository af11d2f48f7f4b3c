"""``reconstruct-dataset``: every capture of a dataset folder (layout in
:mod:`facecap_core.dataset`), one ``reconstruct-capture`` run each (on a work pool, runs of
the capture deployment spread over its workers; else subflows in this process), then a
cross-capture consistency report for subjects with several captures.

A capture that fails (bad video, no face) is reported and the others go on; the flow
ends Failed if any capture failed, so the UI shows it.
"""

from __future__ import annotations

import json
import time
from itertools import combinations
from pathlib import Path

import httpx
from prefect import flow, get_run_logger
from prefect.artifacts import create_table_artifact
from prefect.client.orchestration import get_client
from prefect.client.schemas.filters import FlowRunFilter, FlowRunFilterId
from prefect.context import FlowRunContext
from prefect.deployments import run_deployment
from prefect.exceptions import ObjectNotFound
from prefect.flow_engine import FlowRunTimeoutError
from prefect.runtime import flow_run

from facecap.flows.capture import (
    ConfigParameter,
    Step,
    as_user_sees_it,
    config_file,
    reconstruct_capture,
)
from facecap.flows.service import guard
from facecap.flows.ui import publish_dataset_page
from facecap.pages.dataset import rewrite_dataset_page
from facecap.tasks.outputs import check_output_place, write_results
from facecap.tasks.stages import capture_time_limit_message
from facecap_core.dataset import SUMMARY_NAMES, CaptureEntry, mesh_consistency, scan_dataset
from facecap_core.errors import FacecapError, InputError
from facecap_core.meshio import load_mesh
from facecap_core.pipeline import PipelineConfig

CAPTURE_DEPLOYMENT = "reconstruct-capture/reconstruct-capture"
"""The deployment a dataset run on a work pool submits each capture to (deploy/prefect.yaml)."""
POLL_SECONDS = 5.0
"""How often a dataset run on a work pool reads its capture runs' states."""


def _run_name() -> str:
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
        write_results(out, {"consistency.json": json.dumps(rows, indent=1).encode()})
    return rows


@flow(name="reconstruct-dataset", flow_run_name=_run_name, log_prints=True)
def reconstruct_dataset(root: str, out: str, config: ConfigParameter = None,
                        store: str | None = None, until: Step = "evaluation") -> dict:
    """Reconstruct every capture under ``root`` into ``out/<subject>/<capture>/``.

    Args:
        root: The dataset folder: ROOT/<subject>/<capture>.mp4 (or a photo folder), with
            an optional scan.ply and scan_landmarks.json per subject.
        out: The results folder: OUT/<subject>/<capture>/ for each capture.
        config: The pipeline's settings for every capture (any subset), or the path of a
            YAML file of them.
        store: The artifact store; default the deployment's, FACECAP_STORE.
        until: The last stage to run for every capture (e.g. poses, to check a dataset's
            cameras first).
    """

    logger = get_run_logger()
    named_store = store  # the capture runs get it as named: each worker checks it again
    store = guard(out, store, dataset=root, config=config_file(config))  # a served run: only what it may touch
    entries = scan_dataset(root)
    out_root = Path(out)
    check_dataset_output(entries, out_root)
    check_output_place(out_root, store, (root,))
    out_root.mkdir(parents=True, exist_ok=True)
    pool = _work_pool()
    if pool:
        logger.info(f"{len(entries)} captures, one {CAPTURE_DEPLOYMENT} run each on the work "
                    f"pool {pool}")
        failed, at_once = _through_deployment(entries, out_root, config, named_store, until)
        for name, message in failed.items():
            logger.error(f"{name}: {message}")
    else:
        failed, at_once = _in_process(entries, out_root, config, store, until), 1
    done = {(e.subject, e.capture): e.out_dir(out_root) for e in entries
            if e.name not in failed}
    rows = consistency_report(out_root, done)
    if rows:
        create_table_artifact(rows, key="cross-capture-consistency",
                              description="same subject, two captures: vertex-to-vertex mm")
    summary = {"dataset": Path(root).resolve().name,  # the dataset page's title
               "captures": len(entries), "done": [f"{s}/{c}" for s, c in done],
               "until": until, "failed": failed, "consistency": rows,
               "captures_at_once": at_once}
    write_results(out_root, {"dataset.json": json.dumps(summary, indent=1).encode()})

    rewrite_dataset_page(out_root)  # from what OUT holds now, dataset.json's failures too

    publish_dataset_page(out_root, store)
    if failed:
        raise FacecapError(f"{len(failed)} of {len(entries)} captures failed: "
                           + "; ".join(f"{k}: {v}" for k, v in failed.items()))
    return summary


def summary_line(summary: dict, out: str | Path) -> str:
    """What a dataset run made, in one line for the command line, and where its page is:
    ``3 of 3 captures reconstructed into OUT; their page: OUT/index.html``; captures without
    a mesh in OUT (run with ``until`` a stage before it) are said to have stopped there, not
    to be reconstructed."""
    done = len(summary["done"])
    meshes = sum((Path(out) / name / "mesh.ply").is_file() for name in summary["done"])
    page = Path(out) / "index.html"
    if meshes == done:
        made = f"{done} of {summary['captures']} captures reconstructed into {out}"
    elif summary.get("until"):
        made = (f"{done} of {summary['captures']} captures run into {out}, "
                f"{done - meshes} of them stopped after {summary['until']} with no mesh")
    else:
        made = (f"{done} of {summary['captures']} captures run into {out}, "
                f"{done - meshes} of them with no mesh in {out} (removed since)")
    return f"{made}; their page: {page}"


def _capture_parameters(entry: CaptureEntry, out_root: Path, config: ConfigParameter,
                        until: str) -> dict:
    return {"video": str(entry.video), "out": str(entry.out_dir(out_root)), "config": config,
            "scan": str(entry.scan) if entry.scan else None,
            "scan_landmarks": (str(entry.scan_landmarks)
                               if entry.scan and entry.scan_landmarks else None),
            "until": until}


def _in_process(entries: list[CaptureEntry], out_root: Path, config: ConfigParameter,
                store: str, until: str) -> dict[str, str]:
    """One capture after another as subflows of this run (the ``facecap dataset`` command,
    ``facecap serve``); returns ``{subject/capture: why it failed}``."""
    logger, failed = get_run_logger(), {}
    for entry in entries:
        try:
            reconstruct_capture(**_capture_parameters(entry, out_root, config, until),
                                store=store)
        except FacecapError as exc:
            failed[entry.name] = as_user_sees_it(str(exc), entry.video)
            # exc_info marks it as bad input: the CLI prints it once, in its summary line.
            logger.error(f"{entry.name}: {exc}", exc_info=exc)
        except FlowRunTimeoutError:  # Prefect's own limit, past the stages' own: go on
            failed[entry.name] = capture_time_limit_message(
                "the capture")
    return failed


def _work_pool() -> str | None:
    """The work pool this run's deployment runs on; None outside a deployment, or for one
    served by a process of its own (``facecap serve``), whose captures run in-process."""

    context = FlowRunContext.get()
    run = context.flow_run if context else None
    if run is None or run.deployment_id is None:
        return None

    with get_client(sync_client=True) as client:
        return client.read_deployment(run.deployment_id).work_pool_name


def _through_deployment(entries: list[CaptureEntry], out_root: Path, config: ConfigParameter,
                        store: str | None, until: str) -> tuple[dict[str, str], int]:
    """One run of the capture deployment per capture, all submitted at once: the pool's
    workers take them as the deployment's and the pool's concurrency limits allow. Waits
    for every one; returns ``{subject/capture: why it failed}`` and the most that ran at
    once."""

    if isinstance(config, PipelineConfig):
        config = config.model_dump(mode="json", exclude_unset=True)
    with get_client(sync_client=True) as client:
        try:
            deployment = client.read_deployment_by_name(CAPTURE_DEPLOYMENT)
        except ObjectNotFound:
            raise FacecapError(f"the deployment {CAPTURE_DEPLOYMENT} a dataset run submits its "
                               "captures to is not on this server; register facecap's "
                               "deployments (prefect deploy --prefect-file "
                               "deploy/prefect.yaml)") from None
    by_id = {run_deployment(deployment.id, timeout=0, tags=["facecap", "dataset"],
                            parameters={**_capture_parameters(e, out_root, config, until),
                                        "store": store}).id: e
             for e in entries}
    failed, pending, ran = {}, set(by_id), []
    with get_client(sync_client=True) as client:
        while pending:
            time.sleep(POLL_SECONDS)
            try:
                runs = client.read_flow_runs(flow_run_filter=FlowRunFilter(
                    id=FlowRunFilterId(any_=sorted(pending))))
            except httpx.HTTPError:  # the API away for a moment: the runs go on; ask again
                continue
            for run in runs:
                if run.state is None or not run.state.is_final():
                    continue
                pending.discard(run.id)
                if run.start_time and run.end_time:
                    ran.append((run.start_time, run.end_time))
                entry = by_id[run.id]
                if not run.state.is_completed():
                    failed[entry.name] = as_user_sees_it(
                        _reason(run.state), entry.video)
    return dict(sorted(failed.items())), most_at_once(ran)


def most_at_once(intervals: list[tuple]) -> int:
    """The largest number of (start, end) intervals that overlap at one moment (one that
    ends as another starts does not overlap it)."""
    events = sorted([(start, 1) for start, _ in intervals] + [(end, -1) for _, end in intervals],
                    key=lambda e: (e[0], e[1]))
    running = peak = 0
    for _, step in events:
        running += step
        peak = max(peak, running)
    return peak


def _reason(state) -> str:
    """Why a capture run ended without a result: the facecap error it raised, in its own
    words, else the state's name and message."""
    message = state.message or ""
    for cls in (InputError, FacecapError):
        marker = f"{cls.__name__}: "
        if marker in message:
            return message.split(marker, 1)[1].strip()
    return f"{state.name}: {message}".strip(": ")
