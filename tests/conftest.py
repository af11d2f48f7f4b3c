"""Shared fixtures: the ICT Face Model the tests render and fit, Prefect's test server for
flows run in the tests' process, and a live Prefect server."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from facecap_core.assets import ICT_MODEL_ENV, default_ict_model
from tests.servers import free_port, stop, wait_until_healthy


@pytest.fixture(scope="session")
def ict_model() -> Path:
    """``$FACECAP_ICT_MODEL`` when set (e.g. the full 100-mode model), else the trimmed model
    that ships in the package. Never a skip: a missing model fails the tests that need it."""
    path = default_ict_model()
    if not path.is_file():
        source = (f"${ICT_MODEL_ENV}" if os.environ.get(ICT_MODEL_ENV)
                  else "the packaged model (build it with tools/trim_ict_model.py)")
        pytest.fail(f"ICT Face Model not found at {path} ({source})", pytrace=False)
    return path


@pytest.fixture(scope="session")
def ict4_sweep(tmp_path_factory, ict_model):
    """A 3 s 640x360 sweep of ICT identity 4 (seed 4), rendered once for the session and
    only read: the pose stage's tests and the photo folder's share it."""
    from facecap.synthetic import synthesize
    from facecap.synthetic.config import SynthConfig

    config = SynthConfig(subject="ict:4", ict_model=ict_model, width=640, height=360,
                         duration_s=3.0, seed=4)
    return synthesize(config, tmp_path_factory.mktemp("ict4-sweep"), progress=False)


@pytest.fixture(scope="module")
def prefect_server() -> str:
    """Prefect's test harness (a server on a temporary database, set as this process's
    API) for the flows a module runs in the tests' process; yields its API URL. One per
    module, not per session: the harness sets the process's Prefect settings while it
    runs, and other modules run facecap with no server, or with their own."""
    from prefect.settings import PREFECT_API_URL
    from prefect.testing.utilities import prefect_test_harness

    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    with prefect_test_harness(server_startup_timeout=120):
        yield PREFECT_API_URL.value()


@pytest.fixture(scope="session")
def live_server(tmp_path_factory) -> str:
    """A real ``prefect server start`` (its scheduler, triggers and actions services running,
    as on a facecap host) with its own database; yields its API URL. One server for the
    session: each test names its own deployments, pools and automations."""
    port = free_port()
    env = {**os.environ, "PREFECT_HOME": str(tmp_path_factory.mktemp("prefect")),
           "PREFECT_SERVER_ANALYTICS_ENABLED": "false", "PREFECT_UI_ENABLED": "false",
           "PREFECT_SERVER_SERVICES_SCHEDULER_LOOP_SECONDS": "2"}
    env.pop("PREFECT_API_URL", None)
    proc = subprocess.Popen([sys.executable, "-m", "prefect", "server", "start", "--host",
                             "127.0.0.1", "--port", str(port)], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{port}/api"
    try:
        wait_until_healthy(url, proc)
        yield url
    finally:
        stop(proc, grace_s=30)


@pytest.fixture(autouse=True)
def _own_temp_folder():
    """A test that runs ``facecap`` in this process makes that test's FACECAP_HOME scratch
    folder the process's temp folder (as a command does for itself); the next test gets the
    temp folder back, rather than one inside an earlier test's files."""
    import tempfile

    saved = {name: os.environ.get(name) for name in ("TMPDIR", "GLOG_log_dir")}
    saved_tempdir = tempfile.tempdir
    yield
    for name, value in saved.items():
        if value is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = value
    tempfile.tempdir = saved_tempdir
