"""The capture page (``index.html``, :mod:`flows.page`) and ``mesh.glb``, looked at in headless
Chromium (:mod:`tests.browser`): the face is drawn, the heat map and the cameras change the
picture, the figures shown are the report's, no console error. A synthetic head here (a
sphere in two colours, a ring of cameras); the page of a real capture run is looked at in
``tests/test_flows.py``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from facecap.flows.page import build_page, mesh_glb
from tests.browser import look_at_page

ROOT = Path(__file__).resolve().parents[1]
SHOTS = ROOT / "out" / "test-artifacts" / "page"
"""Where the screenshots are kept for a person to look at (out/ is not in git)."""

REPORT = {
    "subject": "anna <b>", "capture": "take 1", "computed": 12, "cached": 3,
    "wall_seconds": 81.5, "until": "evaluation",
    "stages": {"keyframes": {"cached": True, "seconds": 3.9},
               "depth_00001": {"cached": False, "seconds": 2.0},
               "depth_00002": {"cached": False, "seconds": 2.5}},
    "figures": {"metric_scale": 90.8987, "keyframes": 8, "focal_px": 503.84,
                "scale": {"sigma_pct": 4.0, "used": ["landmarks", "iris"],
                          "dropped": [{"name": "ears", "reason": "too few points"}]},
                "evaluation": {"metric": {"accuracy": {"mean": 0.2812, "median": 0.1634},
                                          "completion": {"mean": 0.97, "median": 0.407}}}},
}
EXPECTED = {
    "metric_scale": "90.9 mm per camera unit, ±4.0 % (1σ) from landmarks + iris; ears "
                    "dropped (too few points)",
    "keyframes": "8", "focal_px": "503.8 px",
    "evaluation_metric": "mean 0.281 mm, median 0.163 mm; completion mean 0.970 mm, median "
                         "0.407 mm",
}


def _look_at(camera_centre: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera (OpenCV: z forward, y down) of a camera at ``camera_centre``."""
    z = (target - camera_centre) / np.linalg.norm(target - camera_centre)
    x = np.cross([0.0, -1.0, 0.0], z)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    return R, -R @ camera_centre


@pytest.fixture(scope="module")
def results(tmp_path_factory) -> dict[str, Path]:
    """A head-sized sphere (the subject's left red, right blue), 8 cameras on an arc in
    front of it, a cloud on its surface."""
    import cv2

    folder = tmp_path_factory.mktemp("results")
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=80.0)
    colours = np.where(sphere.vertices[:, :1] > 0, [[220, 40, 40, 255]], [[40, 40, 220, 255]])
    trimesh.Trimesh(sphere.vertices, sphere.faces, vertex_colors=colours.astype(np.uint8),
                    process=False).export(folder / "mesh.ply")
    keyframes = []
    for angle in np.radians(np.linspace(-60, 60, 8)):
        R, t = _look_at(np.array([400 * np.sin(angle), 0.0, 400 * np.cos(angle)]), np.zeros(3))
        keyframes.append({"frame_index": len(keyframes), "R": R.tolist(), "t": t.tolist()})
    (folder / "cameras.json").write_text(json.dumps({
        "units": "mm", "keyframes": keyframes,
        "intrinsics": {"width": 640, "height": 360, "fx": 500.0, "fy": 500.0, "cx": 320.0,
                       "cy": 180.0}}))
    (folder / "frames").mkdir()
    for k in keyframes:  # what each camera saw: a plain picture is enough here
        cv2.imwrite(str(folder / "frames" / f"frame_{k['frame_index']:06d}.png"),
                    np.full((360, 640, 3), 30 * k["frame_index"], np.uint8))
    points = trimesh.sample.sample_surface(sphere, 5000, seed=0)[0]
    trimesh.PointCloud(points, colors=np.full((len(points), 4), 120, np.uint8)).export(
        folder / "cloud.ply")
    return {name: folder / name for name in ("mesh.ply", "cameras.json", "cloud.ply", "frames")}


def _accuracy(results) -> np.ndarray:
    """A heat map that differs from the colours: 0 mm at the top, 5 mm at the bottom."""
    vertices = trimesh.load(results["mesh.ply"], process=False).vertices
    return (80.0 - vertices[:, 1]) / 32.0


def test_the_page_shows_the_face_the_heat_map_the_cameras_and_the_figures(results, tmp_path):
    page = tmp_path / "index.html"
    page.write_bytes(build_page(REPORT, results, mesh_glb(results["mesh.ply"]),
                                _accuracy(results), results["frames"]))
    assert page.stat().st_size < 15 * 2**20
    seen = look_at_page(page, SHOTS / "synthetic")
    assert seen["errors"] == []
    assert seen["ready"]
    assert seen["drawn"] > 0.3, seen  # the sphere fills the middle of the view
    assert seen["accuracy_change"] > 5.0, seen
    assert seen["cameras_change"] > 0.2, seen
    assert seen["keyframe_opened"], seen  # a click on a camera shows what it saw
    assert seen["figures"] == EXPECTED
    assert "anna &lt;b&gt;" in page.read_text()  # names are text, never markup


def test_a_page_without_its_mesh_or_its_figures_is_seen_to_be_so(results, tmp_path):
    """What the test above asserts fails where it should: a run that made no mesh shows no
    viewer (and says why); a report without figures shows none."""
    no_mesh = tmp_path / "no-mesh.html"
    no_mesh.write_bytes(build_page({**REPORT, "until": "poses"}, results, None))
    seen = look_at_page(no_mesh)
    assert not seen["ready"]
    assert "made no mesh" in no_mesh.read_text()
    no_figures = tmp_path / "no-figures.html"
    no_figures.write_bytes(build_page({**REPORT, "figures": {}}, results,
                                      mesh_glb(results["mesh.ply"])))
    seen = look_at_page(no_figures)
    assert seen["ready"] and seen["figures"] == {}
    assert seen["accuracy_change"] is None  # no scan, no heat map switch


def test_the_glb_holds_the_mesh_and_its_colours(results):
    import io

    ply = trimesh.load(results["mesh.ply"], process=False)
    glb = trimesh.load(io.BytesIO(mesh_glb(results["mesh.ply"])), file_type="glb",
                       force="mesh", process=False)
    assert np.allclose(glb.vertices, ply.vertices, atol=1e-4)
    assert np.array_equal(glb.faces, ply.faces)
    assert np.array_equal(glb.visual.vertex_colors, ply.visual.vertex_colors)


def _dataset_results(out: Path, results: dict[str, Path]) -> None:
    """OUT of two subjects: anna/take1 reconstructed and evaluated three nights (the last
    one flagged it), bob/take1 failed."""
    import shutil

    import cv2

    folder = out / "anna" / "take1"
    folder.mkdir(parents=True)
    shutil.copy(results["mesh.ply"], folder / "mesh.ply")
    (folder / "report.json").write_text(json.dumps(REPORT))
    (folder / "index.html").write_text("<!doctype html><title>anna/take1</title>")
    cv2.imwrite(str(folder / "preview.png"), np.full((320, 960, 3), 90, np.uint8))
    (out / "evaluations").mkdir()
    for night, median in enumerate((0.20, 0.21, 0.35)):
        score = {"accuracy": {"mean": median, "median": median},
                 "completion": {"mean": 1.0, "median": 0.5}}
        flagged = [{"capture": "anna/take1", "measure": "accuracy_median"}] if night == 2 else []
        (out / "evaluations" / f"2026010{night + 1}T020000000000Z.json").write_text(json.dumps(
            {"captures": {"anna/take1": score}, "regressions": flagged}))


def test_the_dataset_page_lists_each_capture_with_its_status_and_history(results, tmp_path):
    from facecap.flows.dataset_page import build_dataset_page
    from tests.browser import chromium

    out = tmp_path / "results"
    _dataset_results(out, results)
    page_file = out / "index.html"
    page_file.write_bytes(build_dataset_page(
        out, [("bob", "take1"), ("anna", "take1")], {"bob/take1": "no face <found>"}))
    with chromium() as browser:
        page = browser.new_page()
        errors = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(page_file.as_uri())
        rows = page.query_selector_all("tbody tr")
        shown = {r.get_attribute("data-capture"): r.inner_text() for r in rows}
        assert set(shown) == {"anna/take1", "bob/take1"}
        assert "regressed" in shown["anna/take1"]
        assert "90.9" in shown["anna/take1"]  # its report's metric scale
        assert "0.350 mm" in shown["anna/take1"]  # the last night's accuracy
        assert page.query_selector("tr[data-capture='bob/take1'] a") is None  # no page
        assert "failed: no face <found>" in shown["bob/take1"]
        assert page.get_attribute("tr[data-capture='anna/take1'] a", "href") == \
            "anna/take1/index.html"
        assert page.query_selector("tr[data-capture='anna/take1'] svg polyline")
        assert page.query_selector("tr[data-capture='anna/take1'] img")
        order = lambda: [r.get_attribute("data-capture")  # noqa: E731
                         for r in page.query_selector_all("tbody tr")]
        page.click("th:nth-child(2)")  # by name
        assert order() == ["anna/take1", "bob/take1"]
        page.click("th:nth-child(2)")  # and back
        assert order() == ["bob/take1", "anna/take1"]
        page.screenshot(path=str(SHOTS / "dataset.png"))
    assert errors == []


def test_the_dataset_page_loses_a_forgotten_subject(results, tmp_path):
    """After ``facecap forget`` removed a subject's results (and its entries in
    dataset.json), the dataset page is written again from what OUT holds: no row, no
    thumbnail of that subject's face."""
    import shutil

    from facecap.flows.dataset_page import build_dataset_page, rewrite_dataset_page

    out = tmp_path / "results"
    _dataset_results(out, results)
    shutil.copytree(out / "anna", out / "carl")
    (out / "dataset.json").write_text(json.dumps({"failed": {"bob/take1": "no face"}}))
    (out / "index.html").write_bytes(build_dataset_page(
        out, [("anna", "take1"), ("bob", "take1"), ("carl", "take1")], {"bob/take1": "no face"}))
    shutil.rmtree(out / "anna")  # what forget removes
    rewrite_dataset_page(out)
    text = (out / "index.html").read_text()
    assert 'data-capture="anna/take1"' not in text
    assert 'data-capture="carl/take1"' in text and 'data-capture="bob/take1"' in text
    assert text.count("data:image/png") == 1  # carl's thumbnail alone
