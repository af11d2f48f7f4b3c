"""Deployments: what ``facecap serve`` offers, and that a live server schedules the nightly
evaluation (a real ``prefect server start``, its scheduler running)."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import pytest

from facecap.deploy.serve import deployments


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
    """Each served flow's parameters are those its row of the deployments table in
    docs/deploy.md names, and the required ones are the ones it names first."""
    import re

    from facecap.flows.capture import reconstruct_capture
    from facecap.flows.dataset import reconstruct_dataset
    from facecap.flows.evaluate import evaluate_dataset

    table = (Path(__file__).parents[1] / "docs" / "deploy.md").read_text()
    for deployment, served, required in [
            ("reconstruct-capture/reconstruct-capture", reconstruct_capture, {"video", "out"}),
            ("reconstruct-dataset/reconstruct-dataset", reconstruct_dataset, {"root", "out"}),
            ("evaluate-dataset/nightly-evaluation", evaluate_dataset, {"root", "out"})]:
        (row,) = [line for line in table.splitlines() if line.startswith(f"| `{deployment}` |")]
        cell = row.split(" | ")[2]
        named = {re.match(r"\w+", name)[0] for name in re.findall(r"`([^`]+)`", cell)}
        assert set(served.parameters.properties) == named, deployment
        assert set(served.parameters.required) == required, deployment


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
