"""facecap's own trees hold only what facecap expects (:mod:`tasks.own_files`): a link, a
FIFO, a folder or a JSON bomb planted where it keeps a lock, a lease or a record is refused
in one line or passed over, never followed, never waited on, never parsed to a crash."""

from __future__ import annotations

import os
import signal
from contextlib import contextmanager
from pathlib import Path

import pytest

from facecap.tasks.own_files import (
    MAX_JSON_DEPTH,
    OwnFileError,
    nesting_depth,
    open_regular,
    read_json,
)
from facecap.tasks.runner import ingest, lease, run_leases
from facecap.tasks.store import input_key, open_store
from facecap_core.errors import InputError

DEEP = "[" * 100_000 + "]" * 100_000
"""JSON nested 100,000 deep: Python's parser recurses once per level."""


@contextmanager
def deadline(seconds: float = 20.0):
    """Fail the test where the block waits longer than ``seconds`` (an open of a FIFO with
    no writer waits forever): the alarm interrupts the waiting call."""
    def hung(signum, frame):
        raise AssertionError(f"still waiting after {seconds} s (a FIFO opened?)")

    previous = signal.signal(signal.SIGALRM, hung)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def plant(path: Path, kind: str, target: Path) -> None:
    """A ``kind`` ('link', 'FIFO', 'folder' or 'deep') at ``path``; a link leads to
    ``target``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if kind == "link":
        path.symlink_to(target)
    elif kind == "FIFO":
        os.mkfifo(path)
    elif kind == "folder":
        path.mkdir()
    else:
        path.write_text(DEEP)


def test_only_a_regular_file_is_opened(tmp_path):
    """A plain file opens (a missing one is made with ``create``, never truncated); a link,
    a FIFO (at once, no writer waited for) or a folder is an OwnFileError naming it."""
    (tmp_path / "plain").write_text("kept")
    fd = open_regular(tmp_path / "plain", create=True)
    os.close(fd)
    assert (tmp_path / "plain").read_text() == "kept"
    os.close(open_regular(tmp_path / "new", create=True))
    assert (tmp_path / "new").is_file()
    for kind, words in (("link", "is a link"), ("FIFO", "is a FIFO"), ("folder", "is a folder")):
        path = tmp_path / f"planted {kind}"
        plant(path, kind, tmp_path / "plain")
        for create in (False, True):
            with deadline(), pytest.raises(OwnFileError) as refused:
                open_regular(path, create=create)
            line = str(refused.value)
            assert line.startswith(f"{path} {words}, where facecap keeps a file of its own")
            assert "move it out of the way or delete it" in line and "\n" not in line
    assert (tmp_path / "plain").read_text() == "kept"
    with pytest.raises(FileNotFoundError):
        open_regular(tmp_path / "missing")


def test_json_is_read_within_a_size_and_a_depth(tmp_path):
    """JSON nested 100,000 deep is an OwnFileError that says how deep, not a RecursionError;
    so is a file past the size bound, or one that is not JSON; brackets in strings are
    text."""
    path = tmp_path / "doc.json"
    path.write_text('{"a": [1, {"b": "[[[[ not nesting ]"}]}')
    assert read_json(path) == {"a": [1, {"b": "[[[[ not nesting ]"}]}
    assert nesting_depth(path.read_bytes()) == 3
    path.write_text("[" * MAX_JSON_DEPTH + "]" * MAX_JSON_DEPTH)
    assert read_json(path) is not None
    for text, words in ((DEEP, "is JSON nested 100000 deep, deeper than facecap writes"),
                        ('{"a": ', "is not JSON"), ("[1, 2, 3]" * 10, "is larger than 40 bytes")):
        path.write_text(text)
        with pytest.raises(OwnFileError) as refused:
            read_json(path, max_bytes=40 if "larger" in words else 2**20)
        assert str(refused.value).startswith(f"{path} {words}"), str(refused.value)
    path.write_bytes(b'{"caf\xe9": 1}')
    with pytest.raises(OwnFileError, match="is not UTF-8 text"):
        read_json(path)


@pytest.mark.parametrize(("name", "kind"), [
    (name, kind) for name in ("lock", "lease", "lock folder") for kind in ("link", "FIFO", "folder")
    # A folder is what .locks is; a FIFO or a file there is no folder (tests/test_tasks.py).
    if (name, kind) not in (("lock folder", "folder"), ("lock folder", "FIFO"))])
def test_a_planted_lock_is_refused_and_what_it_leads_to_kept(name, kind, tmp_path):
    """``STORE/.locks/<key>.lock`` (or ``.lease``, or ``.locks`` itself) planted as a link
    used to be opened for writing through it: the ingest truncated the link's target to 0
    bytes. A FIFO there hung the run. Now: one line naming it, the target untouched, at
    once; the store holds nothing of the capture."""
    video, secret, store = tmp_path / "take.mp4", tmp_path / "secret.txt", tmp_path / "store"
    video.write_bytes(b"the face of alice")
    secret.write_text("the user's own file")
    key = input_key(video)
    locks = store / ".locks"
    if name == "lock folder":
        planted = locks
        (tmp_path / "elsewhere").mkdir()
        plant(locks, kind, tmp_path / "elsewhere")
    else:
        planted = locks / f"{key}.{name}"
        plant(planted, kind, secret)
    with deadline(), pytest.raises(InputError) as refused:
        with run_leases():
            lease(open_store(store), key)
            ingest(str(store), video, "video.mp4")
    line = str(refused.value)
    what = "a folder" if name == "lock folder" else "a file"
    assert line.startswith(f"{planted} is a {kind}, where facecap keeps {what} of its own"), line
    assert "\n" not in line
    assert secret.read_text() == "the user's own file"
    if name == "lock folder" and kind == "link":
        assert not list((tmp_path / "elsewhere").iterdir())  # no lock made behind the link
    assert not open_store(store).exists(key)


@pytest.mark.parametrize("kind", ["FIFO", "deep", "link"])
def test_a_planted_results_record_is_no_record(kind, tmp_path):
    """A FIFO at ``OUT/.facecap-results.json`` used to hang ``reconstruct`` as it committed
    its results (the writer reads the record first): it, a JSON bomb or a link there is read
    as an empty record (nothing of the folder is taken for facecap's) and replaced by the
    real one, without following the link."""
    from facecap.tasks.outputs import RECORD_NAME, write_results

    out, secret = tmp_path / "out", tmp_path / "secret.txt"
    secret.write_text("the user's own file")
    out.mkdir()
    (out / "notes.txt").write_text("the user's notes")
    plant(out / RECORD_NAME, kind, secret)
    with deadline():
        write_results(out, {"mesh.ply": b"a mesh"}, ())
        write_results(out, {"report.json": b"{}"}, ())
    assert (out / "mesh.ply").read_bytes() == b"a mesh"
    assert read_json(out / RECORD_NAME).keys() == {"mesh.ply", "report.json"}
    assert (out / "notes.txt").read_text() == "the user's notes"
    assert secret.read_text() == "the user's own file"


@pytest.mark.parametrize("kind", ["FIFO", "deep"])
def test_a_planted_evaluation_neither_hangs_nor_crashes_the_dataset_page(kind, tmp_path):
    """A FIFO under ``OUT/evaluations/`` used to hang ``facecap dataset`` as it wrote its
    page (and one nested 100,000 deep crashed it): the page passes over it. Before an
    evaluation, the history check names it in one line."""
    from facecap.flows.evaluate import check_history
    from facecap.pages.dataset import rewrite_dataset_page

    out = tmp_path / "out"
    planted = out / "evaluations" / "20261102T020000000000Z.json"
    plant(planted, kind, tmp_path)
    plant(out / "dataset.json", kind, tmp_path)
    with deadline():
        rewrite_dataset_page(out)
        with pytest.raises(InputError) as refused:
            check_history(out)
    assert (out / "index.html").is_file()
    problem = "a FIFO" if kind == "FIFO" else "JSON nested 100000 deep"
    assert str(refused.value).startswith(f"{planted} is not an evaluation facecap wrote "
                                         f"({problem}"), str(refused.value)


@pytest.mark.parametrize(("name", "kind"), [
    ("logs", "link"), ("logs", "FIFO"), ("logs", "file"), ("server.log", "link"),
    ("server.log", "FIFO")])
def test_a_planted_logs_folder_or_server_log_is_refused_before_the_server_starts(
        name, kind, tmp_path, monkeypatch):
    """``FACECAP_HOME/logs`` planted as a link used to have the local Prefect server write
    ``server.log`` behind it (a FIFO there, as ``server.log``, hung the command). Now: one
    line naming it, before a server is started, nothing written behind the link."""
    from facecap.flows import local_server

    home, elsewhere = tmp_path / "home", tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "server.log").write_text("the user's own file")
    monkeypatch.setenv("FACECAP_HOME", str(home))
    planted = home / "logs" if name == "logs" else home / "logs" / "server.log"
    if kind == "file":
        home.mkdir()
        planted.write_text("the user's own file")
    else:
        plant(planted, kind, elsewhere if name == "logs" else elsewhere / "server.log")

    def started(*args, **kwargs):
        raise AssertionError("a server was started")

    monkeypatch.setattr(local_server.subprocess, "Popen", started)
    with deadline(), pytest.raises(OwnFileError) as refused:
        local_server._Server(quiet=True)
    line = str(refused.value)
    what = "a folder" if name == "logs" else "a file"
    assert line.startswith(f"{planted} is a {kind}, where facecap keeps {what} of its own"), line
    assert "\n" not in line and isinstance(refused.value, InputError)  # exit 2, one line
    assert (elsewhere / "server.log").read_text() == "the user's own file"
    assert [p.name for p in elsewhere.iterdir()] == ["server.log"]


def test_the_server_log_is_appended_to_and_started_again_past_its_bound(tmp_path, monkeypatch):
    """The log a server writes to is ``FACECAP_HOME/logs/server.log``, appended to; past
    its bound it starts again from empty."""
    from facecap.flows import local_server

    monkeypatch.setenv("FACECAP_HOME", str(tmp_path / "home"))
    monkeypatch.setattr(local_server, "MAX_LOG_BYTES", 10)
    for text in (b"12345", b"678", b"abc"):
        fd = local_server.open_server_log()
        os.write(fd, text)
        os.close(fd)
    assert local_server.server_log().read_bytes() == b"12345678abc"
    os.close(local_server.open_server_log())
    assert local_server.server_log().read_bytes() == b""


@pytest.mark.parametrize("kind", ["link", "file"])
def test_a_crash_log_is_never_written_behind_a_planted_logs_link(kind, tmp_path, monkeypatch,
                                                                 capsys):
    """A bug's traceback goes to ``FACECAP_HOME/logs/crash-….log``: with ``logs`` planted as
    a link it used to be written behind it. Now the bug's one line says why the traceback
    was not saved, and nothing is written behind the link."""
    from facecap_core import evaluation
    from tests.test_cli import evaluate_a_mesh

    def broken(*args, **kwargs):
        raise ZeroDivisionError("float division by zero")

    home, elsewhere = tmp_path / "home", tmp_path / "elsewhere"
    elsewhere.mkdir()
    home.mkdir()
    plant(home / "logs", "link", elsewhere) if kind == "link" else (home / "logs").write_text("")
    monkeypatch.setenv("FACECAP_HOME", str(home))
    monkeypatch.setattr(evaluation, "evaluate", broken)
    code = evaluate_a_mesh(tmp_path)
    err = capsys.readouterr().err
    assert code == 1 and len(err.strip().splitlines()) == 1, err
    assert err.startswith("facecap: internal error (a bug in facecap"), err
    assert (f"the traceback could not be saved ({home / 'logs'} is a {kind}, where facecap "
            "keeps a folder of its own; move it out of the way or delete it") in err, err
    assert not list(elsewhere.iterdir())


@pytest.mark.parametrize("kind", ["link", "FIFO", "file"])
def test_a_planted_store_tmp_is_refused_and_nothing_written_behind_it(kind, tmp_path):
    """``STORE/.tmp`` (where every artifact is written before its rename into place)
    planted as a link used to have the ingested video copy and the keyframe tracks written
    behind it. Now: one line naming it, nothing written behind the link, nothing stored."""
    video, elsewhere, store = tmp_path / "take.mp4", tmp_path / "elsewhere", tmp_path / "store"
    video.write_bytes(b"the face of alice")
    elsewhere.mkdir()
    key = input_key(video)
    if kind == "file":
        store.mkdir()
        (store / ".tmp").write_text("the user's own file")
    else:
        plant(store / ".tmp", kind, elsewhere)
    with deadline(), pytest.raises(InputError) as refused:
        with run_leases():
            ingest(str(store), video, "video.mp4")
    line = str(refused.value)
    assert line.startswith(f"{store / '.tmp'} is a {kind}, where facecap keeps a folder of its "
                           "own; move it out of the way or delete it"), line
    assert "\n" not in line
    assert not list(elsewhere.iterdir())
    assert not open_store(store).exists(key)


@pytest.mark.parametrize(("name", "kind"), [
    (".alive", "link"), (".alive", "FIFO"), (".alive", "folder"), ("folder", "link")])
def test_a_planted_scratch_alive_file_is_refused(name, kind, tmp_path, monkeypatch):
    """This process's scratch folder ``FACECAP_HOME/scratch/<host>-<pid>-<start>`` holds an
    ``.alive`` file it locks for its life: planted as a link it was opened (made, if the link
    led nowhere) behind it, as a FIFO it hung the command. Now: one line naming it, nothing
    made behind the link, no temp folder set there."""
    import tempfile

    from facecap.tasks import scratch

    home, elsewhere = tmp_path / "home", tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.setenv("FACECAP_HOME", str(home))
    monkeypatch.setattr(scratch, "_folder", None)
    monkeypatch.setattr(scratch, "_alive_lock", None)
    pid = os.getpid()
    folder = home / scratch.SCRATCH / f"{scratch._host()}-{pid}-{scratch.start_ticks(pid)}"
    planted = folder if name == "folder" else folder / scratch.ALIVE
    plant(planted, kind, elsewhere if name == "folder" else elsewhere / "made")
    with deadline(), pytest.raises(OwnFileError) as refused:
        scratch.process_scratch()
    what = "a folder" if name == "folder" else "a file"
    line = str(refused.value)
    assert line.startswith(f"{planted} is a {kind}, where facecap keeps {what} of its own"), line
    assert "\n" not in line and isinstance(refused.value, InputError)  # exit 2, one line
    assert not list(elsewhere.iterdir())
    assert tempfile.gettempdir() != str(folder)


@pytest.mark.parametrize("kind", ["link", "FIFO"])
def test_a_planted_alive_file_is_no_orphan_to_remove(kind, tmp_path):
    """A killed command's scratch folder is removed once no process holds its ``.alive``
    lock; one whose ``.alive`` is a FIFO used to hang every later command that runs flows
    (opened to append, it waits for a reader), and one whose ``.alive`` is a link led
    nowhere had the file made behind it. Now such a folder is no facecap orphan: kept, at
    once, nothing made behind the link; a real orphan beside it is still removed."""
    from facecap.tasks import scratch

    home, elsewhere = tmp_path / "home", tmp_path / "elsewhere"
    elsewhere.mkdir()
    planted, orphan = home / "scratch" / "host-1-1", home / "scratch" / "host-2-2"
    plant(planted / scratch.ALIVE, kind, elsewhere / "made")
    orphan.mkdir()
    (orphan / scratch.ALIVE).touch()
    old = 10 * scratch.GRACE_S
    for folder in (planted, orphan):
        os.utime(folder, (os.path.getmtime(folder) - old,) * 2)
    with deadline():
        removed = scratch.remove_orphans(home)
    assert removed == [orphan] and not orphan.exists()
    assert planted.is_dir() and not list(elsewhere.iterdir())
