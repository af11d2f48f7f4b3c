"""A dataset on a work pool: ``deploy/prefect.yaml`` registered on a real Prefect server
(``prefect deploy``), two real ``prefect worker`` processes, and a dataset run that spreads
its captures over them within the deployment's and the pool's concurrency limits. What ran
when is read back from the server's API."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from datetime import datetime
from pathlib import Path

import pytest

from facecap.flows.dataset import most_at_once
from tests.media import write_video
from tests.servers import stop
from tests.test_bad_inputs import orbit_frames

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[1]
POOL_LIMIT = 4
"""Flow runs the pool may run at once: room for the dataset run and three captures, so that
the capture deployment's limit is what holds the captures to two."""
CAPTURE_LIMIT = 2
"""The capture deployment's concurrency limit in deploy/prefect.yaml."""
CAPTURES = [("anna", "take1"), ("anna", "take2"), ("ben", "take1")]
"""With the capture that is refused, four capture runs for a limit of two."""


def _prefect(args: list[str], env: dict) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "prefect", *args], env=env, cwd=REPO,
                          capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def pool(live_server, tmp_path_factory):
    """The pool "facecap" with facecap's deployments and two workers, each taking both
    queues and two runs at once (room for more captures than the limits allow, so that the
    limits are what bound them); yields the worker environment's folders."""
    tmp = tmp_path_factory.mktemp("pool")
    folders = {name: tmp / name for name in ("datasets", "output", "store", "home")}
    for folder in folders.values():
        folder.mkdir()
    from facecap_core import assets

    source = assets.menpo3d_data()
    (folders["home"] / "assets").mkdir()
    (folders["home"] / "assets" / source.name).symlink_to(source)
    env = {k: v for k, v in os.environ.items() if not k.startswith("FACECAP_")}
    env.update(PREFECT_API_URL=live_server, PREFECT_WORKER_QUERY_SECONDS="2",
               PREFECT_SERVER_ANALYTICS_ENABLED="false")
    for command in (["work-pool", "create", "facecap", "--type", "process"],
                    ["work-pool", "set-concurrency-limit", "facecap", str(POOL_LIMIT)]):
        done = _prefect(command, env)
        assert done.returncode == 0, done.stdout + done.stderr
    deployed = _prefect(["--no-prompt", "deploy", "--all", "--prefect-file",
                         "deploy/prefect.yaml"],
                        {**env, "FACECAP_DATASET_ROOT": str(folders["datasets"]),
                         "FACECAP_OUTPUT_ROOT": str(folders["output"]),
                         "FACECAP_NIGHTLY_TIMEZONE": "UTC"})
    assert deployed.returncode == 0, deployed.stdout + deployed.stderr
    worker_env = {**env, "FACECAP_PROJECT_DIR": str(REPO),
                  "FACECAP_INPUT_ROOTS": str(folders["datasets"]),
                  "FACECAP_OUTPUT_ROOT": str(folders["output"]),
                  "FACECAP_STORE": str(folders["store"]), "FACECAP_HOME": str(folders["home"])}
    logs = [open(tmp / f"worker{i}.log", "w") for i in range(2)]
    workers = [subprocess.Popen([sys.executable, "-m", "prefect", "worker", "start", "--pool",
                                 "facecap", "--type", "process", "--limit", "2",
                                 "--name", f"worker{i}"],
                                env=worker_env, cwd=tmp, stdout=log, stderr=subprocess.STDOUT)
               for i, log in enumerate(logs)]
    try:
        yield folders
    finally:
        for worker in workers:
            worker.terminate()
        for worker, log in zip(workers, logs):
            stop(worker, grace_s=30)
            log.close()


def _intervals(runs) -> list[tuple[datetime, datetime]]:
    return [(r.start_time, r.end_time) for r in runs if r.start_time and r.end_time]


def test_most_at_once_counts_overlaps():
    t = [datetime(2026, 1, 1, 0, m) for m in range(6)]
    assert most_at_once([(t[0], t[2]), (t[1], t[3]), (t[2], t[4])]) == 2  # touching ends
    assert most_at_once([(t[0], t[5]), (t[1], t[2]), (t[3], t[4])]) == 2
    assert most_at_once([(t[0], t[1]), (t[2], t[3])]) == 1


def test_a_dataset_spreads_its_captures_over_the_pool(pool, live_server):
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import (
        DeploymentFilter,
        DeploymentFilterName,
        FlowRunFilter,
        FlowRunFilterParentFlowRunId,
        LogFilter,
        LogFilterFlowRunId,
        WorkPoolFilter,
        WorkPoolFilterName,
    )
    from prefect.deployments import run_deployment
    from prefect.settings import PREFECT_API_URL, temporary_settings

    root = pool["datasets"] / "study"
    for i, (subject, capture) in enumerate(CAPTURES):
        (root / subject).mkdir(parents=True, exist_ok=True)
        write_video(root / subject / f"{capture}.mp4", orbit_frames(40, seed=i))
    (root / "carl").mkdir()
    write_video(root / "carl" / "short.mp4", orbit_frames(3))  # refused by its capture run
    out = pool["output"] / "study"
    start = time.perf_counter()
    with temporary_settings({PREFECT_API_URL: live_server}):
        dataset = run_deployment("reconstruct-dataset/reconstruct-dataset",
                                 parameters={"root": str(root), "out": str(out),
                                             "until": "poses"},
                                 timeout=600, poll_interval=2, as_subflow=False)
        wall = time.perf_counter() - start
        with get_client(sync_client=True) as client:
            captures = client.read_flow_runs(
                flow_run_filter=FlowRunFilter(
                    parent_flow_run_id=FlowRunFilterParentFlowRunId(any_=[dataset.id])),
                deployment_filter=DeploymentFilter(
                    name=DeploymentFilterName(any_=["reconstruct-capture"])))
            in_pool = client.read_flow_runs(work_pool_filter=WorkPoolFilter(
                name=WorkPoolFilterName(any_=["facecap"])))
    print(f"dataset of {len(CAPTURES)} captures over the pool: {wall:.0f} s wall")
    assert dataset.state.is_failed(), dataset.state  # one capture failed; the others ran
    assert sorted(r.parameters["video"] for r in captures) == sorted(
        [str(root / s / f"{c}.mp4") for s, c in CAPTURES] + [str(root / "carl" / "short.mp4")])
    assert sum(r.state.is_completed() for r in captures) == len(CAPTURES)
    summary = json.loads((out / "dataset.json").read_text())
    assert sorted(summary["done"]) == sorted(f"{s}/{c}" for s, c in CAPTURES)
    [(name, why)] = summary["failed"].items()
    assert name == "carl/short" and str(root / "carl" / "short.mp4") in why and "frames" in why
    assert most_at_once(_intervals(captures)) == CAPTURE_LIMIT  # pairs ran together
    assert summary["captures_at_once"] == CAPTURE_LIMIT
    assert most_at_once(_intervals(in_pool)) <= POOL_LIMIT
    ran_on = {r.work_queue_name for r in captures}
    assert ran_on == {"captures"}
    for subject, capture in CAPTURES:
        assert (out / subject / capture / "report.json").is_file()
    # facecap's own log lines reach the run's log from the worker's process.
    with temporary_settings({PREFECT_API_URL: live_server}):
        with get_client(sync_client=True) as client:
            first = next(r for r in captures if r.state.is_completed())
            logs = client.read_logs(log_filter=LogFilter(
                flow_run_id=LogFilterFlowRunId(any_=[first.id])))
    assert any(log.name == "facecap_core.pose.stage" and "cameras of" in log.message
               for log in logs), sorted({log.name for log in logs})


def test_an_out_of_range_setting_is_refused_before_the_run_exists(pool, live_server):
    from prefect.client.orchestration import get_client
    from prefect.deployments import run_deployment
    from prefect.exceptions import PrefectHTTPStatusError
    from prefect.settings import PREFECT_API_URL, temporary_settings

    with temporary_settings({PREFECT_API_URL: live_server}):
        with get_client(sync_client=True) as client:
            deployment = client.read_deployment_by_name("reconstruct-capture/reconstruct-capture")
            before = client.count_flow_runs()
            with pytest.raises(PrefectHTTPStatusError) as refused:
                run_deployment(deployment.id, timeout=0, as_subflow=False, parameters={
                    "video": str(pool["datasets"] / "v.mp4"), "out": str(pool["output"]),
                    "config": {"mvs": {"depth": {"iterations": 0}}}})
            assert "iterations" in str(refused.value) or "minimum" in str(refused.value)
            assert client.count_flow_runs() == before


def _config_models(model) -> dict:
    """``{name: model}`` of a config model and every model nested in its fields."""
    from pydantic import BaseModel

    found = {model.__name__: model}
    for field in model.model_fields.values():
        if isinstance(field.annotation, type) and issubclass(field.annotation, BaseModel):
            found.update(_config_models(field.annotation))
    return found


def test_the_run_form_documents_every_setting(pool, live_server):
    """The deployment's parameter schema on the server (what the UI's Run form is drawn
    from) holds every PipelineConfig field, with its docstring as the description."""
    from prefect.client.orchestration import get_client
    from prefect.settings import PREFECT_API_URL, temporary_settings

    from facecap_core.pipeline import PipelineConfig

    with temporary_settings({PREFECT_API_URL: live_server}):
        with get_client(sync_client=True) as client:
            schema = client.read_deployment_by_name(
                "reconstruct-capture/reconstruct-capture").parameter_openapi_schema
    assert schema["properties"]["config"]["description"]
    models = _config_models(PipelineConfig)
    assert len(models) >= 10
    for name, model in models.items():
        served = schema["definitions"][name]["properties"]
        assert set(served) == set(model.model_fields), name
        for field, info in model.model_fields.items():
            assert info.description and served[field]["description"] == info.description, \
                f"{name}.{field}"


def test_a_dataset_run_without_the_capture_deployment_says_so(live_server, monkeypatch,
                                                               tmp_path):
    from prefect.settings import PREFECT_API_URL, temporary_settings

    from facecap.flows import dataset
    from facecap_core.errors import FacecapError

    monkeypatch.setattr(dataset, "CAPTURE_DEPLOYMENT", "reconstruct-capture/not-registered")
    with temporary_settings({PREFECT_API_URL: live_server}):
        with pytest.raises(FacecapError) as refused:
            dataset._through_deployment([], tmp_path, None, None, "poses")
    message = str(refused.value)
    assert "reconstruct-capture/not-registered" in message and "prefect deploy" in message
