"""Real Prefect servers and workers in the tests: a free port, waiting for a server to
answer, and stopping a process that may not stop on its own."""

from __future__ import annotations

import socket
import subprocess
import time
from pathlib import Path

import httpx
import pytest


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def wait_until_healthy(api: str, server: subprocess.Popen, log: Path | None = None,
                       seconds: float = 120) -> None:
    """Return once the server at ``api`` answers ``/health``; fail the test if it exits or
    does not answer in ``seconds`` (with the end of its ``log``, if it keeps one)."""
    deadline = time.monotonic() + seconds
    while True:
        try:
            if httpx.get(f"{api}/health", timeout=2).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        if server.poll() is not None or time.monotonic() > deadline:
            tail = log.read_text()[-2000:] if log else ""
            pytest.fail(f"Prefect server did not start: {tail}")
        time.sleep(0.5)


def stop(process: subprocess.Popen, grace_s: float = 15) -> None:
    """SIGTERM, then SIGKILL if the process has not ended after ``grace_s`` seconds (a
    worker may still be winding down its runs' processes)."""
    if process.poll() is None:
        process.terminate()
        try:
            process.wait(timeout=grace_s)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(timeout=grace_s)


def final_task_runs(flow_run_id, count: int, seconds: float = 60) -> list:
    """The task runs of a flow run on the current Prefect server, once there are ``count``
    and each has a final state (or as they are after ``seconds``). The server records task
    runs from their events, which may land after the flow has returned: read right away, a
    task run can still be missing, stateless or Running."""
    import asyncio

    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import FlowRunFilter, FlowRunFilterId

    async def read() -> list:
        async with get_client() as client:
            return await client.read_task_runs(flow_run_filter=FlowRunFilter(
                id=FlowRunFilterId(any_=[flow_run_id])))

    deadline = time.monotonic() + seconds
    while True:
        runs = asyncio.run(read())
        if (len(runs) >= count and all(run.state and run.state.is_final() for run in runs)
                or time.monotonic() > deadline):
            return runs
        time.sleep(0.5)
