"""Faults: a worker killed in any stage, a corrupt artifact, a store that goes away.

One module on purpose (~500 lines): the kill chain, the worker processes and the Prefect
server they report to are set up once and shared by every fault.

Every stage runs for real, in worker processes that report to one Prefect test server: the
first stages (ingest, keyframes, poses) through the capture flow on a small video of a dot
scene, the landmarks and coarse mesh on the small face capture of ``tests/test_flows.py`` with
its ground-truth poses seeded into the store, and the stages after the coarse mesh on the same
capture with the ground-truth coarse mesh seeded too (as there). The fault hook of
``tasks.runner`` (``FACECAP_FAULT=STAGE[:N[:HOW]]``) kills a worker with exit code 137 after a
stage has written its files and before it commits them: the moment that loses the most work.
Each worker logs the artifact key of every computation it starts, so the tests count what was
computed again and what was reused.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from facecap.tasks.store import CorruptArtifactError, open_store

ROOT = Path(__file__).resolve().parents[1]

WORKER = """
import dataclasses, json, sys
import facecap.tasks.stages as stages
from facecap.tasks.store import input_key, open_store
from facecap.tasks.graph import stage_key
from facecap.tasks.runner import ingest, run_stage

mode, store, args, log_path = sys.argv[1], sys.argv[2], json.loads(sys.argv[3]), sys.argv[4]

def log(key):
    with open(log_path, "a") as f:  # written before the work: a killed worker leaves it
        f.write(key + "\\n")

def logged_run_stage(store_url, stage, inputs, config, params=None):
    key = stage_key(stage, inputs, config, params)

    def run_and_log(folders, out, cfg, prm):
        log(key)
        return stage.run(folders, out, cfg, prm)

    logged = dataclasses.replace(stage, run=run_and_log)
    return run_stage(store_url, logged, inputs, config, params)

def logged_ingest(store_url, path, name):
    if not open_store(store_url).exists(input_key(path)):
        log(input_key(path))
    return ingest(store_url, path, name)

stages.run_stage, stages.ingest = logged_run_stage, logged_ingest
if mode == "head":  # the real capture flow, up to the poses
    from facecap.flows.capture import reconstruct_capture
    report = reconstruct_capture(args["video"], args["out"], config=args["config"],
                                 until="poses", store=store)
    keys = {name: info["key"] for name, info in report["stages"].items()}
    keys["video"] = input_key(args["video"])
elif mode == "dataset":  # the dataset flow, every capture through the real capture flow
    from facecap.flows.dataset import reconstruct_dataset
    keys = reconstruct_dataset(args["root"], args["out"], config=args["config"], store=store)
elif mode == "middle":  # landmarks and coarse mesh from seeded poses
    from tests.test_faults import make_middle_flow
    keys = make_middle_flow()(store, args["seeded"])
else:  # everything after the coarse mesh
    from tests.test_flows import make_tail_flow, small_config
    keys = make_tail_flow()(store, args["seeded"], small_config().model_dump(mode="json"),
                            args["scan"], args["scan_landmarks"])["keys"]
print("KEYS " + json.dumps(keys))
"""


def make_middle_flow():
    from prefect import flow

    from facecap.tasks.stages import call_stage
    from facecap_core.coarse import CoarseConfig
    from facecap_core.landmarks.stage import LandmarkConfig

    @flow(name="middle")
    def middle(store: str, seeded: dict) -> dict:
        keys = {"video": seeded["video"], "poses": seeded["poses"]}
        keys["landmarks"], _ = call_stage("landmarks", store, keys, LandmarkConfig(), "t")
        keys["coarse"], _ = call_stage("coarse", store, {"landmarks": keys["landmarks"],
                                                         "poses": keys["poses"]},
                                       CoarseConfig(), "t")
        return keys

    return middle


@pytest.fixture(scope="module")
def prefect_api(tmp_path_factory) -> str:
    """One Prefect test server for the module; its URL for worker processes."""
    from prefect.settings import PREFECT_API_URL
    from prefect.testing.utilities import prefect_test_harness

    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    with prefect_test_harness(server_startup_timeout=120):
        yield PREFECT_API_URL.value()


def shared_capture(tmp_path_factory, ict_model) -> Path:
    """The capture of tests/test_flows.py, rendered once per test session."""
    from facecap.synthetic import synthesize
    from facecap.synthetic.config import SynthConfig
    from tests.test_flows import FRAMES, HEIGHT, WIDTH

    folder = tmp_path_factory.getbasetemp() / "robustness-capture" / "subject a"
    if not (folder / "gt" / "render.json").is_file():
        fps = FRAMES / 6.0
        synthesize(SynthConfig(subject="ict:2", ict_model=ict_model, width=WIDTH, height=HEIGHT,
                               fps=fps, duration_s=6.0, exposure_fraction=0.25 * fps / 30,
                               seed=2), folder, progress=False)
    return folder


@pytest.fixture(scope="module")
def capture(tmp_path_factory, ict_model) -> Path:
    return shared_capture(tmp_path_factory, ict_model)


def committed(store: Path) -> dict[str, str]:
    """{key: commit time} of every artifact in a local store."""
    return {key: open_store(store).manifest(key).created for key in open_store(store).keys()}


def worker_home(tmp: Path) -> Path:
    """A FACECAP_HOME for worker processes, with a copy of the template assets (so that no
    worker fetches them)."""
    import shutil

    from facecap_core import assets

    source = assets.menpo3d_data()
    home = tmp / "home"
    if not (home / "assets" / source.name).is_dir():
        shutil.copytree(source, home / "assets" / source.name)
    return home


def start_worker(api: str, mode: str, store: Path, args: dict, log: Path, fault: str | None,
                 home: Path) -> subprocess.Popen:
    """A worker process running ``mode``'s flow against the Prefect server at ``api``; it
    logs the key of every computation it starts to ``log``."""
    env = {**os.environ, "PREFECT_API_URL": api, "FACECAP_HOME": str(home),
           "PREFECT_LOGGING_LEVEL": "WARNING", "GLOG_minloglevel": "3",
           "PYTHONPATH": str(ROOT)}
    env.pop("FACECAP_FAULT", None)
    if fault:
        env["FACECAP_FAULT"] = fault
    return subprocess.Popen([sys.executable, "-c", WORKER, mode, str(store), json.dumps(args),
                             str(log)], env=env, cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def finish(worker: subprocess.Popen) -> subprocess.CompletedProcess:
    stdout, stderr = worker.communicate(timeout=900)
    return subprocess.CompletedProcess(worker.args, worker.returncode, stdout, stderr)


def run_worker(api: str, mode: str, store: Path, args: dict, log: Path, fault: str | None,
               home: Path) -> subprocess.CompletedProcess:
    return finish(start_worker(api, mode, store, args, log, fault, home))


def computed_in(log: Path) -> list[str]:
    return log.read_text().split() if log.is_file() else []


def _without_timings(value):
    """JSON data less the run's own timings (seconds, CPU, memory), which differ per run."""
    if isinstance(value, dict):
        return {k: _without_timings(v) for k, v in value.items()
                if not (k in ("timing", "peak_rss_mb") or k.endswith(("seconds", "_s")))}
    if isinstance(value, list):
        return [_without_timings(v) for v in value]
    return value


def digests(folder: Path) -> dict[str, str]:
    """sha256 of each file of an artifact folder; JSON files without their timings."""
    found = {}
    for path in sorted(folder.rglob("*")):
        if path.is_file() and path.name != "manifest.json":
            data = path.read_bytes()
            if path.suffix == ".json":
                data = json.dumps(_without_timings(json.loads(data)), sort_keys=True).encode()
            found[path.relative_to(folder).as_posix()] = hashlib.sha256(data).hexdigest()
    return found


KILLS = {
    "head": ["input", "keyframes", "poses"],
    "middle": ["landmarks", "coarse"],
    "tail": ["frames", "views", "depth:3", "fusion", "fitting", "evaluation"],
}
"""One worker killed in each stage, in pipeline order: the first stages run the real
capture flow on a video of a dot scene (it has no face, so the flow stops after the
poses); the landmarks and coarse mesh, and the stages after it, run on the face capture
with seeded ground-truth poses (and coarse mesh)."""

CHEAP_POSES = {"keyframes": {"keyframe_angle_deg": 10},
               "poses": {"method": "geometric", "use_tracks": False}}
"""Few keyframes, no photometric refinement: poses in seconds on the 224x128 dot video."""


def run_chain(api: str, mode: str, args: dict, store: Path, tmp: Path) -> list[dict]:
    """Worker k dies in stage k of ``KILLS[mode]``; worker k+1 starts over on the same
    store; the last worker has no fault and finishes. Records what each worker computed and
    committed, and where each killed worker left its uncommitted files."""
    home = worker_home(tmp)
    runs = []
    for number, fault in enumerate(KILLS[mode] + [None]):
        log = tmp / f"computed-{mode}-{number}.log"
        before = committed(store)
        proc = run_worker(api, mode, store, args, log, fault, home)
        run = {"fault": fault, "code": proc.returncode, "stderr": proc.stderr[-3000:],
               "before": before, "after": committed(store), "computed": computed_in(log)}
        if fault:
            stage = fault.split(":")[0]
            work = re.search(rf"facecap fault: {stage} killed before its commit; its files "
                             r"are in (\S+)", proc.stderr)
            run["work"] = Path(work.group(1)) if work else None
        elif proc.returncode == 0:
            run["keys"] = json.loads(proc.stdout.split("KEYS ", 1)[1])
        runs.append(run)
    return runs


@pytest.fixture(scope="module")
def chain(prefect_api, capture, tmp_path_factory) -> dict:
    """The three kill chains; the tail's store is used again by later tests."""
    from tests.media import write_video
    from tests.test_bad_inputs import orbit_frames
    from tests.test_flows import seed_upstream

    chains = {}
    tmp = tmp_path_factory.mktemp("head")
    (tmp / "dots").mkdir()
    video = write_video(tmp / "dots" / "sweep.mp4", orbit_frames(40))
    (tmp / "pipeline.yaml").write_text(json.dumps(CHEAP_POSES))
    args = {"video": str(video), "out": str(tmp / "out"), "config": str(tmp / "pipeline.yaml")}
    chains["head"] = {"store": tmp / "store",
                      "runs": run_chain(prefect_api, "head", args, tmp / "store", tmp)}
    for mode in ("middle", "tail"):
        tmp = tmp_path_factory.mktemp(mode)
        seeded = seed_upstream(str(tmp / "store"), capture, tmp)
        if mode == "middle":
            seeded = {"video": seeded["video"], "poses": seeded["poses"]}
        args = {"seeded": seeded, "scan": str(capture / "gt" / "mesh.ply"),
                "scan_landmarks": str(capture / "gt" / "landmarks.json")}
        chains[mode] = {"store": tmp / "store", "seeded": seeded,
                        "runs": run_chain(prefect_api, mode, args, tmp / "store", tmp)}
    return chains


@pytest.mark.slow
@pytest.mark.parametrize("mode", list(KILLS))
def test_a_worker_killed_in_any_stage_loses_only_that_stage(chain, mode):
    """Each rerun recomputes what the killed worker lost and no committed artifact; the
    last one finishes. Every recomputed artifact is byte for byte (timings aside) what the
    killed worker had computed."""
    runs, store = chain[mode]["runs"], open_store(chain[mode]["store"])
    lost: set[str] = set()
    for run in runs:
        assert run["code"] == (137 if run["fault"] else 0), (run["fault"], run["stderr"])
        computed, before, after = set(run["computed"]), run["before"], run["after"]
        assert not computed & set(before), run["fault"]  # nothing committed is recomputed
        assert {k: after[k] for k in before} == before  # ...or rewritten
        assert lost <= computed, (run["fault"], lost, computed)  # what was lost is redone
        lost = computed - set(after)
        if run["fault"]:
            stage = run["fault"].split(":")[0]
            assert any(k.startswith(f"{stage}-") for k in lost), run["fault"]
    keys = runs[-1]["keys"]
    last_stage = KILLS[mode][-1].split(":")[0]
    assert runs[-1]["computed"] == [keys["video" if last_stage == "input" else last_stage]]
    assert set(keys.values()) <= set(store.keys())
    for run in runs[:-1]:
        stage, work = run["fault"].split(":")[0], run["work"]
        if stage == "input":  # the file being ingested is the user's own: nothing to compare
            continue
        left = digests(work)
        same = [k for k in keys.values() if k.startswith(f"{stage}-")]
        if len(same) > 1:  # the depth maps: the one with the killed worker's file names
            same = [k for k in same if set(digests(store.get(k))) == set(left)]
        assert len(same) == 1, run["fault"]
        if stage == "poses":  # compared as cameras: float sums may differ in the last digits
            assert_same_cameras(work / "cameras.json", store.get(same[0]) / "cameras.json")
        else:
            assert digests(store.get(same[0])) == left, run["fault"]


def assert_same_cameras(a_path: Path, b_path: Path) -> None:
    """Two runs of the pose stage on the same keyframes agree up to the gauge (SfM's origin,
    orientation and scale are arbitrary; COLMAP's RANSAC and initial pair vary run to run):
    after a similarity alignment the camera path agrees to 0.1 % of its extent, the
    orientations to 0.1 degree, the focal length to 0.1 %."""
    import numpy as np

    from facecap_core.camera import camera_center, rotation_angle_deg
    from facecap_core.geometry import umeyama
    from facecap_core.pose.cameras_json import read_cameras_json

    a, b = (read_cameras_json(p) for p in (a_path, b_path))
    assert a.frame_indices == b.frame_indices
    assert abs(a.intrinsics.fx / b.intrinsics.fx - 1) < 1e-3
    rotations = [list(cams.R) for cams in (a, b)]
    centres = [np.array([camera_center(R, t) for R, t in zip(cams.R, cams.t)]) for cams in (a, b)]
    scale, R, t = umeyama(centres[1], centres[0], with_scale=True)  # b's world -> a's
    aligned = scale * centres[1] @ R.T + t
    assert np.abs(aligned - centres[0]).max() < 1e-3 * np.ptp(centres[0], axis=0).max()
    for Ra, Rb in zip(*rotations):
        assert rotation_angle_deg(Ra, Rb @ R.T) < 0.1


def test_a_process_killed_during_a_put_leaves_nothing_readable(tmp_path):
    """The commit itself is cut short (the process dies between two files): no manifest, no
    key, nothing a reader would take; the next put commits the whole artifact."""
    from facecap.tasks.store import artifact_key

    store_dir = tmp_path / "store"
    key = artifact_key("fusion", {}, {"x": 1}, "1")
    script = f"""
import os
from facecap.tasks.store import open_store

class DiesMidway:
    def read(self, size=-1):
        os._exit(137)

open_store({str(store_dir)!r}).put({key!r}, {{"a.ply": b"first file", "b.ply": DiesMidway()}},
                                    stage="fusion", inputs={{}}, config={{"x": 1}}, version="1")
"""
    proc = subprocess.run([sys.executable, "-c", script], cwd=ROOT, timeout=120,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert proc.returncode == 137
    store = open_store(store_dir)
    assert not store.exists(key) and store.keys() == []
    assert not (store_dir / "artifacts" / key).exists()
    store.put(key, {"a.ply": b"first file", "b.ply": b"second file"}, stage="fusion",
              inputs={}, config={"x": 1}, version="1")
    store.verify(key)
    assert store.read_bytes(key, "b.ply") == b"second file"


@pytest.fixture(scope="module")
def finished(chain):
    """The store the tail's kill chain finished, and the same tail flow in this process."""
    from tests.test_flows import make_tail_flow

    tail = chain["tail"]
    assert tail["runs"][-1]["code"] == 0, tail["runs"][-1]["stderr"]
    return {"store": str(tail["store"]), "seeded": tail["seeded"], "tail": make_tail_flow(),
            "keys": tail["runs"][-1]["keys"]}


@pytest.mark.slow
def test_a_corrupt_artifact_is_refused_and_recomputed_once_deleted(finished, capture):
    """A committed file damaged on disk is never read: the next stage refuses it with one
    line that says what to delete; deleted, it is recomputed (the same bytes) and nothing
    else is."""
    from facecap.tasks.graph import BY_NAME
    from facecap.tasks.runner import run_stage
    from tests.test_flows import run_tail, small_config

    store = open_store(finished["store"])
    fusion = finished["keys"]["fusion"]
    original = store.manifest(fusion).files
    cloud = Path(finished["store"]) / "artifacts" / fusion / "cloud.ply"
    data = bytearray(cloud.read_bytes())
    data[-10] ^= 0x01
    cloud.write_bytes(bytes(data))

    inputs = {"fusion": fusion, "coarse": finished["keys"]["coarse"],
              "frames": finished["keys"]["frames"]}
    config = small_config().fitting.model_copy(update={"iterations_per_level": 1})
    with pytest.raises(CorruptArtifactError) as caught:
        run_stage(finished["store"], BY_NAME["fitting"], inputs, config)
    message = str(caught.value)
    assert "\n" not in message and "cloud.ply" in message
    assert f"delete {Path(finished['store']) / 'artifacts' / fusion}" in message

    store.delete(fusion)
    keys, computed = run_tail(finished["tail"], finished["store"], finished["seeded"],
                              small_config(), capture)
    assert keys == finished["keys"]
    assert computed == {"fusion"}, computed
    assert store.manifest(fusion).files["cloud.ply"] == original["cloud.ply"]  # same bytes


@pytest.mark.slow
def test_a_transient_fault_is_retried_within_the_run(finished, capture, monkeypatch):
    """An I/O error in a stage (injected once) is retried by the task and the run finishes."""
    from facecap.tasks import runner
    from tests.test_flows import run_tail, small_config

    store = open_store(finished["store"])
    store.delete(finished["keys"]["views"])
    monkeypatch.setenv("FACECAP_FAULT", "views:1:oserror")
    monkeypatch.setattr(runner, "_FAULT_COUNTS", {})
    keys, computed = run_tail(finished["tail"], finished["store"], finished["seeded"],
                              small_config(), capture)
    assert keys == finished["keys"]
    assert runner._FAULT_COUNTS == {"views": 2}  # failed once, then computed
    assert computed == {"views"}, computed


def _restart_after_first_failure(server, flow_name: str, stop: threading.Event) -> None:
    """Start the S3 server again once a task of the flow waits for its retry."""
    import asyncio

    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import FlowFilter, FlowFilterName

    async def waiting() -> bool:
        async with get_client() as client:
            runs = await client.read_task_runs(
                flow_filter=FlowFilter(name=FlowFilterName(any_=[flow_name])))
            return any(r.state and r.state.name == "AwaitingRetry" for r in runs)

    while not stop.is_set():
        if asyncio.run(waiting()):
            server.start()
            return
        time.sleep(0.1)


@pytest.mark.slow
def test_a_store_outage_is_retried_and_then_succeeds(prefect_api, tmp_path, monkeypatch):
    """The S3 endpoint is down when a task first needs it (the server stopped, as in
    tests/test_store_s3.py); the task's retry finds it back and the flow completes."""
    import uuid

    import boto3
    import s3fs
    from prefect import flow

    from facecap.tasks.stages import call_ingest
    from tests.servers import final_task_runs
    from tests.test_store_s3 import CREDENTIALS, LocalS3

    server = LocalS3()
    server.start()
    for name in [n for n in os.environ if n.startswith(("AWS_", "FSSPEC_S3"))]:
        monkeypatch.delenv(name)
    for name, value in CREDENTIALS.items():
        monkeypatch.setenv(name, value)
    monkeypatch.setenv("AWS_ENDPOINT_URL_S3", server.url)
    monkeypatch.setenv("AWS_MAX_ATTEMPTS", "1")  # botocore gives up at once: Prefect retries
    monkeypatch.setenv("FACECAP_HOME", str(tmp_path / "home"))
    s3fs.S3FileSystem.clear_instance_cache()
    boto3.client("s3", region_name="us-east-1").create_bucket(Bucket="facecap-outage")
    video = tmp_path / "video.mp4"
    video.write_bytes(os.urandom(4096))
    store_url = "s3://facecap-outage/artifacts"
    flow_name = f"outage-{uuid.uuid4().hex[:8]}"

    @flow(name=flow_name)
    def ingest_during_an_outage() -> str:
        return call_ingest(store_url, video, "video.mp4", "outage")

    server.stop()
    stop = threading.Event()
    watcher = threading.Thread(target=_restart_after_first_failure,
                               args=(server, flow_name, stop))
    watcher.start()
    try:
        state = ingest_during_an_outage(return_state=True)
        key = state.result()
    finally:
        stop.set()
        watcher.join()
        s3fs.S3FileSystem.clear_instance_cache()

    [run] = final_task_runs(state.state_details.flow_run_id, count=1)
    assert run.run_count == 2 and run.state.name == "Completed"  # failed once, retried
    assert open_store(store_url).read_bytes(key, "video.mp4") == video.read_bytes()
    server.stop()
