"""The output folder: results land by rename, never through a link, never onto an input or
into the store (:mod:`tasks.outputs`); and what a run leaves outside it.

Each case of the careless-user and attacker list in docs/robustness.md ("Outputs") is a
test here: first at the writer, then through the ``facecap`` command as a user types it.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from facecap.flows.local_server import database_problem
from facecap.tasks.outputs import (
    RECORD_NAME,
    OutputWriteError,
    ResultWriter,
    check_output_place,
    write_results,
)
from facecap_core.errors import InputError
from tests import test_bad_inputs
from tests.media import write_video
from tests.test_bad_inputs import (
    CHEAP_POSES,
    assert_kept,
    assert_one_line_error,
    facecap,
    orbit_frames,
    snapshot,
)

# The bad-input corpus's fixtures: its media, a FACECAP_HOME, kept results (the test server
# is conftest's).
media, home, kept = test_bad_inputs.media, test_bad_inputs.home, test_bad_inputs.kept


def _tree(folder: Path) -> dict[str, str]:
    """Every file and link under ``folder`` (links by target, files by sha256)."""
    found = {}
    for path in sorted(folder.rglob("*")):
        if path.is_symlink():
            found[str(path)] = "-> " + os.readlink(path)
        elif path.is_file():
            found[str(path)] = hashlib.sha256(path.read_bytes()).hexdigest()
    return found


# --------------------------------------------------------------------------- the writer


def _planted_links(elsewhere: Path, out: Path) -> tuple[Path, Path]:
    """``out/report.json`` and ``out/.cameras.json.part`` (the name the export once wrote
    first) planted as links to files in ``elsewhere``."""
    elsewhere.mkdir()
    out.mkdir()
    (elsewhere / "victim").write_bytes(b"precious")
    (elsewhere / "v2").write_bytes(b"also precious")
    (out / "report.json").symlink_to(elsewhere / "victim")
    (out / ".cameras.json.part").symlink_to(elsewhere / "v2")
    return elsewhere, out


def test_a_link_in_the_output_folder_is_replaced_not_followed(tmp_path):
    """Case 1: ``out/report.json`` and ``out/.cameras.json.part`` are links to files
    elsewhere; the results land in ``out`` and the files elsewhere keep their bytes."""
    elsewhere, out = _planted_links(tmp_path / "elsewhere", tmp_path / "out")
    before = _tree(elsewhere)
    write_results(out, {"report.json": b"{}", "cameras.json": b"[]"})
    assert _tree(elsewhere) == before
    assert not (out / "report.json").is_symlink()
    assert (out / "report.json").read_bytes() == b"{}"
    assert (out / "cameras.json").read_bytes() == b"[]"


def test_a_linked_sub_folder_is_refused(tmp_path):
    """``out/colmap`` a link to a folder elsewhere: nothing is written into it."""
    elsewhere, out = tmp_path / "elsewhere", tmp_path / "out"
    elsewhere.mkdir()
    out.mkdir()
    (out / "colmap").symlink_to(elsewhere, target_is_directory=True)
    with pytest.raises(InputError, match="colmap is a link or a file"):
        write_results(out, {"report.json": b"{}", "colmap/cameras.txt": b"# cameras"})
    assert list(elsewhere.iterdir()) == []
    assert not (out / "report.json").exists()  # the batch is all or nothing


def test_a_result_never_replaces_an_input(tmp_path):
    """Case 3 at the writer: an input file (here a photo named ``preview.png``, and a hard
    link to the scan) is never replaced."""
    photos = tmp_path / "photos"
    photos.mkdir()
    cv2.imwrite(str(photos / "preview.png"), np.full((8, 8, 3), 200, np.uint8))
    scan = tmp_path / "scan.ply"
    scan.write_bytes(b"ply scan")
    out = tmp_path / "out"
    out.mkdir()
    os.link(scan, out / "mesh.ply")
    before = _tree(tmp_path)
    with pytest.raises(InputError, match="would replace the input"):
        write_results(photos, {"preview.png": b"png"}, inputs=(photos,))
    with pytest.raises(InputError, match="would replace the input .*scan.ply"):
        write_results(out, {"mesh.ply": b"ply mesh"}, inputs=(scan,))
    assert _tree(tmp_path) == before


def test_only_what_facecap_wrote_is_removed(tmp_path):
    """Results of an earlier run that this run did not make go; a file of the user's own
    with a result's name, or one changed since facecap wrote it, stays."""
    out = tmp_path / "out"
    write_results(out, {"heatmap_metric.png": b"earlier", "heatmap_similarity.png": b"earlier",
                        "evaluation.json": b"earlier"})
    (out / "heatmap_similarity.png").write_bytes(b"edited by the user")
    (out / "preview.png").write_bytes(b"the user's own")
    with ResultWriter(out) as writer:
        writer.add("mesh.ply", b"mesh")
        writer.commit(stale={"heatmap_metric.png", "heatmap_similarity.png", "preview.png"})
    names = sorted(p.name for p in out.iterdir())
    assert names == [RECORD_NAME, "evaluation.json", "heatmap_similarity.png", "mesh.ply",
                     "preview.png"]
    assert set(json.loads((out / RECORD_NAME).read_text())) == {"evaluation.json", "mesh.ply"}


def test_a_folder_without_a_record_loses_its_stale_plain_files_only(tmp_path):
    """Results an earlier version wrote (no record): a stale result goes as it did then,
    but not a link of that name, nor an input."""
    out, scan = tmp_path / "out", tmp_path / "scan.ply"
    out.mkdir()
    scan.write_bytes(b"scan")
    (out / "heatmap_metric.png").write_bytes(b"an earlier version's")
    (out / "heatmap_similarity.png").symlink_to(scan)
    os.link(scan, out / "evaluation.json")
    with ResultWriter(out, inputs=(scan,)) as writer:
        writer.add("mesh.ply", b"mesh")
        writer.commit(stale={"heatmap_metric.png", "heatmap_similarity.png",
                             "evaluation.json"})
    assert not (out / "heatmap_metric.png").exists()
    assert (out / "heatmap_similarity.png").is_symlink()
    assert (out / "evaluation.json").read_bytes() == b"scan"


def test_a_killed_writers_staged_files_are_removed_later(tmp_path):
    """A staged file an hour old was left by a killed writer (it may hold a mesh): the
    next writer into that folder removes it; a fresh one (a writer at work) stays."""
    out = tmp_path / "out"
    out.mkdir()
    abandoned, fresh = out / ".mesh.ply.0123456789ab.part", out / ".mesh.ply.ba9876543210.part"
    abandoned.write_bytes(b"a mesh")
    fresh.write_bytes(b"a mesh")
    old = time.time() - 2 * 3600
    os.utime(abandoned, (old, old))
    write_results(out, {"report.json": b"{}"})
    assert not abandoned.exists() and fresh.exists()


def test_the_preview_is_made_from_the_runs_own_mesh(tmp_path):
    """A link planted in ``--out`` under a result's name (``heatmap_metric.png`` pointing
    at a file elsewhere) is not read into the preview: the preview comes from the run's
    artifacts in the store."""
    import trimesh

    from facecap.flows.capture import _export
    from facecap.tasks.store import artifact_key, open_store

    store = open_store(tmp_path / "store")
    key = artifact_key("fitting", {"fusion": "fusion-x"}, {}, "1")
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=80.0)
    store.put(key, {"mesh.ply": mesh.export(file_type="ply")}, stage="fitting",
              inputs={"fusion": "fusion-x"}, config={}, version="1")
    secret = tmp_path / "secret.png"
    cv2.imwrite(str(secret), np.full((40, 40, 3), 7, np.uint8))
    out = tmp_path / "out"
    out.mkdir()
    (out / "heatmap_metric.png").symlink_to(secret)
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    with ResultWriter(out) as writer:
        results = _export(str(tmp_path / "store"), {"fitting": key}, writer, scratch)
        writer.commit()
    assert set(results) == {"mesh.ply", "mesh.glb", "preview.png"}
    assert (out / "preview.png").read_bytes() != secret.read_bytes()
    assert cv2.imread(str(out / "preview.png")).shape == (320, 960, 3)


def test_a_full_disk_leaves_the_earlier_results_whole(tmp_path, monkeypatch):
    """ENOSPC on the second file of a batch: one-line error, the first file's earlier
    version still in place, no temporary file left behind."""
    out = tmp_path / "out"
    write_results(out, {"mesh.ply": b"earlier mesh", "report.json": b"earlier report"})
    real_open, calls = os.open, []

    def failing_open(path, flags, *args, **kwargs):
        if flags & os.O_CREAT and str(path).startswith(".report.json"):
            calls.append(path)
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_open(path, flags, *args, **kwargs)

    monkeypatch.setattr(os, "open", failing_open)
    with pytest.raises(OutputWriteError, match=r"No space left on device\); free space"):
        write_results(out, {"mesh.ply": b"new mesh", "report.json": b"new report"})
    monkeypatch.undo()
    assert calls
    assert (out / "mesh.ply").read_bytes() == b"earlier mesh"
    assert sorted(p.name for p in out.iterdir()) == [RECORD_NAME, "mesh.ply", "report.json"]


def test_an_output_folder_in_the_store_or_an_input_folder_is_refused(tmp_path, home):
    store = tmp_path / "store"
    (store / "artifacts" / "poses-x").mkdir(parents=True)
    for out in (store, store / "artifacts" / "poses-x", home / "store", home / "scratch" / "a"):
        with pytest.raises(InputError, match="keeps for itself"):
            check_output_place(out, str(store))
    photos = tmp_path / "photos"
    photos.mkdir()
    with pytest.raises(InputError, match="is the input folder"):
        check_output_place(photos / ".", str(store), (photos,))
    with pytest.raises(InputError, match="lies inside the input folder"):
        check_output_place(photos / "anna" / "results", str(store), (photos,))
    check_output_place(tmp_path / "results", str(store), (photos,))  # anywhere else is fine


NAMES = st.sampled_from(["report.json", "mesh.ply", "colmap", "colmap/cameras.txt",
                         ".report.json.part", "preview.png", RECORD_NAME])


@settings(max_examples=60, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(plants=st.lists(st.tuples(NAMES, st.sampled_from(["file", "link-file", "link-dir",
                                                           "dir", "hard-link", "input"])),
                       max_size=6),
       results=st.lists(NAMES.filter(lambda n: n not in ("colmap", RECORD_NAME)), min_size=1,
                        max_size=4, unique=True))
def test_fuzz_writes_stay_in_the_output_folder(tmp_path_factory, plants, results):
    """Whatever files, links (to files, folders, inputs) and folders lie in ``out`` under
    the names facecap writes, a batch either lands in ``out`` or is refused in one line:
    nothing outside ``out`` and no input changes, and a refused batch changes nothing."""
    tmp = tmp_path_factory.mktemp("fuzz")
    elsewhere, inputs, out = tmp / "elsewhere", tmp / "inputs", tmp / "out"
    for folder in (elsewhere, inputs, out):
        folder.mkdir()
    (elsewhere / "victim").write_bytes(b"victim")
    (inputs / "scan.ply").write_bytes(b"scan")
    for name, kind in plants:
        path = out / name
        if path.exists() or path.is_symlink() or not path.parent.is_dir():
            continue
        if kind == "file":
            path.write_bytes(b"planted")
        elif kind == "link-file":
            path.symlink_to(elsewhere / "victim")
        elif kind == "link-dir":
            path.symlink_to(elsewhere, target_is_directory=True)
        elif kind == "dir":
            path.mkdir()
        elif kind == "hard-link":
            os.link(elsewhere / "victim", path)
        else:
            os.link(inputs / "scan.ply", path)
    outside, out_before = _tree(elsewhere) | _tree(inputs), _tree(out)
    try:
        write_results(out, {name: b"result " + name.encode() for name in results},
                      inputs=(inputs / "scan.ply",))
    except (InputError, OutputWriteError) as exc:
        assert "\n" not in str(exc)
        assert _tree(out) == out_before
    else:
        for name in results:
            assert (out / name).read_bytes() == b"result " + name.encode()
            assert not (out / name).is_symlink()
    assert _tree(elsewhere) | _tree(inputs) == outside


# --------------------------------------------------------------------------- the command


def test_reconstruct_into_the_store_is_refused(media, kept, tmp_path, capfd):
    """Case 2: ``--out STORE/artifacts/<key>`` (it would delete the artifact's files)."""
    artifact = next((kept["store"] / "artifacts").iterdir())
    before = snapshot(kept["store"])
    code, _, err = facecap(capfd, "reconstruct", media["orbit"], "--out", artifact, "--store",
                           kept["store"], "--until", "keyframes")
    assert_one_line_error(code, err, ["lies inside", "another --out"])
    assert_kept(before, snapshot(kept["store"]))


def test_reconstruct_into_the_photo_folder_is_refused(kept, tmp_path, capfd):
    """Case 3: ``--out`` the photo folder, which holds photos named like results."""
    photos = tmp_path / "photos"
    photos.mkdir()
    frames = orbit_frames(12)
    for i, frame in enumerate(frames[:10]):
        cv2.imwrite(str(photos / f"IMG_{i:04d}.jpg"), frame)
    cv2.imwrite(str(photos / "preview.png"), frames[10])
    cv2.imwrite(str(photos / "heatmap_metric.png"), frames[11])
    before = _tree(photos)
    code, _, err = facecap(capfd, "reconstruct", photos, "--out", photos, "--store",
                           kept["store"])
    assert_one_line_error(code, err, ["is the input folder", "another --out"])
    assert _tree(photos) == before


@pytest.mark.slow
def test_a_run_writes_through_no_link_in_its_output_folder(media, kept, tmp_path, capfd,
                                                           prefect_server):
    """Case 1 through the command: links planted in ``--out`` under a result's name and
    under the temporary name the export used to write first."""
    elsewhere, out = _planted_links(tmp_path / "elsewhere", tmp_path / "linked")
    before = _tree(elsewhere)
    code, _, err = facecap(capfd, "reconstruct", media["orbit"], "--out", out, "--store",
                           kept["store"], "--until", "keyframes")
    assert code == 0, err
    assert _tree(elsewhere) == before
    assert json.loads((out / "report.json").read_text())["until"] == "keyframes"


def _children(pid: int) -> set[int]:
    import psutil

    try:
        return {p.pid for p in psutil.Process(pid).children(recursive=True)}
    except psutil.NoSuchProcess:
        return set()


def _alive(pids: set[int]) -> set[int]:
    import psutil

    return {p for p in pids if psutil.pid_exists(p)
            and psutil.Process(p).status() != psutil.STATUS_ZOMBIE}


@pytest.mark.slow
def test_a_killed_run_leaves_nothing_outside_facecap_home(media, tmp_path, home):
    """Case 4: ``facecap reconstruct`` killed (SIGKILL) in its pose stage, with no Prefect
    server named: its server stops, nothing is in the system's temp folder, and the next
    command removes the killed run's scratch folder (frames, COLMAP's database)."""
    system_tmp = tmp_path / "system-tmp"
    system_tmp.mkdir()
    (tmp_path / "cheap.yaml").write_text(CHEAP_POSES)
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_API")}
    env.update(TMPDIR=str(system_tmp), FACECAP_HOME=str(home), PREFECT_HOME=str(tmp_path / "ph"))
    command = [sys.executable, "-m", "facecap", "reconstruct", str(media["orbit"]), "--out",
               str(tmp_path / "out"), "--store", str(tmp_path / "store"), "--config",
               str(tmp_path / "cheap.yaml"), "--until", "poses"]
    proc = subprocess.Popen(command, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    scratch, children, deadline = home / "scratch", set(), time.monotonic() + 240
    while time.monotonic() < deadline and proc.poll() is None:
        children |= _children(proc.pid)
        if any(scratch.glob("*/work/poses-*")):
            break
        time.sleep(0.2)
    assert proc.poll() is None, "the run ended before its pose stage"
    children |= _children(proc.pid)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert children, "no server process was seen"
    deadline = time.monotonic() + 30
    while _alive(children) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not _alive(children), "the killed run's server lives on"
    assert list(system_tmp.iterdir()) == []
    (left,) = scratch.iterdir()  # the killed run's, frames and all
    old = time.time() - 3600  # as if the next command came an hour later
    os.utime(left, (old, old))
    code = subprocess.run([sys.executable, "-m", "facecap", "store", "prune",
                           "--older-than-days", "1", "--store", str(tmp_path / "store")],
                          env=env, capture_output=True, text=True)
    assert code.returncode == 0, code.stderr
    assert list(scratch.iterdir()) == []


@pytest.mark.slow
def test_a_prune_during_a_run_keeps_what_the_run_reads(media, kept, tmp_path, capfd,
                                                       prefect_server, monkeypatch):
    """Case 5: ``store prune`` of everything (an age of zero) while a capture's keyframe
    stage runs. Without leases it removed the run's video from the store and the run failed
    with a false "video not found"; now the video is kept (and said so), the run ends well,
    and a prune after the run removes it."""
    from datetime import UTC, datetime, timedelta

    from facecap.tasks import lifecycle
    from facecap.tasks.store import open_store
    from facecap_core import keyframes

    store = open_store(kept["store"])
    seen, select = {}, keyframes.main

    def pruning_first(*args, **kwargs):
        seen["removal"] = lifecycle.prune(store, datetime.now(UTC) + timedelta(days=1))
        return select(*args, **kwargs)

    monkeypatch.setattr(keyframes, "main", pruning_first)
    out = tmp_path / "pruned"
    code, _, err = facecap(capfd, "reconstruct", media["orbit"], "--out", out, "--store",
                           kept["store"], "--until", "keyframes")
    assert code == 0, err
    removal = seen["removal"]
    assert [k for k in removal.in_use if k.startswith("input-")], removal
    assert not [k for k in removal.artifacts if k.startswith("input-")], removal
    assert [k for k in removal.artifacts if k.startswith("fitting-")]  # not this run's: gone
    after = lifecycle.prune(store, datetime.now(UTC) + timedelta(days=1))
    assert [k for k in after.artifacts if k.startswith("input-")] and not after.in_use


@pytest.mark.slow
def test_a_full_facecap_home_is_one_line(media, kept, tmp_path, capfd, prefect_server,
                                         monkeypatch):
    """A stage whose scratch files (under FACECAP_HOME) meet a full disk: one line naming
    the folder and what to do, exit 2, the earlier results in ``--out`` untouched."""
    from facecap_core import keyframes

    def disk_full(video, out_dir, config):
        raise OSError(errno.ENOSPC, "No space left on device", str(out_dir / "frames.npz"))

    monkeypatch.setattr(keyframes, "main", disk_full)
    before = snapshot(kept["out"])
    code, _, err = facecap(capfd, "reconstruct", media["static"], "--out", kept["out"],
                           "--store", kept["store"], "--until", "keyframes")
    assert_one_line_error(code, err, ["keyframes stage could not write", "no space left",
                                      "free space there", "FACECAP_HOME"])
    assert_kept(before, snapshot(kept["out"]))


@pytest.mark.parametrize("setting, expected", [
    ({}, "capture not found"),
    ({"FACECAP_CAPTURE_TIMEOUT_S": "abc"}, "FACECAP_CAPTURE_TIMEOUT_S"),
], ids=["a capture that is not there", "a setting that is no number"])
def test_a_refused_command_stops_the_server_it_started(tmp_path, setting, expected):
    """A command that runs flows starts its server first thing, before it has read its
    arguments and settings; refused (bad input, exit 2, one line, however early), it stops
    that server rather than leave it."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_API")}
    env.update(FACECAP_HOME=str(tmp_path / "home"), PREFECT_HOME=str(tmp_path / "ph"),
               **setting)
    proc = subprocess.Popen([sys.executable, "-m", "facecap", "reconstruct",
                             str(tmp_path / "missing.mp4"), "--out", str(tmp_path / "out")],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True)
    children = set()
    while proc.poll() is None:
        children |= _children(proc.pid)
        time.sleep(0.02)
    err = proc.stderr.read()
    assert proc.returncode == 2 and expected in err and len(err.splitlines()) == 1, err
    deadline = time.monotonic() + 10
    while _alive(children) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not _alive(children), "the refused command's server lives on"


@pytest.mark.slow
def test_the_local_server_logs_to_a_file_and_dies_with_its_command(tmp_path):
    """The server a command starts for itself writes to ``logs/server.log`` (its shutdown
    traceback never reaches the console), and a SIGKILL of the command stops it."""
    script = ("import sys, time\nfrom facecap.flows.local_server import start_local_server\n"
              "print(start_local_server(), flush=True)\ntime.sleep(600)\n")
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_API")}
    env.update(FACECAP_HOME=str(tmp_path / "home"), PREFECT_HOME=str(tmp_path / "ph"),
               PREFECT_SERVER_ANALYTICS_ENABLED="false",
               PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS="180")
    proc = subprocess.Popen([sys.executable, "-c", script], env=env, stdout=subprocess.PIPE,
                            text=True)
    server = None
    try:
        server = int(proc.stdout.readline())
        log = os.readlink(f"/proc/{server}/fd/2")
    finally:
        proc.kill()
        proc.wait()
    deadline = time.monotonic() + 30
    while _alive({server}) and time.monotonic() < deadline:
        time.sleep(0.2)
    alive = _alive({server})
    if alive:
        os.kill(server, signal.SIGKILL)
    assert not alive, "the server outlived its command"
    assert log == str(tmp_path / "home" / "logs" / "server.log")


HEARTBEAT_SCRIPT = """
import sys
from facecap import console
from prefect import flow
from prefect.settings import get_current_settings

console.prefect_env(heartbeats=sys.argv[1] == "served")

@flow
def one() -> object:
    return get_current_settings().flows.heartbeat_frequency

print(one())
"""


@pytest.mark.slow
@pytest.mark.parametrize("command", ["reconstruct", "served"])
def test_flow_runs_on_the_command_s_own_server_send_no_heartbeats(tmp_path, command):
    """A heartbeat tells a server that a run whose process died has crashed; the server a
    command starts for itself dies with it, so its flow runs send none (Prefect's heartbeat
    thread held every run's end up to a second). A served deployment's runs keep them."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_API")}
    env.update(FACECAP_HOME=str(tmp_path / "home"), PREFECT_HOME=str(tmp_path / "ph"),
               PREFECT_SERVER_ANALYTICS_ENABLED="false",
               PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS="180")
    env.pop("PREFECT_FLOWS_HEARTBEAT_FREQUENCY", None)
    proc = subprocess.run([sys.executable, "-c", HEARTBEAT_SCRIPT, command], env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.split()[-1] == ("None" if command == "reconstruct" else "180")


DRAIN_SCRIPT = """
import logging
from facecap import console

console._quiet_console("WARNING")
logging.getLogger("EventsWorker").warning("Still processing items: 3 items remaining...")
logging.getLogger("APILogWorker").warning("Still processing items: 1 items remaining...")
logging.getLogger("EventsWorker").warning("EventsWorker queue is full (100 items), dropping item")
logging.getLogger("prefect.server").warning("the server said so")
"""


def test_the_exit_drain_of_events_and_logs_is_not_on_the_console(tmp_path):
    """A command ends while Prefect's senders still hold events and logs for a slow server;
    their progress lines are not the user's business (a refused input is one line), what
    they drop and every other warning is."""
    env = {**os.environ, "PREFECT_HOME": str(tmp_path / "ph")}
    proc = subprocess.run([sys.executable, "-c", DRAIN_SCRIPT], env=env, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = proc.stderr.splitlines()
    assert len(lines) == 2, lines
    assert "dropping item" in lines[0] and "the server said so" in lines[1]


@pytest.mark.slow
def test_a_server_database_that_cannot_open_is_one_line(tmp_path):
    """A damaged Prefect database (a first start stopped while it set the database up
    leaves one, as does a file of another program's) fails every start alike: one line that
    names the file and what to do, exit 2, not an internal error blaming facecap."""
    (tmp_path / "ph").mkdir()
    (tmp_path / "ph" / "prefect.db").write_bytes(b"not a database\n" * 64)
    root = tmp_path / "root" / "anna"
    root.mkdir(parents=True)
    write_video(root / "take.mp4", [np.full((64, 64, 3), 128, np.uint8)] * 4)
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_API")}
    env.update(FACECAP_HOME=str(tmp_path / "home"), PREFECT_HOME=str(tmp_path / "ph"),
               PREFECT_SERVER_ANALYTICS_ENABLED="false")
    proc = subprocess.run([sys.executable, "-m", "facecap", "evaluate-dataset",
                           str(tmp_path / "root"), "--out", str(tmp_path / "out")],
                          env=env, capture_output=True, text=True, timeout=600)
    assert_one_line_error(proc.returncode, proc.stderr,
                          ["cannot open its database", str(tmp_path / "ph" / "prefect.db"),
                           "move that file aside"])


def test_the_database_error_is_read_from_this_start_of_the_log(tmp_path):
    log = tmp_path / "server.log"
    log.write_text("sqlalchemy.exc.OperationalError: (sqlite3.OperationalError) an old one\n")
    offset = log.stat().st_size
    assert database_problem(log, offset) is None
    with open(log, "a") as file:
        file.write("Traceback ...\nsqlalchemy.exc.OperationalError: (sqlite3.OperationalError) "
                   "duplicate column name: state_timestamp\n[SQL: ALTER TABLE flow_run]\n")
    assert database_problem(log, offset) == "duplicate column name: state_timestamp"
    assert database_problem(tmp_path / "missing.log", 0) is None


# --------------------------------------------------------------------------- train-ears


@pytest.fixture
def quick_training(monkeypatch):
    """``facecap train-ears`` with its rendering and dlib's training replaced by stand-ins
    that make small files: what is tested is where the files go. Records each render."""
    import importlib

    from facecap.ear_training.render import EarSample

    training = importlib.import_module("facecap.ear_training.train")  # the package's train()

    renders = []

    class Model:
        def save(self, path: str) -> None:
            Path(path).write_bytes(b"model")

    def render(config, ict_model, transfer, progress):
        renders.append(ict_model)
        image = np.zeros((32, 32, 3), np.uint8)
        return [EarSample(image, np.zeros((4, 2)), np.ones(4, bool), (1, 1, 9, 9),
                          (1.0, 1.0, 9.0, 9.0), side, 60.0, False) for side in ("left", "right")]

    monkeypatch.setattr(training, "write_contour_file",
                        lambda path, config, ict: Path(path).write_text('{"ict": null}'))
    monkeypatch.setattr(training, "load_contour_file", lambda path: {"ict": None})
    monkeypatch.setattr(training, "render_dataset", render)
    monkeypatch.setattr(training, "train_detector", lambda *a: Model())
    monkeypatch.setattr(training, "predictor_boxes", lambda detector, samples: ([], 2))
    monkeypatch.setattr(training, "train_predictor", lambda *a: Model())
    return renders


def test_train_ears_writes_through_no_link_nor_over_an_input(quick_training, home, tmp_path,
                                                            monkeypatch, capsys):
    """Links planted in --out under the model's names (and its renders' cache) are replaced,
    never followed or read; a hard link to the ICT model in --out is never replaced; a folder
    of the store is refused before anything is rendered."""
    from facecap.cli import main

    ict = tmp_path / "ict_face_model.npz"
    ict.write_bytes(b"the ICT model")
    monkeypatch.setenv("FACECAP_ICT_MODEL", str(ict))
    elsewhere, out = tmp_path / "elsewhere", tmp_path / "out"
    elsewhere.mkdir()
    out.mkdir()
    for name in ("ear_detector.svm", "training.json", "dataset.npz"):
        (elsewhere / name).write_bytes(b"precious")
        (out / name).symlink_to(elsewhere / name)
    before = _tree(elsewhere)
    assert main(["train-ears", "--out", str(out)]) == 0, capsys.readouterr().err
    assert _tree(elsewhere) == before and len(quick_training) == 1  # the link was not read
    for name in ("ear_detector.svm", "ear_predictor.dat", "ear_contour.json", "training.json",
                 "dataset.npz"):
        assert (out / name).is_file() and not (out / name).is_symlink(), name
    assert len(list((out / "previews").glob("*.png"))) == 2
    assert json.loads((out / "training.json").read_text())["samples"] == 2

    (out / "ear_contour.json").unlink()
    os.link(ict, out / "ear_contour.json")  # the ICT model under a result's name
    capsys.readouterr()
    (out / "dataset.npz").unlink()  # so that a run that went on would render again
    trained = len(quick_training)
    assert main(["train-ears", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("facecap: error: ") and str(ict) in err[0], err
    assert ict.read_bytes() == b"the ICT model"
    assert len(quick_training) == trained  # refused before the training, not after it
    (out / "ear_contour.json").unlink()
    (out / "training.json").unlink()
    (out / "training.json").mkdir()  # a folder where a result goes
    assert main(["train-ears", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "is a folder where facecap writes a result" in err[0], err
    assert len(quick_training) == trained

    store = home / "store"
    store.mkdir(exist_ok=True)
    renders = len(quick_training)
    assert main(["train-ears", "--out", str(store / "artifacts")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "which facecap keeps for itself" in err[0], err
    assert len(quick_training) == renders and not (store / "artifacts").exists()


@pytest.mark.slow
def test_a_terminated_run_ends_with_one_line_and_exit_143(media, tmp_path, home):
    """``facecap reconstruct`` sent SIGTERM in its pose stage (while COLMAP works): one line
    that says so, exit 143 (128 + the signal, as a shell reports it), no native stack trace
    (pycolmap's glog would print one) and no Python traceback on the terminal."""
    (tmp_path / "cheap.yaml").write_text(CHEAP_POSES)
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_API")}
    env.update(FACECAP_HOME=str(home), PREFECT_HOME=str(tmp_path / "ph"))
    command = [sys.executable, "-m", "facecap", "reconstruct", str(media["orbit"]), "--out",
               str(tmp_path / "out"), "--store", str(tmp_path / "store"), "--config",
               str(tmp_path / "cheap.yaml"), "--until", "poses"]
    proc = subprocess.Popen(command, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    scratch, deadline = home / "scratch", time.monotonic() + 240
    while time.monotonic() < deadline and proc.poll() is None:
        if any(scratch.glob("*/work/poses-*")):
            break
        time.sleep(0.1)
    assert proc.poll() is None, "the run ended before its pose stage"
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=120)
    lines = [line for line in err.strip().splitlines() if line.strip()]
    assert proc.returncode == 143, err
    assert lines and lines[-1] == "facecap: terminated", err
    assert "Traceback" not in err and "*** SIGTERM" not in err and "stack trace" not in err, err
