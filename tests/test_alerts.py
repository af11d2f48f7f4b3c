"""Alerts (deploy/alerts.py, ``facecap alerts``) on a live Prefect server: the webhook gets a
message when the evaluation regresses and when a facecap run fails, and setting them up
again changes nothing but their contents."""

from __future__ import annotations

import json
import re
import subprocess
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest
import yaml

from facecap.cli import main
from facecap.deploy import alerts
from facecap_core.errors import InputError

ROOT = Path(__file__).resolve().parents[1]


class Webhook:
    """An HTTP endpoint on 127.0.0.1 that keeps the text of every JSON POST it receives."""

    def __init__(self) -> None:
        self.texts: list[str] = []
        received = self.texts

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:
                body = self.rfile.read(int(self.headers.get("Content-Length", 0)))
                received.append(json.loads(body)["text"])
                self.send_response(200)
                self.end_headers()

            def log_message(self, *args) -> None:  # keep the test output clean
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/hook"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def wait_for(self, *words: str, timeout: float = 60) -> str:
        """The first message naming all of ``words``, waiting up to ``timeout`` s for it."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for text in list(self.texts):
                if all(word in text for word in words):
                    return text
            time.sleep(0.5)
        raise AssertionError(f"no message naming {words} in {timeout:g} s; got {self.texts}")


@pytest.fixture(scope="module")
def webhook():
    hook = Webhook()
    yield hook
    hook.server.shutdown()


@pytest.fixture(scope="module")
def on_server(live_server):
    """PREFECT_API_URL pointed at the live server for the module's tests."""
    from prefect.events.worker import EventsWorker
    from prefect.settings import PREFECT_API_URL, temporary_settings

    EventsWorker.drain_all()  # an events worker of an earlier test may hold another server
    with temporary_settings({PREFECT_API_URL: live_server}):
        yield live_server
        EventsWorker.drain_all()
    _remove_alerts(live_server)


def _remove_alerts(api: str) -> None:
    """The live server outlives this module: leave no automation posting to a closed port,
    nor this module's blocks."""
    from prefect.client.orchestration import get_client
    from prefect.settings import PREFECT_API_URL, temporary_settings

    with temporary_settings({PREFECT_API_URL: api}), get_client(sync_client=True) as client:
        for name in (alerts.REGRESSED, alerts.RUN_FAILED):
            for automation in client.read_automations_by_name(name):
                client.delete_automation(automation.id)
        for block in client.read_block_documents():
            if block.name == alerts.BLOCK_NAME or block.name.startswith("alerts-test-"):
                client.delete_block_document(block.id)


@pytest.fixture(scope="module")
def alerts_set_up(on_server, webhook):
    """The alerts, through the CLI, pointed at the local endpoint."""
    assert main(["alerts", "--webhook", webhook.url]) == 0
    # The triggers service reloads its automations on its periodic pass (every 5 s): an event
    # that arrives before then meets no automation.
    time.sleep(6)
    return webhook


def emit_regression(dataset: str, regressions: list[dict]) -> None:
    """As flows/evaluate.py does: from inside the evaluation's flow run."""
    from prefect import flow
    from prefect.events import emit_event
    from prefect.events.worker import EventsWorker

    @flow(name="alerts-test-evaluation", flow_run_name=f"dataset {dataset}")
    def evaluation() -> None:
        emit_event(event="facecap.evaluation.regressed",
                   resource={"prefect.resource.id": f"facecap.dataset.{dataset}"},
                   payload={"regressions": regressions})

    evaluation()
    EventsWorker.drain_all()  # sent now, not when the process exits


def fail_a_run(flow_name: str, run_name: str, message: str) -> None:
    from prefect import flow

    @flow(name=flow_name, flow_run_name=run_name, retries=0)
    def broken() -> None:
        raise InputError(message)

    state = broken(return_state=True)
    assert state.is_failed()


@pytest.mark.slow  # a live server: ~30 s to start on 2 cores
def test_a_regression_reaches_the_webhook_naming_dataset_and_figures(alerts_set_up):
    emit_regression("nightly-set", [
        {"capture": "ict3/take1", "measure": "accuracy median", "previous_mm": 0.262,
         "now_mm": 0.413},
        {"capture": "ict4/take1", "measure": "completion median", "previous_mm": 0.5,
         "now_mm": 0.71},
        {"capture": "ict5/take1", "measure": "mesh missing", "previous_mm": 0.3,
         "now_mm": None}])
    text = alerts_set_up.wait_for("nightly-set")
    assert "accuracy regressed" in text
    assert "3 regression(s)" in text
    assert "ict5/take1: mesh missing (accuracy median was 0.3 mm)" in text
    assert "ict3/take1: accuracy median 0.262 mm -> 0.413 mm" in text
    assert "ict4/take1: completion median 0.5 mm -> 0.71 mm" in text
    assert "Run: dataset nightly-set" in text  # the evaluation's flow run


@pytest.mark.slow  # a live server: ~30 s to start on 2 cores
def test_a_failed_facecap_run_reaches_the_webhook_and_another_flow_does_not(alerts_set_up):
    fail_a_run("someone-elses-flow", "other/run", "not facecap's")
    fail_a_run("reconstruct-capture", "alerts-test/broken", "the test capture is unreadable")
    text = alerts_set_up.wait_for("alerts-test/broken")
    assert "reconstruct-capture" in text
    assert "Failed" in text
    assert "the test capture is unreadable" in text
    time.sleep(2)  # the other run failed first: its message would have come by now
    assert not any("other/run" in t for t in alerts_set_up.texts)


@pytest.mark.slow  # a live server: ~30 s to start on 2 cores
def test_setting_up_again_updates_in_place(alerts_set_up, capsys):
    from prefect.client.orchestration import get_client

    with get_client(sync_client=True) as client:
        [failed] = client.read_automations_by_name(alerts.RUN_FAILED)
        client.pause_automation(failed.id)  # the operator paused it in the UI
        [regressed] = client.read_automations_by_name(alerts.REGRESSED)
        block_id = regressed.actions[0].block_document_id
        alerts.regressed_automation(block_id).create()  # a duplicate, made by hand

    capsys.readouterr()
    assert main(["alerts", "--webhook", alerts_set_up.url + "?again=1"]) == 0
    printed = capsys.readouterr().out
    assert "'facecap: accuracy regressed': updated, 1 duplicate(s) removed" in printed

    with get_client(sync_client=True) as client:
        assert len(client.read_automations_by_name(alerts.REGRESSED)) == 1
        [failed_again] = client.read_automations_by_name(alerts.RUN_FAILED)
        assert failed_again.id == failed.id and not failed_again.enabled  # still paused
        assert failed_again.trigger.expect == {"prefect.flow-run.Failed",
                                               "prefect.flow-run.Crashed",
                                               "prefect.flow-run.TimedOut"}
        blocks = [b for b in client.read_block_documents_by_type("custom-webhook")
                  if b.name == alerts.BLOCK_NAME]
        assert len(blocks) == 1
        assert blocks[0].data["secrets"]["webhook_url"].endswith("?again=1")


@pytest.mark.slow  # a live server: ~30 s to start on 2 cores
def test_the_alerts_can_go_through_a_block_made_in_the_ui(alerts_set_up, capsys):
    from prefect.blocks.notifications import CustomWebhookNotificationBlock
    from prefect.blocks.system import Secret
    from prefect.client.orchestration import get_client

    own = CustomWebhookNotificationBlock(name="ops", url=alerts_set_up.url,
                                         json_data={"text": "ops: {{subject}}"})
    own_id = own.save("alerts-test-ops", overwrite=True)
    Secret(value="x").save("alerts-test-secret", overwrite=True)
    for block, says in (("custom-webhook/alerts-test-none", "no block custom-webhook/alerts-test-none"),
                        ("secret/alerts-test-secret", "cannot send notifications")):
        assert main(["alerts", "--block", block]) == 2
        assert says in capsys.readouterr().err

    assert main(["alerts", "--block", "custom-webhook/alerts-test-ops"]) == 0
    with get_client(sync_client=True) as client:
        for name in (alerts.REGRESSED, alerts.RUN_FAILED):
            [automation] = client.read_automations_by_name(name)
            assert automation.actions[0].block_document_id == own_id


def test_bad_operator_input_is_one_line_and_exit_code_2(capsys, monkeypatch):
    from prefect.settings import PREFECT_API_URL, temporary_settings

    monkeypatch.delenv(alerts.WEBHOOK_ENV, raising=False)
    with temporary_settings({PREFECT_API_URL: "http://127.0.0.1:9/api"}):
        for argv, says in ((["alerts"], "no alert webhook"),
                           (["alerts", "--webhook", "ftp://x"], "not an http(s) URL"),
                           (["alerts", "--webhook", "http://hooks.example/x"], "does not answer"),
                           (["alerts", "--block", "no-slash"], "TYPE/NAME")):
            assert main(argv) == 2, argv
            err = capsys.readouterr().err
            assert err.count("\n") == 1 and says in err, (argv, err)
    with temporary_settings(restore_defaults={PREFECT_API_URL}):
        assert main(["alerts", "--webhook", "http://hooks.example/x"]) == 2
        assert "PREFECT_API_URL is not set" in capsys.readouterr().err


def run_registration_job(tmp_path: Path, webhook: str, deploy_status: int = 0):
    """The compose `deployments` job's command, run by sh with stand-ins for `prefect` and
    `facecap` that log their arguments; returns (exit code, the log, stdout)."""
    raw = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    job = raw["services"]["deployments"]
    assert job["command"][:2] == ["sh", "-c"]
    command = job["command"][2].replace("$$", "$")  # as Compose hands it to the shell
    log = tmp_path / "calls.log"
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir(exist_ok=True)
    for name, status in (("prefect", f'case "$*" in *deploy*) exit {deploy_status};; esac'),
                         ("facecap", "")):
        stub = bin_dir / name
        stub.write_text(f'#!/bin/sh\necho "{name} $*" >> "{log}"\n{status}\n')
        stub.chmod(0o755)
    env = {"PATH": f"{bin_dir}:/usr/bin:/bin", "FACECAP_ALERT_WEBHOOK": webhook}
    done = subprocess.run(["sh", "-c", command], env=env, capture_output=True, text=True,
                          timeout=30)
    calls = log.read_text() if log.exists() else ""
    log.unlink(missing_ok=True)
    return done.returncode, calls, done.stdout


def test_the_compose_registration_sets_up_the_alerts_when_a_webhook_is_set(tmp_path):
    environment = yaml.safe_load((ROOT / "docker-compose.yml").read_text())[
        "services"]["deployments"]["environment"]
    assert environment[alerts.WEBHOOK_ENV] == "${FACECAP_ALERT_WEBHOOK:-}"
    assert re.search(rf"^{alerts.WEBHOOK_ENV}=$", (ROOT / ".env.example").read_text(), re.M)

    status, calls, _ = run_registration_job(tmp_path, "https://hooks.example/x")
    assert status == 0 and calls.splitlines()[-1] == "facecap alerts"
    assert "deploy --all --prefect-file deploy/prefect.yaml" in calls
    status, calls, out = run_registration_job(tmp_path, "")
    assert status == 0 and "facecap alerts" not in calls and "no alerts" in out
    status, calls, _ = run_registration_job(tmp_path, "https://hooks.example/x", deploy_status=1)
    assert status == 1 and "facecap alerts" not in calls  # a failed registration stops the job
