"""The service's caching, fan-out and recovery, on a real Prefect server (test harness) and a
real local store.

The stages after the coarse mesh run for real on a small synthetic capture; the pose and
coarse artifacts are made from the capture's ground truth and put into the store like any
stage's output, so these tests judge the orchestration, not the upstream stages.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

# Every test here runs the tail of the pipeline on a real Prefect server.
pytestmark = pytest.mark.slow

from facecap.synthetic.config import SynthConfig
from facecap.tasks.store import open_store
from facecap_core.meshio import load_landmarks, load_mesh, save_landmarks
from facecap_core.pipeline import PipelineConfig

WIDTH, HEIGHT, FRAMES = 320, 180, 18
KEYFRAMES = list(range(5, 13))


@pytest.fixture(scope="module")
def capture(tmp_path_factory, ict_model):
    from facecap.synthetic import synthesize

    folder = tmp_path_factory.mktemp("capture") / "subject a"
    fps = FRAMES / 6.0
    config = SynthConfig(subject="ict:2", ict_model=ict_model, width=WIDTH, height=HEIGHT,
                         fps=fps, duration_s=6.0, exposure_fraction=0.25 * fps / 30, seed=2)
    synthesize(config, folder, progress=False)
    return folder


def small_config() -> PipelineConfig:
    return PipelineConfig.model_validate({
        "mvs": {"views": {"num_sources": 4},
                "depth": {"processing_width": WIDTH, "window_radius": 3, "iterations": 3}},
        # The short fit leaves self-intersections that relaxing them would spend half the
        # fit's time on (tests/fitting/test_sanity.py tests that step): not here.
        "fitting": {"stiffness": [50.0, 10.0, 2.0], "landmark_weight": [50.0, 10.0, 2.0],
                    "iterations_per_level": 2, "use_edges": False, "relax_folds": False},
    })


def _cameras_doc(intr, frames, indices, scale: float, units: str) -> dict:
    return {"intrinsics": intr.to_dict(), "units": units, "metric_scale": 1.0 / scale,
            "keyframes": [{"frame_index": i, "R": np.asarray(frames[i]["R"]).tolist(),
                           "t": (np.asarray(frames[i]["t"]) * scale).tolist()}
                          for i in indices]}


def seed_upstream(store_url: str, capture: Path, tmp: Path) -> dict[str, str]:
    """Store ground-truth pose and coarse artifacts; returns their keys and the video's."""
    from facecap.synthetic import load_gt_cameras
    from facecap.synthetic.ground_truth import coarse_from_gt
    from facecap.tasks.graph import stage_key
    from facecap.tasks.runner import ingest

    store = open_store(store_url)
    intr, frames = load_gt_cameras(capture / "gt" / "cameras.json")
    video = ingest(store_url, capture / "video.mp4", "video.mp4")
    poses = tmp / "poses"
    poses.mkdir()
    # The pose stage's units are arbitrary: 1/100 of a mm here.
    (poses / "cameras.json").write_text(json.dumps(
        _cameras_doc(intr, frames, KEYFRAMES, 0.01, "arbitrary")))
    keys = {"video": video}
    keys["poses"] = stage_key("poses", {"video": video}, {"ground_truth": True})
    store.put(keys["poses"], {"cameras.json": poses / "cameras.json"}, stage="poses",
              inputs={"video": video}, config={"ground_truth": True}, version="gt")
    coarse = tmp / "coarse"
    coarse.mkdir()
    mesh = load_mesh(capture / "gt" / "mesh.ply")
    import trimesh

    trimesh.Trimesh(coarse_from_gt(mesh.vertices, mesh.faces, seed=1), mesh.faces,
                    process=False).export(coarse / "coarse.ply")
    (coarse / "cameras.json").write_text(json.dumps(
        _cameras_doc(intr, frames, KEYFRAMES, 1.0, "mm")))
    save_landmarks(coarse / "landmarks3d.json", load_landmarks(capture / "gt" / "landmarks.json"))
    (coarse / "ears3d.json").write_text(json.dumps({"vertex_ids": [], "points": []}))
    keys["coarse"] = stage_key("coarse", {"poses": keys["poses"]}, {"ground_truth": True})
    store.put(keys["coarse"], {p.name: p for p in coarse.iterdir()}, stage="coarse",
              inputs={"poses": keys["poses"]}, config={"ground_truth": True}, version="gt")
    return keys


def make_tail_flow():
    from prefect import flow
    from prefect.task_runners import ThreadPoolTaskRunner

    from facecap.flows.capture import run_stages
    from facecap.tasks.graph import STAGES
    from facecap.tasks.stages import call_ingest

    @flow(name="tail", task_runner=ThreadPoolTaskRunner(max_workers=2))
    def tail(store: str, seeded: dict, config: dict, scan: str, scan_landmarks: str) -> dict:
        """The stages after the seeded coarse mesh; returns their keys, what computed and
        the flow run's id."""
        from prefect.runtime import flow_run

        cfg = PipelineConfig.model_validate(config)
        keys = dict(seeded)
        keys["scan"] = call_ingest(store, scan, Path(scan).name, "t")
        keys["scan_landmarks"] = call_ingest(store, scan_landmarks, Path(scan_landmarks).name)
        after = [s for s in STAGES if s.name not in ("keyframes", "poses", "landmarks",
                                                      "coarse")]
        runs = run_stages(store, keys, cfg, "t", after)
        return {"keys": keys, "computed": sorted(row for row, (_, new) in runs.items() if new),
                "flow_run_id": flow_run.id}

    return tail


def tail_result(tail, store_url, seeded, config, capture) -> dict:
    return tail(store_url, seeded, config.model_dump(mode="json"),
                str(capture / "gt" / "mesh.ply"), str(capture / "gt" / "landmarks.json"))


def run_tail(tail, store_url, seeded, config, capture):
    """The tail flow's keys, and the report rows it computed (the tasks' own word)."""
    result = tail_result(tail, store_url, seeded, config, capture)
    return result["keys"], set(result["computed"])


@pytest.fixture(scope="module")
def first_run(prefect_server, capture, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("flow")
    store_url = str(tmp / "store")
    seeded = seed_upstream(store_url, capture, tmp)
    tail = make_tail_flow()
    result = tail_result(tail, store_url, seeded, small_config(), capture)
    return {"store": store_url, "seeded": seeded, "tail": tail, "keys": result["keys"],
            "computed": set(result["computed"]), "flow_run_id": result["flow_run_id"]}


def test_tail_reconstructs_the_capture(first_run, capture):
    store = open_store(first_run["store"])
    keys = first_run["keys"]
    depth = [k for name, k in keys.items() if name.startswith("depth_")]
    assert first_run["computed"] == {"frames", "views", "fusion", "fitting", "evaluation",
                                     *(f"depth_{i:05d}" for i in KEYFRAMES)}
    assert len(depth) == len(KEYFRAMES)
    evaluation = json.loads((store.get(keys["evaluation"]) / "evaluation.json").read_text())
    # Ground-truth cameras at 320 px: the fitted mesh is within a few mm of the truth.
    assert evaluation["similarity"]["accuracy"]["median"] < 1.5
    mesh = load_mesh(store.get(keys["fitting"]) / "mesh.ply")
    from facecap_core.template import Template

    template = Template.default()
    assert len(mesh.vertices) == len(template.vertices)
    assert np.array_equal(mesh.faces, template.faces)


def _capture_report(first_run) -> dict:
    from facecap.flows.capture import _figures, _stage_report

    keys = first_run["keys"]
    runs = {name: (key, True) for name, key in keys.items()
            if name not in ("video", "scan", "scan_landmarks")}
    return {"subject": "subject a", "capture": "video (1)", "store": first_run["store"],
            "computed": len(runs), "cached": 0, "wall_seconds": 1.0, "until": "evaluation",
            "stages": _stage_report(first_run["store"], runs),
            "figures": _figures(first_run["store"], runs)}


def _publish_and_read_link(report: dict, out: Path, results: dict) -> tuple[str, str]:
    """Publish a capture run's UI artifacts as the capture flow does; the results link's
    address (from the markdown the UI shows) and its description."""
    from prefect import flow
    from prefect.client.schemas.filters import ArtifactFilter, ArtifactFilterKey

    from facecap.flows.ui import artifact_keys, publish_capture

    label = f"{report['subject']}/{report['capture']}"

    @flow(name="publish")
    def publish() -> None:
        publish_capture(report, out, label, results)

    publish()
    link_key = artifact_keys(label)[2]
    link = max(read_api(lambda c: c.read_artifacts(  # the latest version of the link
        artifact_filter=ArtifactFilter(key=ArtifactFilterKey(any_=[link_key])))),
        key=lambda artifact: artifact.created)
    text, address = link.data.rsplit("](", 1)
    assert text == "[results of subject a/video \\(1\\)" and address.endswith(")"), link.data
    return address[:-1], link.description


def test_the_ui_link_opens_the_capture_page(first_run, tmp_path, monkeypatch):
    """The run's ``index.html`` and ``mesh.glb``, exported and kept in the store as a capture
    run does, opened in headless Chromium through the link the Prefect UI shows (the page
    server of a folder store): the face is drawn, the heat map of its accuracy changes the
    picture, the cameras show, the figures are the report's, no console error."""
    from facecap.flows.capture import _export, _page
    from facecap.pages.server import address, page_server, serve_in_background
    from facecap.pages.stored import PAGE_NAME, store_page
    from facecap.tasks.outputs import ResultWriter
    from tests.browser import look_at_page
    from tests.test_page import SHOTS

    keys, report = first_run["keys"], _capture_report(first_run)
    out = tmp_path / "results (1)"
    with ResultWriter(out) as writer:
        results = _export(first_run["store"], keys, writer, tmp_path)
        page, _ = _page(first_run["store"], keys, report, results)
        report["page"] = {"key": store_page(open_store(first_run["store"]), report, page)}
        writer.add(PAGE_NAME, page)
        writer.commit()
    assert (out / "mesh.glb").stat().st_size > 0
    server = page_server(open_store(first_run["store"]), "127.0.0.1", 0)
    serve_in_background(server)
    monkeypatch.setenv("FACECAP_PAGES_URL", address(server))
    try:
        link, where = _publish_and_read_link(report, out, results)
        assert link.startswith(f"{address(server)}/artifacts/{report['page']['key']}/index.html?")
        assert where == "subject a/video (1): results (its page, for 24 h)"
        seen = look_at_page(link, SHOTS / "capture")
    finally:
        server.shutdown()
        server.server_close()
    assert seen["errors"] == [] and seen["ready"], seen
    assert seen["drawn"] > 0.2 and seen["accuracy_change"] > 3.0, seen
    assert seen["cameras_change"] > 0.2 and seen["keyframe_opened"], seen
    metric = report["figures"]["evaluation"]["metric"]["accuracy"]
    assert seen["figures"]["evaluation_metric"].startswith(
        f"mean {metric['mean']:.3f} mm, median {metric['median']:.3f} mm")


def test_a_rerun_s_page_takes_its_parts_from_the_store(first_run, tmp_path, monkeypatch):
    """The page's slow parts (the keyframes' images, the cloud's sample, the scan) are kept
    in the store under the run's stage keys, made from them: a rerun of the same artifacts
    gives the same page without decoding a keyframe, a run of other artifacts makes its
    own, and ``forget``'s walk down the inputs finds them. Parts with a hole (a keyframe
    image that could not be read) are not kept; damaged ones are made and kept anew."""
    import facecap.pages.capture as capture_page
    from facecap.flows.capture import _export, _page
    from facecap.pages.stored import PARTS_NAME, stored_parts
    from facecap.tasks.lifecycle import derived
    from facecap.tasks.outputs import ResultWriter

    store = open_store(first_run["store"])
    keys, report = first_run["keys"], _capture_report(first_run)
    key, _ = stored_parts(store, report)
    if store.exists(key):  # kept by another test's page: made here from the artifacts
        store.delete(key)

    def no_decoding(*args):
        raise AssertionError("a keyframe was decoded for parts the store holds")

    with ResultWriter(tmp_path / "out") as writer:
        results = _export(first_run["store"], keys, writer, tmp_path)
        with monkeypatch.context() as patch:  # a keyframe that cannot be read: not kept
            patch.setattr(capture_page, "_keyframe_image", lambda frames, index: None)
            _, holed = _page(first_run["store"], keys, report, results)
        assert holed is None and not store.exists(key)
        page, parts = _page(first_run["store"], keys, report, results)
        with monkeypatch.context() as patch:
            patch.setattr(capture_page, "_keyframe_images", no_decoding)
            again, parts_again = _page(first_run["store"], keys, report, results)
        assert (again, parts_again) == (page, parts) and parts == key
        assert b"data:image/jpeg;base64," in page  # the keyframes' images are in it
        (store.get(key) / PARTS_NAME).chmod(0o644)
        (store.get(key, verify=False) / PARTS_NAME).write_text("{")  # damaged: made again
        assert _page(first_run["store"], keys, report, results) == (page, parts)
        with monkeypatch.context() as patch:
            patch.setattr(capture_page, "_keyframe_images", no_decoding)
            assert _page(first_run["store"], keys, report, results) == (page, parts)
        other = {**report, "stages": {**report["stages"], "fusion": {
            **report["stages"]["fusion"], "key": keys["frames"]}}}
        _, other_parts = _page(first_run["store"], keys, other, results)
    assert parts.startswith("page-") and other_parts not in (None, parts)
    store.delete(other_parts)  # made from a report no run wrote
    assert store.manifest(parts).inputs == {name: info["key"]
                                            for name, info in report["stages"].items()}
    assert parts in derived(store, {keys["frames"]})


def test_without_a_page_server_the_ui_link_names_the_page_on_disk(first_run, tmp_path,
                                                                     monkeypatch):
    from facecap.pages.stored import store_page

    monkeypatch.delenv("FACECAP_PAGES_URL", raising=False)
    report = _capture_report(first_run)  # its page kept: only the server is missing
    report["page"] = {"key": store_page(open_store(first_run["store"]), report, b"a page")}
    out = tmp_path / "results (1)"
    out.mkdir()
    link, where = _publish_and_read_link(report, out, {})
    assert link == (out.resolve() / "index.html").as_uri()
    assert "set FACECAP_PAGES_URL and run `facecap pages`" in where


def test_rerun_is_all_cached(first_run, capture):
    """A rerun computes nothing, and its task runs say so in the UI: each stage's task run
    ends in a state named Reused, the depth maps all in one ("depth (N maps reused)")."""
    from tests.servers import final_task_runs

    store = open_store(first_run["store"])
    before = set(store.keys())
    result = tail_result(first_run["tail"], first_run["store"], first_run["seeded"],
                         small_config(), capture)
    assert result["keys"] == first_run["keys"]
    assert set(store.keys()) == before
    assert result["computed"] == []
    maps = [row for row in first_run["computed"] if row.startswith("depth_")]
    assert len(maps) == len(KEYFRAMES)
    count = len(first_run["computed"]) - len(maps) + 1 + 2  # each stage's and the two ingests
    every = final_task_runs(result["flow_run_id"], count)
    assert len(every) == count, sorted(run.name for run in every)
    stages = [run for run in every if not run.name.startswith("ingest")]
    assert stages and {run.state and run.state.name for run in stages} == {"Reused"}, \
        sorted((run.name, run.state and run.state.name) for run in stages)
    depth = [run.name for run in stages if run.name.startswith("depth")]
    assert depth == [f"depth ({len(maps)} maps reused) t"], depth


def test_fusion_change_recomputes_only_fusion_fitting_evaluation(first_run, capture):
    store = open_store(first_run["store"])
    config = small_config()
    config.mvs.fusion.max_normal_deg = 25.0
    before = set(store.keys())
    keys, computed = run_tail(first_run["tail"], first_run["store"], first_run["seeded"],
                              config, capture)
    new = set(store.keys()) - before
    assert sorted(k.split("-")[0] for k in new) == ["evaluation", "fitting", "fusion"]
    assert computed == {"fusion", "fitting", "evaluation"}


def test_lost_depth_maps_are_recomputed_alone(first_run, capture):
    """A run killed during MVS leaves some depth maps uncommitted: the rerun makes only
    those (a deleted artifact stands in for one that was never committed)."""
    store = open_store(first_run["store"])
    keys = first_run["keys"]
    lost = [keys[f"depth_{i:05d}"] for i in KEYFRAMES[2:4]]
    for key in lost:
        store.delete(key)
    new_keys, computed = run_tail(first_run["tail"], first_run["store"], first_run["seeded"],
                                  small_config(), capture)
    assert new_keys == keys
    assert computed == {f"depth_{i:05d}" for i in KEYFRAMES[2:4]}


def read_api(read):
    """``await read(client)`` on the test server."""
    import asyncio

    from prefect.client.orchestration import get_client

    async def main():
        async with get_client() as client:
            return await read(client)

    return asyncio.run(main())


def test_core_logs_are_in_the_runs_log(first_run):
    """What facecap_core's modules log at INFO is in the flow run's log in the API, each line
    in the task run it happened in: the depth maps from the task runner's threads too."""
    import time

    from prefect.client.schemas.filters import LogFilter, LogFilterFlowRunId

    log_filter = LogFilter(flow_run_id=LogFilterFlowRunId(any_=[first_run["flow_run_id"]]))
    for _ in range(60):  # the logs reach the API in batches
        core = [log for log in read_api(lambda c: c.read_logs(log_filter=log_filter))
                if log.name.startswith("facecap_core.")]
        if any("landmark RMS" in log.message for log in core):  # the last one
            break
        time.sleep(0.5)
    by_module: dict[str, list] = {}
    for log in core:
        by_module.setdefault(log.name, []).append(log)
    assert all(log.level >= 20 and log.task_run_id is not None for log in core)
    (fit,) = [log for log in by_module["facecap_core.fitting.run"]
              if log.message.startswith("fitted ")]
    assert "landmark RMS" in fit.message and "cloud targets" in fit.message
    (fusion,) = by_module["facecap_core.mvs.fusion"]
    assert f"from {len(KEYFRAMES)} depth maps" in fusion.message
    depth = by_module["facecap_core.mvs.depth"]
    assert sorted(int(log.message.split()[4].rstrip(":")) for log in depth) == KEYFRAMES
    assert len({log.task_run_id for log in depth}) == len(KEYFRAMES)  # each in its task run
    assert "MVS references" in by_module["facecap_core.mvs.views"][0].message
    # Every stage's task run says in its own words which stage it is (the UI's log list
    # shows messages alone): "t: depth[3] computed", "t: fitting computed".
    for _ in range(60):
        runs = [log.message for log in read_api(lambda c: c.read_logs(log_filter=log_filter))
                if log.name == "prefect.task_runs" and " computed" in log.message]
        if any(message.startswith("t: evaluation computed") for message in runs):  # the last
            break
        time.sleep(0.5)
    for stage in ("frames", "views", "fusion", "fitting", "evaluation",
                  *(f"depth[{i}]" for i in KEYFRAMES)):
        assert any(message.startswith(f"t: {stage} computed") for message in runs), (stage, runs)


def test_one_progress_artifact_reaches_100(first_run):
    from prefect.client.schemas.filters import (
        ArtifactFilter,
        ArtifactFilterFlowRunId,
        ArtifactFilterType,
    )

    found = read_api(lambda c: c.read_artifacts(artifact_filter=ArtifactFilter(
        flow_run_id=ArtifactFilterFlowRunId(any_=[first_run["flow_run_id"]]),
        type=ArtifactFilterType(any_=["progress"]))))
    assert len(found) == 1  # one for the run, the depth maps' steps in it
    assert float(found[0].data) == 100.0
    assert found[0].description.startswith("t: evaluation done")


def test_the_ui_link_opens_the_dataset_page_and_its_rows_open_the_captures(first_run,
                                                                          tmp_path, monkeypatch):
    """A dataset run's link in the UI opens the dataset page kept in the store, whose row
    opens the capture's page kept there (the page server of a folder store)."""
    import html
    import re
    import urllib.request

    from prefect import flow
    from prefect.client.schemas.filters import ArtifactFilter, ArtifactFilterKey

    from facecap.flows.ui import dataset_link_key, publish_dataset_page
    from facecap.pages.server import address, page_server, serve_in_background
    from facecap.pages.stored import store_page

    store = open_store(first_run["store"])
    report = _capture_report(first_run)
    page = b"<!doctype html><title>the capture's page</title>"
    report["page"] = {"key": store_page(store, report, page)}
    out = tmp_path / "dataset results"
    (out / "subject a" / "video (1)").mkdir(parents=True)
    (out / "subject a" / "video (1)" / "report.json").write_text(json.dumps(report))
    server = page_server(store, "127.0.0.1", 0)
    serve_in_background(server)
    monkeypatch.setenv("FACECAP_PAGES_URL", address(server))

    @flow(name="publish-dataset")
    def publish() -> None:
        publish_dataset_page(out, first_run["store"])

    try:
        publish()
        (link,) = read_api(lambda c: c.read_artifacts(artifact_filter=ArtifactFilter(
            key=ArtifactFilterKey(any_=[dataset_link_key(out)]))))
        address_shown = link.data.rsplit("](", 1)[1][:-1]
        assert address_shown.startswith(f"{address(server)}/artifacts/page-")
        with urllib.request.urlopen(address_shown, timeout=10) as answer:
            dataset_page = answer.read().decode()
        assert "subject a/video (1)" in dataset_page
        (row_link,) = set(re.findall(r'href="(http[^"]+)"', dataset_page))
        with urllib.request.urlopen(html.unescape(row_link), timeout=10) as answer:
            assert answer.read() == page
    finally:
        server.shutdown()
        server.server_close()
