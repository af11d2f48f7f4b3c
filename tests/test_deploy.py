"""Deployments: what ``facecap serve`` offers, and that a live server schedules the nightly
evaluation (a real ``prefect server start``, its scheduler running)."""

from __future__ import annotations

import asyncio
import os
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

from deploy.serve import deployments


def test_deployments_name_their_flows_and_parameters():
    by_name = {d.name: d for d in deployments("/data/root", "/data/out", "30 3 * * *",
                                              "Europe/Berlin")}
    assert set(by_name) == {"reconstruct-capture", "reconstruct-dataset", "nightly-evaluation"}
    assert by_name["reconstruct-dataset"].entrypoint == "flows/dataset.py:reconstruct_dataset"
    assert by_name["reconstruct-capture"].entrypoint == "flows/capture.py:reconstruct_capture"
    night = by_name["nightly-evaluation"]
    assert night.entrypoint == "flows/evaluate.py:evaluate_dataset"
    assert night.parameters == {"root": "/data/root", "out": "/data/out"}
    [schedule] = night.schedules
    assert schedule.schedule.cron == "30 3 * * *"
    assert schedule.schedule.timezone == "Europe/Berlin"
    assert not by_name["reconstruct-dataset"].schedules


def test_served_flows_accept_only_documented_parameters():
    from flows.dataset import reconstruct_dataset

    schema = reconstruct_dataset.parameters
    assert set(schema.properties) == {"root", "out", "config", "store"}
    assert set(schema.required) == {"root", "out"}
    from flows.capture import reconstruct_capture

    schema = reconstruct_capture.parameters
    assert set(schema.properties) == {"video", "out", "config", "scan", "scan_landmarks", "until",
                                      "store", "progress", "ipd_mm"}
    assert set(schema.required) == {"video", "out"}
    documented = (Path(__file__).parents[1] / "docs" / "deploy.md").read_text()
    assert "`ipd_mm`" in documented


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def live_server(tmp_path_factory):
    port = _free_port()
    env = {**os.environ, "PREFECT_HOME": str(tmp_path_factory.mktemp("prefect")),
           "PREFECT_SERVER_ANALYTICS_ENABLED": "false", "PREFECT_UI_ENABLED": "false",
           "PREFECT_SERVER_SERVICES_SCHEDULER_LOOP_SECONDS": "2"}
    proc = subprocess.Popen([sys.executable, "-m", "prefect", "server", "start", "--host",
                             "127.0.0.1", "--port", str(port)], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{port}/api"
    try:
        for _ in range(240):
            try:
                urllib.request.urlopen(f"{url}/health", timeout=1)
                break
            except OSError:
                if proc.poll() is not None:
                    pytest.fail("prefect server exited at start")
                time.sleep(0.5)
        else:
            pytest.fail("prefect server did not become healthy in 120 s")
        yield url
    finally:
        proc.terminate()
        proc.wait(30)


@pytest.mark.slow
def test_nightly_evaluation_gets_scheduled_runs(live_server):
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import DeploymentFilter, DeploymentFilterId
    from prefect.settings import PREFECT_API_URL, temporary_settings

    with temporary_settings({PREFECT_API_URL: live_server}):
        deployment_id = deployments("/data/root", "/data/out", timezone="Europe/Berlin")[2].apply()

        async def scheduled():
            async with get_client() as client:
                return await client.read_flow_runs(deployment_filter=DeploymentFilter(
                    id=DeploymentFilterId(any_=[deployment_id])))

        runs = []
        for _ in range(60):
            runs = asyncio.run(scheduled())
            if runs:
                break
            time.sleep(1)
    assert runs, "the scheduler made no run for the nightly deployment"
    assert all(r.state.name == "Scheduled" for r in runs)
    from zoneinfo import ZoneInfo

    for run in runs:
        local = run.expected_start_time.astimezone(ZoneInfo("Europe/Berlin"))
        assert (local.hour, local.minute) == (2, 0)
        assert run.parameters == {"root": "/data/root", "out": "/data/out"}
