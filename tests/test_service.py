"""The shared service's bounds: what a served run may read, write and reach
(``flows/service.py``), and the largest capture any run accepts (``FACECAP_MAX_*``).

Served runs are tested through the flow functions in a process whose environment sets the
worker's limits (``FACECAP_INPUT_ROOTS``, ``FACECAP_OUTPUT_ROOT``, ``FACECAP_STORE``), as a
worker's does; the local ``facecap`` command in the same environment is not limited.
"""

from __future__ import annotations

import http.server
import os
import threading
from pathlib import Path

import pytest

from facecap_core.errors import InputError
from tests.media import write_video
from tests.test_bad_inputs import assert_one_line_error, facecap, orbit_frames


@pytest.fixture(scope="module")
def videos(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("videos")
    frames = orbit_frames(40)
    return {"orbit": write_video(d / "orbit.mp4", frames),
            "short": write_video(d / "short.mp4", frames[:3])}


@pytest.fixture
def worker(tmp_path, monkeypatch, videos) -> dict[str, Path]:
    """A worker's environment: inputs under ``inputs``, results under ``outputs``, one
    store; a 3-frame video inside the inputs (refused by the preflight, after the guard),
    and a secret outside them."""
    from facecap_core import assets

    home = tmp_path / "home"
    source = assets.menpo3d_data()
    (home / "assets").mkdir(parents=True)
    (home / "assets" / source.name).symlink_to(source)
    roots = {name: tmp_path / name for name in ("inputs", "outputs", "store", "elsewhere")}
    for folder in roots.values():
        folder.mkdir()
    (roots["inputs"] / "anna").mkdir()
    (roots["inputs"] / "anna" / "take.mp4").write_bytes(videos["short"].read_bytes())
    (roots["elsewhere"] / "secret.mp4").write_bytes(videos["orbit"].read_bytes())
    (roots["inputs"] / "anna" / "link.mp4").symlink_to(roots["elsewhere"] / "secret.mp4")
    monkeypatch.setenv("FACECAP_HOME", str(home))
    monkeypatch.setenv("FACECAP_INPUT_ROOTS", f"{tmp_path / 'nothing here'}:{roots['inputs']}")
    monkeypatch.setenv("FACECAP_OUTPUT_ROOT", str(roots["outputs"]))
    monkeypatch.setenv("FACECAP_STORE", str(roots["store"]))
    return roots


def _refused(flow, words: list[str], **parameters) -> str:
    with pytest.raises(InputError) as refused:
        flow(**parameters)
    message = str(refused.value)
    for word in words:
        assert word in message, (word, message)
    return message


@pytest.fixture
def listener():
    """An HTTP server that records every request it gets (a stand-in for an internal API a
    store URL could point a worker at)."""
    requests = []

    class Recorder(http.server.BaseHTTPRequestHandler):
        def do_GET(self):  # noqa: N802 - the name http.server calls
            requests.append(self.path)
            self.send_response(200)
            self.end_headers()

        do_HEAD = do_GET  # noqa: N815

        def log_message(self, *args):
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Recorder)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{server.server_address[1]}", requests
    server.shutdown()


def test_a_served_capture_reads_only_inside_the_input_roots(worker, prefect_server):
    from facecap.flows.capture import reconstruct_capture

    out = str(worker["outputs"] / "anna")
    secret = worker["elsewhere"] / "secret.mp4"
    outside = "outside the folders this service reads from"
    _refused(reconstruct_capture, [f"the video {secret}", outside], video=str(secret), out=out)
    _refused(reconstruct_capture, [outside], video="/etc/passwd", out=out)
    _refused(reconstruct_capture, ["link.mp4", outside],  # a link inside, to a file outside
             video=str(worker["inputs"] / "anna" / "link.mp4"), out=out)
    _refused(reconstruct_capture, [outside],  # '..' out of a root
             video=str(worker["inputs"] / ".." / "elsewhere" / "secret.mp4"), out=out)
    photos = worker["inputs"] / "anna" / "photos"  # a photo folder with a linked photo
    photos.mkdir()
    (worker["elsewhere"] / "face.jpg").write_bytes(b"a photo outside the roots")
    (photos / "face.jpg").symlink_to(worker["elsewhere"] / "face.jpg")
    _refused(reconstruct_capture, ["the photo", "face.jpg", outside], video=str(photos),
             out=out)
    take = str(worker["inputs"] / "anna" / "take.mp4")
    for parameter in ("config", "scan", "scan_landmarks"):
        _refused(reconstruct_capture, [f"the {parameter.replace('_', ' ')} /etc/hostname",
                                       outside],
                 video=take, out=out, **{parameter: "/etc/hostname"})
    # Inside the roots the run gets past the guard, to the preflight's own checks.
    _refused(reconstruct_capture, ["take.mp4 has 3 frames"], video=take, out=out)
    assert not any(worker["store"].iterdir())


def test_a_served_capture_writes_only_inside_the_output_root(worker, prefect_server):
    from facecap.flows.capture import reconstruct_capture

    take = str(worker["inputs"] / "anna" / "take.mp4")
    (worker["outputs"] / "escape").symlink_to(worker["elsewhere"], target_is_directory=True)
    for out in ("/tmp/facecap-anywhere", worker["outputs"] / ".." / "elsewhere",
                worker["outputs"] / "escape" / "anna", worker["inputs"] / "anna"):
        _refused(reconstruct_capture, ["outside the folder this service writes to"],
                 video=take, out=str(out))
    assert not Path("/tmp/facecap-anywhere").exists()
    assert sorted(p.name for p in worker["elsewhere"].iterdir()) == ["secret.mp4"]


def test_a_served_run_uses_the_deployments_store_only(worker, prefect_server, listener):
    """No store URL but the worker's own: another scheme (an HTTP request to an internal
    API), another bucket, another folder. The listener gets no request."""
    from facecap.flows.capture import reconstruct_capture

    url, requests = listener
    take = str(worker["inputs"] / "anna" / "take.mp4")
    out = str(worker["outputs"] / "anna")
    for store in (f"{url}/internal/api", "s3://someone-elses-bucket/x", str(worker["elsewhere"]),
                  f"simplecache::{url}/x"):
        _refused(reconstruct_capture, ["keeps its artifacts in its own store",
                                       "leave 'store' empty"], video=take, out=out, store=store)
    assert requests == []
    # Its own store, named again, is accepted (the run goes on to the preflight).
    _refused(reconstruct_capture, ["has 3 frames"], video=take, out=out,
             store=str(worker["store"]))


def test_served_dataset_and_evaluation_runs_are_bounded_too(worker, prefect_server):
    from facecap.flows.dataset import reconstruct_dataset
    from facecap.flows.evaluate import evaluate_dataset

    out = str(worker["outputs"] / "results")
    for flow in (reconstruct_dataset, evaluate_dataset):
        _refused(flow, [f"the dataset {worker['elsewhere']}", "outside the folders"],
                 root=str(worker["elsewhere"]), out=out)
        _refused(flow, ["outside the folder this service writes to"],
                 root=str(worker["inputs"]), out=str(worker["elsewhere"]))
    _refused(reconstruct_dataset, ["the config /etc/hostname", "outside the folders"],
             root=str(worker["inputs"]), out=out, config="/etc/hostname")
    _refused(evaluate_dataset, ["keeps its artifacts in its own store"],
             root=str(worker["inputs"]), out=out, store="memory://elsewhere")


def test_a_served_run_refuses_a_path_it_cannot_compare(worker, prefect_server):
    """A NUL byte (no file name holds one) or a path given as bytes: one line, not the
    ValueError or TypeError of resolving it."""
    from facecap.flows.capture import reconstruct_capture
    from facecap.flows.service import guard

    out = str(worker["outputs"] / "anna")
    take = str(worker["inputs"] / "anna" / "take.mp4")
    _refused(reconstruct_capture, [f"the video path {take + chr(0) + '.txt'!r} holds a NUL "
                                   "byte; give the path without it"],
             video=take + "\0.txt", out=out)
    _refused(guard, [f"the output folder path {out + chr(0)!r} holds a NUL byte"],
             out=out + "\0", store=None, video=take)
    _refused(guard, [f"the video {os.fsencode(take)!r} is bytes, not a path; give the path "
                     "as text"], out=out, store=None, video=os.fsencode(take))
    assert not any(worker["store"].iterdir())


def test_a_served_run_reads_a_tilde_as_the_flow_does(worker, prefect_server, monkeypatch,
                                                     videos):
    """``~`` is not expanded when a served run opens its video, so the guard does not expand
    it either: ``~/anna/take.mp4`` is the folder ``~`` of the worker's working directory,
    here outside the roots (though ``$HOME/anna/take.mp4`` lies inside them)."""
    from facecap.flows.capture import reconstruct_capture

    monkeypatch.setenv("HOME", str(worker["inputs"]))
    monkeypatch.chdir(worker["elsewhere"])
    (worker["elsewhere"] / "~" / "anna").mkdir(parents=True)
    (worker["elsewhere"] / "~" / "anna" / "take.mp4").write_bytes(videos["short"].read_bytes())
    _refused(reconstruct_capture, ["the video ~/anna/take.mp4 is outside the folders this "
                                   "service reads from"],
             video="~/anna/take.mp4", out=str(worker["outputs"] / "anna"))


def test_a_served_run_refuses_a_hard_link_out_of_the_roots(worker, prefect_server, videos):
    """A hard link is the file itself, wherever its other names are: an input with more
    than one (a video, a config, each photo of a photo folder) is refused; a copy is not."""
    from facecap.flows.capture import reconstruct_capture

    out = str(worker["outputs"] / "anna")
    secret = worker["elsewhere"] / "short.mp4"
    secret.write_bytes(videos["short"].read_bytes())
    linked = worker["inputs"] / "anna" / "linked.mp4"
    os.link(secret, linked)
    _refused(reconstruct_capture, [f"the video {linked} has other hard links; copy it into "
                                   "the input folder instead"], video=str(linked), out=out)
    (worker["elsewhere"] / "pipeline.yaml").write_text("{}\n")
    os.link(worker["elsewhere"] / "pipeline.yaml", worker["inputs"] / "pipeline.yaml")
    _refused(reconstruct_capture, ["the config", "has other hard links"], out=out,
             video=str(worker["inputs"] / "anna" / "take.mp4"),
             config=str(worker["inputs"] / "pipeline.yaml"))
    photos = worker["inputs"] / "anna" / "photos"
    photos.mkdir()
    (photos / "a.jpg").write_bytes(b"a photo of its own")
    (worker["elsewhere"] / "face.jpg").write_bytes(b"a photo outside the roots")
    os.link(worker["elsewhere"] / "face.jpg", photos / "b.jpg")
    _refused(reconstruct_capture, [f"the photo {photos / 'b.jpg'} has other hard links"],
             video=str(photos), out=out)
    assert not any(worker["store"].iterdir())


def test_a_refused_store_url_is_shown_without_its_password(worker):
    from facecap.flows.service import ServicePolicy

    message = _refused(ServicePolicy.from_env().check_store, ["s3://user:***@host/bucket"],
                       store="s3://user:secret@host/bucket")
    assert "secret" not in message


def test_a_deployment_without_roots_reads_and_writes_nothing(monkeypatch, tmp_path):
    """The worker's settings unset: a served run's policy admits no path at all."""
    from facecap.flows.service import ServicePolicy

    monkeypatch.delenv("FACECAP_INPUT_ROOTS", raising=False)
    monkeypatch.delenv("FACECAP_OUTPUT_ROOT", raising=False)
    policy = ServicePolicy.from_env()
    with pytest.raises(InputError, match="FACECAP_INPUT_ROOTS is unset"):
        policy.input(tmp_path / "video.mp4", "video")
    with pytest.raises(InputError, match="FACECAP_OUTPUT_ROOT is unset"):
        policy.output(tmp_path / "out")


def test_the_local_command_is_not_bounded(worker, capfd):
    """The same environment, the ``facecap`` command on one's own machine: a video, an
    output folder and a store anywhere are the user's to name (the 3-frame video is then
    refused for what it is)."""
    short = worker["elsewhere"] / "short.mp4"
    short.write_bytes((worker["inputs"] / "anna" / "take.mp4").read_bytes())
    code, _, err = facecap(capfd, "reconstruct", short, "--out", worker["elsewhere"] / "out",
                           "--store", worker["elsewhere"] / "store")
    assert_one_line_error(code, err, ["short.mp4 has 3 frames"])


# --------------------------------------------------------------------------- input limits


LIMITS = {
    # environment: (value, words of the message)
    "FACECAP_MAX_FILE_MB": ("0.01", ["orbit.mp4 is 0.8 MiB, more than the limit of 0.01 MiB",
                                     "cut it"]),
    "FACECAP_MAX_DURATION_S": ("0.5", ["orbit.mp4 lasts 1 s, longer than the limit of 0.5 s"]),
    "FACECAP_MAX_FRAMES": ("20", ["orbit.mp4 has 40 frames, more than the limit of 20"]),
    "FACECAP_MAX_SIDE_PX": ("200", ["224x128 pixels, larger than the limit of 200"]),
}


@pytest.mark.parametrize("variable", sorted(LIMITS))
def test_input_limits_are_checked_before_any_compute(variable, videos, tmp_path, monkeypatch,
                                                     capfd):
    """Each limit, set in the environment, refuses the 40-frame 224x128 video in the
    preflight: one line, nothing stored, nothing written."""
    value, words = LIMITS[variable]
    monkeypatch.setenv(variable, value)
    store, out = tmp_path / "store", tmp_path / "out"
    code, _, err = facecap(capfd, "reconstruct", videos["orbit"], "--out", out, "--store", store)
    assert_one_line_error(code, err, words)
    assert not store.exists() and not out.exists()


def test_input_limits_are_validated(videos, tmp_path, monkeypatch, capfd):
    monkeypatch.setenv("FACECAP_MAX_FRAMES", "many")
    code, _, err = facecap(capfd, "reconstruct", videos["orbit"], "--out", tmp_path / "out")
    assert_one_line_error(code, err, ["invalid FACECAP_MAX_FRAMES='many'", "valid integer"])
