"""The stage runner: content keys, one computation per key under concurrency, atomic
stores, and which faults are retried."""

from __future__ import annotations

import errno
import re
import threading
import time
from dataclasses import replace
from pathlib import Path

import pytest

from facecap.tasks.graph import BY_NAME, stage_key
from facecap.tasks.runner import ingest, is_transient, run_stage
from facecap.tasks.store import CorruptArtifactError, StoreWriteError, open_store
from facecap_core.errors import FacecapError, InputError
from facecap_core.stage import OutputMismatch


def _stage(run, name: str = "fusion", outputs: tuple[str, ...] = ("result.txt",)):
    """A stage row with another body, the files it writes and no config section (its params
    reach the body)."""
    return replace(BY_NAME[name], run=run, section=None, outputs=outputs,
                   optional_outputs=())


def test_key_depends_on_inputs_config_and_version(monkeypatch):
    base = stage_key("fusion", {"frames": "input-" + "0" * 32}, {"a": 1})
    assert base == stage_key("fusion", {"frames": "input-" + "0" * 32}, {"a": 1})
    assert base != stage_key("fusion", {"frames": "input-" + "1" * 32}, {"a": 1})
    assert base != stage_key("fusion", {"frames": "input-" + "0" * 32}, {"a": 2})
    assert base != stage_key("fusion", {"frames": "input-" + "0" * 32}, {"a": 1}, {"index": 3})
    bumped = replace(BY_NAME["fusion"], version=BY_NAME["fusion"].version + ".1")
    assert base != stage_key(bumped, {"frames": "input-" + "0" * 32}, {"a": 1})


def test_landmark_key_depends_on_the_ear_model(tmp_path, monkeypatch):
    """A retrained ear model (or none) makes new landmark artifacts instead of reusing ones
    computed with another model."""
    from facecap_core.landmarks.ears import MODELS_DIR

    inputs = {"video": "input-" + "0" * 32, "poses": "poses-" + "0" * 32}
    shipped = stage_key("landmarks", inputs, {})
    monkeypatch.setenv("FACECAP_EAR_MODELS", str(tmp_path))
    absent = stage_key("landmarks", inputs, {})
    for path in MODELS_DIR.iterdir():
        (tmp_path / path.name).write_bytes(path.read_bytes())
    assert stage_key("landmarks", inputs, {}) == shipped  # the same files: the same key
    (tmp_path / "ear_predictor.dat").write_bytes(b"retrained")
    retrained = stage_key("landmarks", inputs, {})
    assert len({shipped, absent, retrained}) == 3


def test_concurrent_runs_compute_once(tmp_path):
    store = str(tmp_path / "store")
    calls = []

    def slow(folders, out: Path, config, params):
        calls.append(1)
        time.sleep(0.5)
        (out / "result.txt").write_text(str(params["x"]))

    results = []
    threads = [threading.Thread(target=lambda: results.append(
        run_stage(store, _stage(slow), {}, {}, {"x": 7}))) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(calls) == 1
    assert len({key for key, _ in results}) == 1
    assert sorted(computed for _, computed in results) == [False, False, True]
    key = results[0][0]
    assert (open_store(store).get(key) / "result.txt").read_text() == "7"


def test_a_failed_stage_stores_nothing(tmp_path):
    store = str(tmp_path / "store")

    def half(folders, out: Path, config, params):
        (out / "part.txt").write_text("half")
        raise InputError("the input is bad")

    with pytest.raises(InputError):
        run_stage(store, _stage(half), {}, {})
    assert open_store(store).keys() == []


def test_inputs_reach_the_stage_as_folders(tmp_path):
    store = str(tmp_path / "store")
    video = tmp_path / "v.mp4"
    video.write_bytes(b"not really a video")
    key = ingest(store, video, "video.mp4")
    assert ingest(store, video, "video.mp4") == key  # content-addressed: same key

    seen = {}

    def body(folders, out: Path, config, params):
        seen["bytes"] = (folders["video"] / "video.mp4").read_bytes()
        (out / "ok").write_text("1")

    run_stage(store, _stage(body, "keyframes", outputs=("ok",)), {"video": key}, {})
    assert seen["bytes"] == b"not really a video"
    with pytest.raises(InputError, match="not found"):
        ingest(store, tmp_path / "missing.mp4", "video.mp4")


def test_a_stage_writes_exactly_the_files_its_row_lists(tmp_path):
    """Stage.outputs is checked on every run: a file the row does not list, or one it lists
    and the run did not write, fails the stage (not retried) and stores nothing. A field
    the params give names one file; one they do not give, one or more."""
    store = str(tmp_path / "store")
    outputs = ("a.json", "map_{index:05d}.npz", "frame_{frame:06d}.png")

    def writer(*names):
        def body(folders, out: Path, config, params):
            for name in names:
                (out / name).parent.mkdir(parents=True, exist_ok=True)
                (out / name).write_text("1")
        return body

    ok = _stage(writer("a.json", "map_00003.npz", "frame_000012.png", "frame_000020.png"),
                outputs=outputs)
    key, computed = run_stage(store, ok, {}, {}, {"index": 3})
    assert computed and sorted(p.name for p in open_store(store).get(key).iterdir()
                               if p.name != "manifest.json") == [
        "a.json", "frame_000012.png", "frame_000020.png", "map_00003.npz"]
    for names, says in [
        (("a.json", "map_00003.npz", "frame_000012.png", "debug.txt"),
         "wrote debug.txt, which its row does not list"),
        (("a.json", "map_00004.npz", "frame_000012.png"),
         "wrote map_00004.npz, which its row does not list and did not write "
         "map_{index:05d}.npz"),
        (("a.json", "map_00003.npz"), "did not write frame_{frame:06d}.png, which its row lists"),
        (("a.json", "map_00003.npz", "frame_12.png", "frame_000012.png"), "wrote frame_12.png"),
    ]:
        before = open_store(store).keys()
        with pytest.raises(OutputMismatch, match=re.escape(says)) as failed:
            run_stage(store, _stage(writer(*names), outputs=outputs), {}, {"n": len(before)},
                      {"index": 3})
        assert not is_transient(failed.value)
        assert open_store(store).keys() == before
    # A file written only when there is something in it (the poses' points.ply).
    maybe = replace(_stage(writer("a.json"), outputs=("a.json",)),
                    optional_outputs=("points.ply",))
    run_stage(store, maybe, {}, {"with": False})
    run_stage(store, replace(maybe, run=writer("a.json", "points.ply")), {}, {"with": True})


def test_every_row_exports_and_reads_files_it_lists():
    """What a run copies to the user's folder and what the capture flow reads of the
    evaluation (its per-vertex accuracy) are files of the rows."""
    from facecap_core.evaluation.stage import ACCURACY_NPY
    from facecap_core.stage import output_pattern

    for stage in BY_NAME.values():
        listed = [output_pattern(n) for n in stage.outputs + stage.optional_outputs]
        assert all(any(p.fullmatch(f) for p in listed) for f in stage.exported), stage.name
    assert ACCURACY_NPY.format(protocol="metric") in BY_NAME["evaluation"].outputs


@pytest.mark.parametrize("exc, retried", [
    (InputError("bad video"), False),
    (FacecapError("no face"), False),
    (StoreWriteError("disk full"), True),
    (CorruptArtifactError("checksum"), True),
    (ConnectionError("reset"), True),
    (TimeoutError("slow"), True),
    (OSError("EIO"), True),
    (ValueError("bug"), False),
    # A file where the store's folder should be, or the reverse: it stays so.
    (NotADirectoryError(errno.ENOTDIR, "Not a directory"), False),
    (IsADirectoryError(errno.EISDIR, "Is a directory"), False),
])
def test_only_transient_faults_are_retried(exc, retried):
    assert is_transient(exc) is retried


def test_a_store_folder_that_is_a_file_fails_its_first_task_at_once(tmp_path):
    """The store's lock folder is a file: the task fails with one line, not retried (a
    lasting errno), instead of ~20 s of retries ending in a traceback."""
    from facecap.tasks.runner import key_lock

    (tmp_path / "store").mkdir()
    (tmp_path / "store" / ".locks").write_text("a file where the lock folder should be")
    with pytest.raises(StoreWriteError) as refused:
        with key_lock(open_store(str(tmp_path / "store")), "input-" + "0" * 32):
            pass
    assert "cannot lock artifact input-" in str(refused.value)
    assert "Not a directory" in str(refused.value) and not is_transient(refused.value)


def test_results_are_exported_only_as_they_were_committed(tmp_path):
    """The output folder shows this run's results only (an earlier run's heat map goes, the
    user's own files stay, one named like a result too); a stored result changed after its
    commit (fx 500 -> 999 in cameras.json) is refused when exported, not handed to the user."""
    from facecap.flows.capture import _export
    from facecap.tasks.graph import OUTPUT_NAMES
    from facecap.tasks.outputs import ResultWriter, write_results
    from facecap.tasks.store import artifact_key

    store = open_store(str(tmp_path / "store"))
    key = artifact_key("poses", {"video": "input-x"}, {}, "1")
    store.put(key, {"cameras.json": b'{"fx": 500}'}, stage="poses", inputs={"video": "input-x"},
              config={}, version="1")
    out = tmp_path / "out"
    # An earlier run's heat maps, which this run (no scan, no mesh) did not make; the user
    # has since put a file of their own under one of those names.
    write_results(out, {"heatmap_metric.png": b"an earlier run",
                        "heatmap_similarity.png": b"an earlier run"})
    (out / "heatmap_similarity.png").write_bytes(b"the user's own file")
    (out / "notes.txt").write_text("the user's own file")
    with ResultWriter(out) as writer:
        _export(str(tmp_path / "store"), {"poses": key}, writer, tmp_path)
        writer.commit(stale=OUTPUT_NAMES)
    assert (out / "cameras.json").read_bytes() == b'{"fx": 500}'
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == [
        "cameras.json", "heatmap_similarity.png", "notes.txt"]
    assert (out / "heatmap_similarity.png").read_bytes() == b"the user's own file"
    (store.get(key) / "cameras.json").write_bytes(b'{"fx": 999}')
    with pytest.raises(CorruptArtifactError, match="cameras.json"), \
            ResultWriter(tmp_path / "again") as writer:
        _export(str(tmp_path / "store"), {"poses": key}, writer, tmp_path)
        writer.commit()
    assert not (tmp_path / "again" / "cameras.json").exists()


@pytest.mark.parametrize("when_missing", ["warn", "error"])
def test_core_logs_outside_a_run_neither_warn_nor_fail(when_missing, capfd):
    """facecap_core used outside any run (a benchmark, plain Python): the run log handler
    skips its records, whatever PREFECT_LOGGING_TO_API_WHEN_MISSING_FLOW says (Prefect's
    own handler warns there, or raises)."""
    import logging
    import warnings

    from prefect.settings import PREFECT_LOGGING_TO_API_WHEN_MISSING_FLOW, temporary_settings

    from facecap.tasks.logs import in_run, send_core_logs_to_runs

    send_core_logs_to_runs()
    assert not in_run()
    log = logging.getLogger("facecap_core.fitting.run")
    with temporary_settings({PREFECT_LOGGING_TO_API_WHEN_MISSING_FLOW: when_missing}):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            log.info("fitted outside a run")
            log.warning("a warning outside a run")
    assert "Logging error" not in capfd.readouterr().err


def test_core_logs_go_to_runs_once_whatever_the_extra_loggers_say(tmp_path):
    """A worker started with Prefect's default settings sends facecap_core's INFO records to
    its runs; one whose PREFECT_LOGGING_EXTRA_LOGGERS names facecap_core or one of its
    modules sends each record once (Prefect's handler there is replaced)."""
    import os
    import subprocess
    import sys

    script = ("import logging, facecap.tasks.stages\n"
              "for name in ('facecap_core', 'facecap_core.mvs'):\n"
              "    logger = logging.getLogger(name)\n"
              "    print(name, logger.level, [type(h).__name__ for h in logger.handlers])\n")
    root = Path(__file__).resolve().parents[1]
    for extra in ("", "facecap_core,facecap_core.mvs"):
        env = {**os.environ, "PREFECT_LOGGING_EXTRA_LOGGERS": extra,
               "PREFECT_HOME": str(tmp_path)}
        out = subprocess.run([sys.executable, "-c", script], cwd=root, env=env, check=True,
                             capture_output=True, text=True, timeout=120).stdout
        assert out.splitlines() == ["facecap_core 20 ['RunLogHandler']", "facecap_core.mvs 0 []"]


def test_a_stage_waited_for_after_its_limit_is_judged_by_its_own_end(monkeypatch):
    """A stage the flow waits for only when a later stage reads it (the frames, beside the
    landmarks): finished within its time limit, it is not over it because the wait came
    later; one that ended past the limit is."""
    import concurrent.futures
    import uuid

    from prefect.futures import PrefectConcurrentFuture

    from facecap.tasks.stages import _timed, first_finished, stage_result

    monkeypatch.setenv("FACECAP_STAGE_TIMEOUT_S", "0.2")

    def finished(after_s: float) -> tuple[PrefectConcurrentFuture, float]:
        started = time.monotonic()
        wrapped = concurrent.futures.Future()
        future = _timed(PrefectConcurrentFuture(task_run_id=uuid.uuid4(),
                                                wrapped_future=wrapped))
        time.sleep(after_s)
        wrapped.set_result(("frames-key", True))
        return future, started

    on_time, started = finished(0.01)
    time.sleep(0.3)  # the flow waits for it past its limit
    assert stage_result("frames", on_time, "t", started) == ("frames-key", True)
    late, started = finished(0.3)
    with pytest.raises(FacecapError, match="frames stage of t was stopped after its time limit"):
        stage_result("frames", late, "t", started)
    # Of two maps running, the one that finished is taken, whichever started first.
    slow = PrefectConcurrentFuture(task_run_id=uuid.uuid4(),
                                   wrapped_future=concurrent.futures.Future())
    done, _ = finished(0.0)
    assert first_finished([slow, done], time.monotonic()) == 1
