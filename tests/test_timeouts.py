"""Time limits: a stage that runs past ``FACECAP_STAGE_TIMEOUT_S`` is stopped, its task run
ends TimedOut and the capture run Failed with one line, on a real Prefect server; nothing
hangs and nothing retries it."""

from __future__ import annotations

import time

import pytest

from facecap_core.errors import FacecapError
from tests.media import write_video
from tests.test_bad_inputs import orbit_frames


@pytest.fixture
def worker_home(tmp_path, monkeypatch):
    from facecap_core import assets

    source = assets.menpo3d_data()
    (tmp_path / "home" / "assets").mkdir(parents=True)
    (tmp_path / "home" / "assets" / source.name).symlink_to(source)
    monkeypatch.setenv("FACECAP_HOME", str(tmp_path / "home"))
    monkeypatch.setenv("FACECAP_STORE", str(tmp_path / "store"))
    return tmp_path


def test_a_stage_past_its_time_limit_fails_the_run(worker_home, live_server, monkeypatch):
    from prefect.client.orchestration import get_client
    from prefect.settings import PREFECT_API_URL, temporary_settings

    from facecap.flows.capture import reconstruct_capture
    from tests.servers import final_task_runs

    video = write_video(worker_home / "orbit.mp4", orbit_frames(150))
    monkeypatch.setenv("FACECAP_STAGE_TIMEOUT_S", "0.05")  # decoding 150 frames takes longer
    start = time.perf_counter()
    with temporary_settings({PREFECT_API_URL: live_server}):
        state = reconstruct_capture(str(video), str(worker_home / "out"), until="keyframes",
                                    return_state=True)
        seconds = time.perf_counter() - start
        with pytest.raises(FacecapError) as stopped:
            state.result()
        run_id = state.state_details.flow_run_id
        with get_client(sync_client=True) as client:
            run = client.read_flow_run(run_id)
        every = final_task_runs(run_id, count=2)  # the video's ingest and the keyframes
        keyframes = [t for t in every if t.name.startswith("keyframes")]
    message = str(stopped.value)
    assert "keyframes stage" in message and "0.05 s" in message
    assert "FACECAP_STAGE_TIMEOUT_S" in message and "\n" not in message
    assert run.state.is_failed()
    # Stopped in its thread (TimedOut), or, had a handler swallowed that, failed by the
    # check after it; never retried.
    assert len(keyframes) == 1 and keyframes[0].state.name in ("TimedOut", "Completed")
    assert keyframes[0].run_count == 1
    assert seconds < 60, seconds  # the retries' delays alone would be 42 s


def test_a_capture_past_its_time_limit_is_one_line_naming_that_limit(worker_home, live_server):
    """FACECAP_CAPTURE_TIMEOUT_S, as a worker's flow run reads it (at import), stops the run
    in whichever stage it is in; the message names the capture's limit, not the stage's."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    video = write_video(worker_home / "orbit.mp4", orbit_frames(150))
    env = {**os.environ, "PREFECT_API_URL": live_server, "FACECAP_CAPTURE_TIMEOUT_S": "2"}
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "facecap", "reconstruct", str(video),
                           "--out", str(worker_home / "out"), "--until", "poses"],
                          env=env, cwd=Path(__file__).parents[1], capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 2, done.stderr[-2000:]
    [line] = [x for x in done.stderr.splitlines() if x.startswith("facecap:")]
    assert "time limit of 2 s (FACECAP_CAPTURE_TIMEOUT_S)" in line, done.stderr[-2000:]
    assert "Traceback" not in done.stderr
    assert time.perf_counter() - start < 120
