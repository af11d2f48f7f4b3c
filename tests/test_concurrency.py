"""Concurrency: two workers run the dataset flow on the same captures at once.

A dataset of three captures (more than the two workers) of one recording: two subjects'
folders hold copies of the same video, so every capture flow of both workers asks for the
same artifacts at about the same time. The capture flows run for real from the video
(ingest, keyframes, frames, landmarks, views, depth maps, fusion, fitting); the pose and
coarse artifacts are the capture's ground truth, seeded into the store under the keys the
flows will ask for (the pose stage needs a larger capture than a test can render; see
tests/test_flows.py). Each worker is a separate process with the store's file locks as the
only coordination, and logs the key of every computation it starts.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from facecap.tasks.store import open_store
from facecap_core.pipeline import PipelineConfig
from tests.test_faults import (  # noqa: F401 - prefect_api is a fixture
    committed,
    computed_in,
    digests,
    finish,
    prefect_api,
    shared_capture,
    start_worker,
    worker_home,
)


@pytest.fixture(scope="module")
def capture(tmp_path_factory, ict_model) -> Path:
    return shared_capture(tmp_path_factory, ict_model)


def config_file(folder: Path) -> tuple[Path, PipelineConfig]:
    from tests.test_flows import small_config

    config = small_config()
    path = folder / "pipeline.json"  # JSON is YAML
    path.write_text(json.dumps(config.model_dump(mode="json")))
    return path, config


def seed_poses_and_coarse(store_url: str, video: Path, capture: Path, config: PipelineConfig,
                          tmp: Path) -> set[str]:
    """The capture's ground-truth poses and coarse mesh, stored under the keys the capture
    flow computes for ``video`` with ``config``; returns the seeded keys."""
    from facecap.tasks.graph import config_data, stage_key
    from tests.test_flows import seed_upstream

    gt = seed_upstream(store_url, capture, tmp)  # the files, under keys of their own
    store = open_store(store_url)
    # The settings models, as the flow passes them (their keys leave key-neutral settings out).
    section = {name: getattr(config, name) for name in ("keyframes", "poses", "landmarks", "coarse")}
    video_key = gt["video"]  # the same bytes as ``video``
    keyframes = stage_key("keyframes", {"video": video_key}, section["keyframes"])
    poses = stage_key("poses", {"video": video_key, "keyframes": keyframes}, section["poses"])
    landmarks = stage_key("landmarks", {"video": video_key, "poses": poses},
                          section["landmarks"])
    coarse = stage_key("coarse", {"landmarks": landmarks, "poses": poses}, section["coarse"])
    for stage, key, inputs in [("poses", poses, {"video": video_key, "keyframes": keyframes}),
                               ("coarse", coarse, {"landmarks": landmarks, "poses": poses})]:
        folder = store.get(gt[stage])
        store.put(key, {p.name: p for p in folder.iterdir() if p.name != "manifest.json"},
                  stage=stage, inputs=inputs, config=config_data(section[stage]),
                  version="ground truth")
    return {poses, coarse}


def dataset(root: Path, capture: Path) -> list[tuple[str, str]]:
    names = [("subject a", "take 1"), ("subject a", "take 2"), ("subject b", "take 1")]
    for subject, take in names:
        (root / subject).mkdir(parents=True, exist_ok=True)
        shutil.copyfile(capture / "video.mp4", root / subject / f"{take}.mp4")
    return names


def run_dataset(api: str, folder: Path, capture: Path, workers: int) -> dict:
    """``workers`` processes run reconstruct-dataset at once on one fresh, seeded store."""
    folder.mkdir()
    root, store = folder / "dataset", folder / "store"
    names = dataset(root, capture)
    config_path, config = config_file(folder)
    seeded = seed_poses_and_coarse(str(store), root / "subject a" / "take 1.mp4", capture,
                                   config, folder)
    before = set(committed(store))
    home = worker_home(folder)
    procs = [start_worker(api, "dataset", store, {"root": str(root),
                                                  "out": str(folder / f"out-{n}"),
                                                  "config": str(config_path)},
                          folder / f"computed-{n}.log", None, home) for n in range(workers)]
    results = [finish(p) for p in procs]
    return {"store": store, "names": names, "seeded": seeded, "before": before,
            "results": results, "computed": [computed_in(folder / f"computed-{n}.log")
                                             for n in range(workers)],
            "outs": [folder / f"out-{n}" for n in range(workers)]}


@pytest.fixture(scope="module")
def runs(prefect_api, capture, tmp_path_factory) -> dict:  # noqa: F811 - the fixture imported above
    tmp = tmp_path_factory.mktemp("concurrency")
    return {"together": run_dataset(prefect_api, tmp / "together", capture, workers=2),
            "serial": run_dataset(prefect_api, tmp / "serial", capture, workers=1)}


@pytest.mark.slow
def test_two_workers_compute_each_artifact_once(runs):
    together = runs["together"]
    for result in together["results"]:
        assert result.returncode == 0, result.stderr[-3000:]
    computed = [key for log in together["computed"] for key in log]
    assert computed, "the workers computed nothing"
    assert len(computed) == len(set(computed)), "an artifact was computed twice"
    new = set(committed(together["store"])) - together["before"]
    # Each run's page (pages.stored.store_page) says how that run went: one per capture run
    # and dataset run, not a computation to share.
    pages = {key for key in new if key.startswith("page-")}
    assert len(pages) >= 2
    new -= pages
    assert set(computed) == new  # and every new artifact was computed by one of them
    stages = {key.split("-")[0] for key in new}
    assert stages == {"keyframes", "frames", "landmarks", "views", "depth", "fusion",
                      "fitting"}
    # Which worker computes a key is a race; that both finish every capture is not.
    for out in together["outs"]:
        summary = json.loads((out / "dataset.json").read_text())
        assert summary["failed"] == {} and len(summary["done"]) == 3


@pytest.mark.slow
def test_results_are_identical_to_a_serial_run(runs):
    together, serial = runs["together"], runs["serial"]
    assert serial["results"][0].returncode == 0, serial["results"][0].stderr[-3000:]
    a, b = open_store(together["store"]), open_store(serial["store"])
    computed = [key for key in a.keys() if not key.startswith("page-")]  # pages: each run's
    assert computed == [key for key in b.keys() if not key.startswith("page-")]
    for key in computed:
        assert digests(a.get(key)) == digests(b.get(key)), key
    reference = serial["outs"][0]
    for out in together["outs"]:
        for subject, take in together["names"]:
            for name in ("mesh.ply", "cloud.ply", "cameras.json"):
                assert ((out / subject / take / name).read_bytes()
                        == (reference / subject / take / name).read_bytes()), (subject, take)
        assert (json.loads((out / "consistency.json").read_text())
                == json.loads((reference / "consistency.json").read_text()))
    [row] = json.loads((reference / "consistency.json").read_text())  # subject a's 2 takes
    assert row["max_mm"] == 0.0  # one recording, so one mesh
