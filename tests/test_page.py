"""The capture page (``index.html``, :mod:`pages.capture`) and ``mesh.glb``, looked at in headless
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

from facecap.pages.capture import build_page, mesh_glb
from tests.browser import BACKGROUND, look_at_page, settled

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
    "ears": "nothing is known about the ears: this run's report has no ear checks",
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
    from facecap.pages.dataset import build_dataset_page
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

    from facecap.pages.dataset import build_dataset_page, rewrite_dataset_page

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


def _full_report() -> dict:
    """A report as a full run writes it: every stage (so that the figures and the stage table
    make the column beside the view taller than a laptop's screen), 40 depth maps."""
    stages = {name: {"cached": False, "seconds": 10.0 + i} for i, name in enumerate(
        ("video", "frames", "keyframes", "poses", "landmarks", "coarse", "views", "fusion",
         "fitting", "scan", "scan_landmarks", "evaluation"))}
    stages |= {f"depth_{k:05d}": {"cached": False, "seconds": 3.0} for k in range(40)}
    score = {**REPORT["figures"]["evaluation"]["metric"],
             "ears": {"accuracy": {"mean": 1.2, "median": 0.9},
                      "completion": {"mean": 2.5, "median": 1.7}}}
    figures = {**REPORT["figures"], "coverage": {"yaw_min_deg": -86.0, "yaw_max_deg": 88.5,
                                                 "yaw_span_deg": 174.5},
               "roughness": {"bent_share_pct": 2.7, "bent_deg": 20, "median_bend_deg": 1.4},
               "ears": {"left": {"used": True, "points": 20}, "right": {"used": True,
                                                                       "points": 18}},
               "mesh_sanity": {"flipped": 0, "stretched_edges": 0,
                               "self_intersecting_pairs": 0, "ok": True},
               "cloud_noise": {"noise_mm": 0.09, "reference_mm": 0.12},
               "evaluation": {"similarity": score, "metric": score}}
    return {**REPORT, "stages": stages, "figures": figures}


def _opened(browser, page_file: Path, width: int = 1100, height: int = 700):
    """``page_file`` open in a page of that size, its viewer ready."""
    page = browser.new_page(viewport={"width": width, "height": height})
    page.goto(page_file.as_uri())
    page.wait_for_function("window.facecap && window.facecap.ready", timeout=60_000)
    return page


def _in_sight(page, selector: str) -> bool:
    """Whether the element is shown and wholly inside the window, as the page is scrolled."""
    box = page.evaluate(f"(() => {{ const e = document.querySelector({json.dumps(selector)}); "
                        "if (!e || e.hidden) return null; const r = e.getBoundingClientRect(); "
                        "return [r.top, r.bottom, r.left, r.right, innerHeight, innerWidth]; })()")
    return box is not None and box[0] >= 0 and box[1] <= box[4] and box[2] >= 0 \
        and box[3] <= box[5] and box[1] > box[0]


@pytest.mark.parametrize("size", [(1280, 800), (1366, 768)])
def test_the_colour_bar_is_in_sight_on_a_laptop_whatever_the_wheel_does(results, tmp_path,
                                                                         size):
    """At a laptop's size, the heat map's colour bar is on the screen as the page opens,
    after the wheel zoomed over the view, and after the page scrolled to its last figures."""
    from tests.browser import chromium

    page_file = tmp_path / "index.html"
    page_file.write_bytes(build_page(_full_report(), results, mesh_glb(results["mesh.ply"]),
                                     _accuracy(results), results["frames"]))
    with chromium() as browser:
        page = _opened(browser, page_file, *size)
        assert page.evaluate("document.documentElement.scrollHeight") > size[1]  # it scrolls
        page.click("[data-mode=accuracy]")
        assert _in_sight(page, "#colourbar")
        view = page.locator("#canvas").bounding_box()
        page.mouse.move(view["x"] + view["width"] / 2, view["y"] + view["height"] / 2)
        for _ in range(5):
            page.mouse.wheel(0, 300)
            page.wait_for_timeout(50)
        assert _in_sight(page, "#colourbar")
        page.mouse.move(size[0] - 100, size[1] / 2)  # over the figures
        page.mouse.wheel(0, 5000)
        page.wait_for_function("scrollY > 0")  # the page scrolled to its last rows
        assert _in_sight(page, "#colourbar")
        assert _in_sight(page, "[data-stage=depth]")
        page.screenshot(path=str(SHOTS / f"colour-bar-{size[0]}x{size[1]}.png"))


def test_the_colour_bar_names_its_protocol_and_each_mm(results, tmp_path):
    from tests.browser import chromium

    page_file = tmp_path / "index.html"
    page_file.write_bytes(build_page(REPORT, results, mesh_glb(results["mesh.ply"]),
                                     _accuracy(results)))
    with chromium() as browser:
        page = _opened(browser, page_file)
        page.click("[data-mode=accuracy]")
        text = page.inner_text("#colourbar")
        assert "metric protocol" in text and "not scored" in text
        ticks = page.query_selector_all("#colourbar .ticks span")
        assert [t.inner_text() for t in ticks] == ["0", "1", "2", "3", "4", "≥ 5 mm"]
        ramp = page.locator("#colourbar .ramp").bounding_box()
        for k, tick in enumerate(ticks):  # each label sits under its place on the ramp
            box = tick.bounding_box()  # the ends' labels aligned with the ends
            at = box["x"] + box["width"] * (0 if k == 0 else 1 if k == 5 else 0.5)
            assert abs(at - (ramp["x"] + ramp["width"] * k / 5)) < 2, (k, box, ramp)


def test_plain_is_grey(results, tmp_path):
    from tests.browser import _pixels, chromium

    page_file = tmp_path / "index.html"
    page_file.write_bytes(build_page(REPORT, results, mesh_glb(results["mesh.ply"])))
    with chromium() as browser:
        page = _opened(browser, page_file)
        page.click("[data-mode=plain]")
        settled(page)
        shot = _pixels(page.locator("#canvas").screenshot())
        h, w = shot.shape[:2]
        middle = shot[h // 3: 2 * h // 3, w // 3: 2 * w // 3].reshape(-1, 3)
        drawn = middle[np.abs(middle - 244).sum(axis=1) > 30]
        assert len(drawn) > 0.5 * len(middle)
        assert np.median(drawn.max(axis=1) - drawn.min(axis=1)) < 4  # no hue, just shading


WARNED = {
    "mesh_sanity": {"triangles": 20000, "flipped": 2, "degenerate": 0, "stretched_edges": 0,
                    "max_edge_stretch": 1.9, "self_intersecting_pairs": 314, "ok": False},
    "dropped_keyframes": [{"frame_index": 12, "reason": "not registered by structure from "
                           "motion"}, {"frame_index": 40, "reason": "not registered by "
                                       "structure from motion"}],
    "coverage": {"yaw_min_deg": -10.0, "yaw_max_deg": 65.0, "yaw_span_deg": 75.0},
    "cloud_noise": {"noise_mm": 0.31, "reference_mm": 0.12, "weight": 0.15},
}


def test_the_report_s_warnings_are_on_the_page(results, tmp_path):
    """A mesh that fails its checks, keyframes left out, a narrow sweep and a noisy cloud
    are each said in words above the figures; a report without ear checks says that nothing
    is known of the ears; the ears' scores are shown where they were scored."""
    from tests.browser import chromium

    figures = {**REPORT["figures"], **WARNED}
    figures["evaluation"] = {"metric": {
        **REPORT["figures"]["evaluation"]["metric"],
        "ears": {"accuracy": {"mean": 1.234, "median": 0.987},
                 "completion": {"mean": 2.5, "median": 1.75}}}}
    warned, clean = tmp_path / "warned.html", tmp_path / "clean.html"
    warned.write_bytes(build_page({**REPORT, "figures": figures}, results,
                                  mesh_glb(results["mesh.ply"])))
    clean_figures = {**_full_report()["figures"], "mesh_sanity": {**WARNED["mesh_sanity"],
                     "flipped": 0, "self_intersecting_pairs": 0, "ok": True},
                     "dropped_keyframes": [], "cloud_noise": {"noise_mm": 0.09,
                                                              "reference_mm": 0.12}}
    clean.write_bytes(build_page({**REPORT, "figures": clean_figures}, results,
                                 mesh_glb(results["mesh.ply"])))
    with chromium() as browser:
        page = _opened(browser, warned)
        shown = {li.get_attribute("data-warning"): li.inner_text()
                 for li in page.query_selector_all("#warnings li")}
        assert set(shown) == {"mesh_sanity", "dropped_keyframes", "coverage", "cloud_noise"}
        assert all(_in_sight(page, f"[data-warning={key}]") for key in shown)  # no scrolling
        assert "314 self-intersecting triangle pairs, 2 flipped triangles" in \
            shown["mesh_sanity"]
        assert "2 of 10 keyframes" in shown["dropped_keyframes"] and "12, 40" in \
            shown["dropped_keyframes"]
        assert "75°" in shown["coverage"]
        assert "0.310 mm" in shown["cloud_noise"] and "0.12 mm" in shown["cloud_noise"]
        figure = lambda key: page.inner_text(f"[data-figure={key}]")  # noqa: E731
        assert figure("ears").startswith("nothing is known about the ears")
        assert figure("ears_metric") == ("mean 1.234 mm, median 0.987 mm; completion mean "
                                         "2.500 mm, median 1.750 mm")
        assert figure("mesh_sanity").startswith("failed: 314 self-intersecting")
        assert figure("keyframes") == "8 registered, 2 left out (frames 12, 40)"
        page = _opened(browser, clean)
        assert page.query_selector("#warnings") is None
        assert page.inner_text("[data-figure=ears]") == "left 20 points; right 18 points"
        assert page.inner_text("[data-figure=mesh_sanity]").startswith("passed")


def test_a_run_stopped_early_says_what_it_made_and_offers_no_dead_view(results, tmp_path):
    """``--until keyframes``: no mesh, so no view and no buttons that would do nothing; the
    page says where the run stopped and what it made."""
    from tests.browser import chromium

    report = {**REPORT, "until": "keyframes", "figures": {},
              "stages": {"video": {"cached": True, "seconds": 0.2},
                         "frames": {"cached": False, "seconds": 4.1},
                         "keyframes": {"cached": False, "seconds": 3.9}}}
    page_file = tmp_path / "index.html"
    page_file.write_bytes(build_page(report, results, None))
    with chromium() as browser:
        page = browser.new_page(viewport={"width": 1280, "height": 800})
        errors = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(page_file.as_uri())
        assert page.query_selector_all("button, canvas") == []
        said = page.inner_text("#no-mesh")
        assert "stopped after keyframes" in said and "--until keyframes" in said
        assert "video, frames, keyframes" in said
        assert [r.get_attribute("data-stage") for r in
                page.query_selector_all("#stages tbody tr")] == ["video", "frames", "keyframes"]
        assert _in_sight(page, "#no-mesh")
    assert errors == []


def test_the_stage_table_has_a_header_and_says_a_reused_stage_took_no_time(results, tmp_path):
    from tests.browser import chromium

    report = {**REPORT, "stages": {**REPORT["stages"],
                                   "depth_00003": {"cached": True, "seconds": 50.0}}}
    page_file = tmp_path / "index.html"
    page_file.write_bytes(build_page(report, results, mesh_glb(results["mesh.ply"])))
    with chromium() as browser:
        page = _opened(browser, page_file)
        assert [th.inner_text() for th in page.query_selector_all("#stages thead th")] == \
            ["stage", "this run", "time"]
        cells = lambda stage: [td.inner_text() for td in  # noqa: E731
                               page.query_selector_all(f"[data-stage={stage}] td")]
        assert cells("keyframes") == ["keyframes", "reused", "(3.9 s when computed)"]
        # The reused map's old seconds are not this run's: 2.0 + 2.5 s over the two made.
        assert cells("depth") == ["depth", "2 of 3 maps computed",
                                  "4.5 s summed over the maps (made side by side)"]


def test_the_dataset_page_says_a_capture_stopped_before_its_mesh(results, tmp_path):
    """A capture run with ``--until keyframes`` is neither done nor failed: its row says
    where it stopped."""
    from facecap.pages.dataset import build_dataset_page
    from tests.browser import chromium

    out = tmp_path / "results"
    _dataset_results(out, results)
    folder = out / "carl" / "take1"
    folder.mkdir(parents=True)
    (folder / "report.json").write_text(json.dumps(
        {**REPORT, "until": "keyframes", "figures": {},
         "stages": {"keyframes": {"cached": False, "seconds": 3.9}}}))
    page_file = out / "index.html"
    page_file.write_bytes(build_dataset_page(out, [("anna", "take1"), ("carl", "take1")]))
    with chromium() as browser:
        page = browser.new_page()
        page.goto(page_file.as_uri())
        status = lambda name: page.inner_text(  # noqa: E731
            f"tr[data-capture='{name}'] td:nth-child(3)")
        assert status("carl/take1") == "stopped after keyframes: no mesh"
        assert status("anna/take1") == "regressed"


def _shot(page) -> np.ndarray:
    from tests.browser import _pixels

    settled(page)
    return _pixels(page.locator("#canvas").screenshot())


def test_the_inside_of_an_open_mesh_is_drawn(tmp_path):
    """A bowl opening towards the viewer (as the fitted mesh is open at the neck): its inside,
    the triangles' back, is drawn, not a hole."""
    from tests.browser import chromium

    sphere = trimesh.creation.icosphere(subdivisions=4, radius=80.0)
    keep = (sphere.vertices[sphere.faces][:, :, 2] < 10.0).all(axis=1)
    bowl = trimesh.Trimesh(sphere.vertices, sphere.faces[keep], process=False)
    bowl.remove_unreferenced_vertices()
    bowl.visual.vertex_colors = np.tile([[200, 150, 120, 255]], (len(bowl.vertices), 1))
    bowl.export(tmp_path / "mesh.ply")
    page_file = tmp_path / "index.html"
    page_file.write_bytes(build_page(REPORT, {"mesh.ply": tmp_path / "mesh.ply"},
                                     mesh_glb(tmp_path / "mesh.ply")))
    with chromium() as browser:
        page = _opened(browser, page_file)  # looking along -z, into the bowl
        for mode in ("colour", "plain"):
            page.click(f"[data-mode={mode}]")
            shot = _shot(page)
            h, w = shot.shape[:2]
            middle = shot[h // 3: 2 * h // 3, w // 3: 2 * w // 3]
            assert (np.abs(middle - BACKGROUND).sum(axis=2) > 30).mean() > 0.9, mode


def test_hiding_the_cameras_brings_the_view_back(results, tmp_path):
    """Showing the cameras steps the view back to see them; hiding them again steps it
    forwards to where it was."""
    from tests.browser import chromium

    page_file = tmp_path / "index.html"
    page_file.write_bytes(build_page(REPORT, results, mesh_glb(results["mesh.ply"]),
                                     frames=results["frames"]))
    with chromium() as browser:
        page = _opened(browser, page_file)
        before = _shot(page)
        page.click("[data-toggle=cameras]")
        assert np.abs(_shot(page) - before).mean() > 5.0  # stepped back: a smaller head
        page.click("[data-toggle=cameras]")
        assert np.abs(_shot(page) - before).mean() < 0.5


def test_a_scored_capture_s_thumbnail_is_its_front_view(results, tmp_path):
    """The preview of a scored capture is the heat map (three square views over a colour
    bar): its row shows the front view, square, not the whole strip shrunk."""
    import cv2

    from facecap.pages.dataset import THUMB_WIDTH, build_dataset_page
    from facecap_core.evaluation import COLORBAR_HEIGHT
    from tests.browser import chromium

    out = tmp_path / "results"
    _dataset_results(out, results)
    heat_map = np.full((480 + COLORBAR_HEIGHT, 3 * 480, 3), 255, np.uint8)
    heat_map[:480, :480] = (200, 60, 40)  # the front view
    cv2.imwrite(str(out / "anna" / "take1" / "preview.png"), heat_map)
    page_file = out / "index.html"
    page_file.write_bytes(build_dataset_page(out, [("anna", "take1")]))
    with chromium() as browser:
        page = browser.new_page()
        page.goto(page_file.as_uri())
        size = page.evaluate("(() => { const i = document.querySelector("
                             "\"tr[data-capture='anna/take1'] img\"); "
                             "return [i.naturalWidth, i.naturalHeight]; })()")
        assert size == [THUMB_WIDTH, THUMB_WIDTH]


def test_the_cloud_can_be_seen_alone(results, tmp_path):
    """With the cloud shown, the Mesh switch hides the mesh: the cloud's grey points alone,
    none of the sphere's red or blue; on again, the mesh is back."""
    from tests.browser import chromium

    page_file = tmp_path / "index.html"
    page_file.write_bytes(build_page(REPORT, results, mesh_glb(results["mesh.ply"])))

    def coloured(shot: np.ndarray) -> float:
        """The share of the view's middle (under no button) in the sphere's colours."""
        h, w = shot.shape[:2]
        middle = shot[h // 4: 3 * h // 4, w // 4: 3 * w // 4]
        return float(((middle.max(axis=2) - middle.min(axis=2)) > 60).mean())

    with chromium() as browser:
        page = _opened(browser, page_file)
        page.click("[data-toggle=cloud]")
        both = _shot(page)
        assert coloured(both) > 0.1
        page.click("[data-toggle=mesh]")
        assert page.get_attribute("[data-toggle=mesh]", "aria-pressed") == "false"
        alone = _shot(page)
        h, w = alone.shape[:2]
        middle = alone[h // 4: 3 * h // 4, w // 4: 3 * w // 4]
        assert coloured(alone) < 0.001
        drawn = np.abs(middle - 244).sum(axis=2) > 30  # the cloud's grey points
        assert 0.02 < drawn.mean() < 0.9, drawn.mean()
        page.click("[data-toggle=mesh]")
        assert np.abs(_shot(page) - both).mean() < 0.5


def test_each_part_s_support_by_its_cloud_is_said_in_words(results):
    """``figures.parts`` (the fitting stage's reference-free figures) is one figure: each
    supported part's distance from its cloud, the cloud under it and its landmarks, and the
    parts the cloud does not support named as the template's shape."""
    from facecap.pages.figures import figure_rows

    parts = {"nose": {"supported": True, "supported_share": 0.72, "mesh_to_cloud_mm": -0.309,
                      "mesh_to_cloud_abs_mm": 0.748, "cloud_noise_mm": 0.1816,
                      "landmark_to_cloud_mm": 1.458},
             "ears": {"supported": False, "supported_share": 0.103,
                      "mesh_to_cloud_mm": 0.386}}
    report = {**REPORT, "figures": {**REPORT["figures"], "parts": parts}}
    text = dict((key, text) for key, _, text in figure_rows(report))["parts"]
    assert text == ("nose: mesh -0.31 mm from its cloud (typically 0.75 mm), 72 % under "
                    "cloud, cloud noise 0.18 mm, landmarks 1.46 mm off the cloud; shaped by "
                    "the template, not the capture (too little cloud): ears (10 % under cloud)")
    page = build_page(report, results, mesh_glb(results["mesh.ply"])).decode()
    assert 'data-figure="parts"' in page or "data-figure=parts" in page
    assert "1.46 mm off the cloud" in page


def test_the_camera_solve_is_said_in_words_and_odd_values_are_left_out(results):
    """The pose stage's ``solve`` figures (field of view, principal point, reprojection
    error, track length, the views' turn against the tracker's) are one row; a value that
    is not a finite number (a report is anyone's to write) is left out, not shown."""
    from facecap.pages.figures import figure_rows

    solve = {"focal_px": 298.6, "principal_point_px": [120.4, 158.7],
             "field_of_view_deg": [43.7, 56.4], "reprojection_px": {"median": 0.412, "rms": 0.6},
             "track_length": 4.25, "turn_deg": 143.2, "tracked_turn_deg": 141.0}
    report = {**REPORT, "figures": {**REPORT["figures"], "solve": solve}}
    text = dict((key, text) for key, _, text in figure_rows(report))["solve"]
    assert text == ("field of view 44° × 56°; principal point (120.4, 158.7) px; reprojection "
                    "0.41 px median; points seen by 4.2 views on average; views turn 143° "
                    "along the sweep (the tracker's 141°)")
    odd = {**solve, "principal_point_px": ["<b>", 1], "track_length": float("nan"),
           "reprojection_px": "x", "tracked_turn_deg": True}
    report = {**REPORT, "figures": {**REPORT["figures"], "solve": odd}}
    text = dict((key, text) for key, _, text in figure_rows(report))["solve"]
    assert text == "field of view 44° × 56°; views turn 143° along the sweep"
    page = build_page(report, results, mesh_glb(results["mesh.ply"])).decode()
    assert "views turn 143° along the sweep" in page
    # A principal point held at the centre is said to be; only a true flag says so.
    for flag, said in ((True, True), (False, False), ("yes", False)):
        held = {**solve, "principal_point_px": [119.5, 159.5], "principal_point_held": flag}
        report = {**REPORT, "figures": {**REPORT["figures"], "solve": held}}
        text = dict((key, text) for key, _, text in figure_rows(report))["solve"]
        assert ("principal point (119.5, 159.5) px (held at the image centre" in text) is said


def _measured_report(results) -> dict:
    """REPORT with ``figures.measurements`` of the sphere: its 68 "landmarks" are vertices on
    its front (the side the cameras see), measured as the capture flow measures a face."""
    from facecap_core.measure import landmark_measurements, under_scale

    sphere = trimesh.load(results["mesh.ply"], process=False)
    front = np.flatnonzero(sphere.vertices[:, 2] > 45)
    ids = front[np.argsort(sphere.vertices[front, 0])][np.linspace(0, len(front) - 1, 68)
                                                         .astype(int)]
    measurements = under_scale(landmark_measurements(sphere.vertices, sphere.faces, ids, 4.0),
                               4.0)
    return {**REPORT, "figures": {**REPORT["figures"], "measurements": measurements}}


def test_two_clicks_measure_the_face_straight_and_along_its_surface(results, tmp_path):
    """Measure: two clicks on the mesh pick two vertices; the page's straight distance is
    theirs within 0.1 mm, its surface distance no shorter and within 0.5 % of the path
    facecap_core/measure.py finds, each said with the scale's 1σ; a preset shows the
    report's figure and draws its line; the page stays small and is ready in under 2 s."""
    import time

    from facecap_core.measure import SurfacePaths
    from tests.browser import chromium

    report = _measured_report(results)
    page_file = tmp_path / "index.html"
    page_file.write_bytes(build_page(report, results, mesh_glb(results["mesh.ply"])))
    assert page_file.stat().st_size < 15 * 2**20
    sphere = trimesh.load(results["mesh.ply"], process=False)
    paths = SurfacePaths(sphere.vertices, sphere.faces)
    with chromium() as browser:
        page = browser.new_page(viewport={"width": 1100, "height": 700})
        errors = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        start = time.perf_counter()
        page.goto(page_file.as_uri())
        page.wait_for_function("window.facecap && window.facecap.ready", timeout=60_000)
        assert time.perf_counter() - start < 2.0
        before = _shot(page)
        page.click("#measure-button")
        assert page.is_visible("#measure")
        box = page.locator("#canvas").bounding_box()
        aims = [int(np.argmin(np.linalg.norm(sphere.vertices - target, axis=1)))
                for target in ([-40.0, 15.0, 80.0], [35.0, -25.0, 80.0])]
        for i in aims:
            x, y = page.evaluate(f"window.facecap.vertexOnScreen({i})")
            page.mouse.click(box["x"] + x, box["y"] + y)
            page.wait_for_timeout(100)
        m = page.evaluate("window.facecap.measurement")
        assert [m["a"], m["b"]] == aims
        straight = float(np.linalg.norm(sphere.vertices[aims[0]] - sphere.vertices[aims[1]]))
        assert abs(m["straight"] - straight) < 0.1
        geodesic, _ = paths.path(*aims)
        assert m["surface"] >= m["straight"]
        assert abs(m["surface"] - geodesic) <= 0.005 * geodesic, (m, geodesic)
        said = page.inner_text("#measure-result")
        assert (f"straight {straight:.1f} mm ± {0.04 * straight:.1f} mm (±4.0 %, 1σ)"
                in said), said
        assert f"along the surface {m['surface']:.1f} mm ±" in said
        assert np.abs(_shot(page) - before).mean() > 0.05  # the points and the lines drawn
        page.click("[data-preset=mouth_width]")
        preset = report["figures"]["measurements"]["mouth_width"]
        m = page.evaluate("window.facecap.measurement")
        assert [m["a"], m["b"]] == preset["vertices"]
        said = page.inner_text("#measure-result")
        anatomical = preset["anatomical"]
        assert said.startswith(f"Mouth width: {anatomical['mm']:.1f} mm ± "
                               f"{anatomical['sigma_mm']:.1f} mm (1σ, with where the landmarks "
                               "sit); between its landmark vertices: straight "
                               f"{preset['straight']['mm']:.1f} mm ± "
                               f"{preset['straight']['sigma_mm']:.1f} mm (±4.0 %, 1σ); "
                               f"along the surface {preset['surface']['mm']:.1f} mm"), said
        assert abs(m["straight"] - preset["straight"]["mm"]) < 0.01
        assert abs(m["surface"] - preset["surface"]["mm"]) <= 0.005 * preset["surface"]["mm"]
        page.screenshot(path=str(SHOTS / "measure.png"))
        # A run whose metric scale has no stated σ: the preset's figure without a ±.
        unknown = {**report, "figures": {**report["figures"], "measurements": {
            key: {**m, "anatomical": {**m["anatomical"], "sigma_mm": None}}
            for key, m in report["figures"]["measurements"].items()}}}
        page_file.write_bytes(build_page(unknown, results, mesh_glb(results["mesh.ply"])))
        page.goto(page_file.as_uri())
        page.wait_for_function("window.facecap && window.facecap.ready", timeout=60_000)
        page.click("#measure-button")
        page.click("[data-preset=mouth_width]")
        said = page.inner_text("#measure-result")
        assert said.startswith(f"Mouth width: {anatomical['mm']:.1f} mm (its uncertainty is "
                               "not known); between its landmark vertices: straight"), said
    assert errors == []
    assert report["figures"]["measurements"]["mouth_width"]["name"] in \
        page_file.read_text()  # the preset's button


def test_the_light_turns_and_the_wireframe_shows(results, tmp_path):
    """The light slider moves the light round to the side (a raking light: the picture
    changes), the Wireframe switch draws the triangles' edges over the surface."""
    from tests.browser import chromium

    page_file = tmp_path / "index.html"
    page_file.write_bytes(build_page(REPORT, results, mesh_glb(results["mesh.ply"])))
    with chromium() as browser:
        page = _opened(browser, page_file)
        page.click("[data-mode=plain]")
        front = _shot(page)
        page.fill("#light input", "80")  # fires input
        raking = _shot(page)
        assert page.evaluate("window.facecap.light") == 80
        assert np.abs(raking - front).mean() > 5.0
        page.screenshot(path=str(SHOTS / "raking-light.png"))
        page.click("[data-toggle=wireframe]")
        assert page.get_attribute("[data-toggle=wireframe]", "aria-pressed") == "true"
        wired = _shot(page)
        assert np.abs(wired - raking).mean() > 2.0
        page.screenshot(path=str(SHOTS / "wireframe.png"))


def _results_folder(results, folder: Path) -> dict[str, Path]:
    """A run's results folder as the flow writes it: the mesh, cameras, cloud, ``mesh.glb``
    and ``report.json`` beside ``index.html``."""
    import shutil

    folder.mkdir(parents=True, exist_ok=True)
    for name in ("mesh.ply", "cameras.json", "cloud.ply"):
        shutil.copyfile(results[name], folder / name)
    (folder / "mesh.glb").write_bytes(mesh_glb(folder / "mesh.ply"))
    (folder / "report.json").write_text(json.dumps(REPORT))
    made = {name: folder / name for name in ("mesh.ply", "cameras.json", "cloud.ply",
                                             "mesh.glb")}
    (folder / "index.html").write_bytes(build_page(REPORT, made, made["mesh.glb"].read_bytes()))
    return made


def _downloaded(page, name: str) -> bytes:
    """The bytes a click on the download link of ``name`` downloads."""
    with page.expect_download() as caught:
        page.click(f"[data-download='{name}']")
    download = caught.value
    assert download.suggested_filename == name
    return Path(download.path()).read_bytes()


def test_the_downloads_are_the_files_beside_the_page(results, tmp_path):
    """Each download link names a file of the results folder beside the page (those the run
    made: no OBJ here); from disk a click downloads a mesh's bytes, and opens a text file
    (a browser ignores ``download`` on a file:// page: the page says so)."""
    from tests.browser import chromium

    folder = tmp_path / "result"
    _results_folder(results, folder)
    with chromium() as browser:
        page = _opened(browser, folder / "index.html")
        names = page.eval_on_selector_all("[data-download]",
                                          "links => links.map(a => a.getAttribute('href'))")
        assert names == ["mesh.ply", "mesh.glb", "report.json"]
        assert all((folder / name).is_file() for name in names)
        assert page.is_visible("#downloads ul") and not page.is_visible("#downloads-elsewhere")
        assert page.is_visible("#downloads-from-disk")
        for name in ("mesh.ply", "mesh.glb"):
            assert _downloaded(page, name) == (folder / name).read_bytes()
        page.click("[data-download='report.json']")
        page.wait_for_url((folder / "report.json").as_uri())
        assert json.loads(page.inner_text("body")) == REPORT


def test_the_store_s_copy_of_the_page_says_where_its_files_are(results, tmp_path):
    """Served with its results folder, the links stay and a click downloads each file;
    opened through the store's signed link (signed for index.html alone: every other file
    is 404) they go, and the page says where the files are rather than show dead links,
    asking the store for nothing (no 404 in the console)."""
    import functools
    import threading
    from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer

    from tests.browser import chromium

    folder = tmp_path / "result"
    _results_folder(results, folder)

    def store_s_copy(route):  # the page server's answer to an unsigned file: 404
        if route.request.url.split("?")[0].endswith("/index.html"):
            route.fulfill(status=200, body=(folder / "index.html").read_bytes(),
                          content_type="text/html")
        else:
            route.fulfill(status=404, body="no such page")

    whole = ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(
        SimpleHTTPRequestHandler, directory=str(folder)))
    threading.Thread(target=whole.serve_forever, daemon=True).start()
    try:
        with chromium() as browser:
            for served in (True, False):
                page = browser.new_page(viewport={"width": 1100, "height": 700})
                errors = []
                page.on("console", lambda m, errors=errors: errors.append(m.text)
                        if m.type == "error" else None)
                if served:
                    page.goto(f"http://127.0.0.1:{whole.server_address[1]}/index.html")
                else:
                    page.route("http://pages.test/**", store_s_copy)
                    page.goto("http://pages.test/artifacts/page-0123abcd/index.html"
                              "?expires=1&signature=x")
                page.wait_for_function("window.facecap && window.facecap.ready",
                                       timeout=60_000)
                assert page.evaluate("window.facecap.downloadsChecked")
                assert page.is_visible("#downloads ul") is served
                assert page.is_visible("#downloads-elsewhere") is not served
                assert not page.is_visible("#downloads-from-disk")
                if served:
                    for name in ("mesh.ply", "mesh.glb", "report.json"):
                        assert _downloaded(page, name) == (folder / name).read_bytes()
                assert errors == []
                page.close()
    finally:
        whole.shutdown()


def _bumpy_head(vertices: np.ndarray) -> np.ndarray:
    """The sphere, stretched and with a nose: a shape an alignment cannot turn on itself."""
    v = vertices * [1.0, 1.3, 0.85]
    nose = np.exp(-((v[:, 0] / 15) ** 2 + (v[:, 1] / 20) ** 2)) * (v[:, 2] > 0)
    return v + nose[:, None] * [0.0, 0.0, 25.0]


def test_the_scan_shows_beside_the_reconstruction(results, tmp_path):
    """Scan beside: the view splits in two through one camera, the scan on the right, where
    only background was; off again, one view. A page without a scan has no such switch."""
    from tests.browser import chromium

    sphere = trimesh.load(results["mesh.ply"], process=False)
    scan = (_bumpy_head(sphere.vertices) + [0.0, 0.0, -10.0], sphere.faces)
    page_file = tmp_path / "index.html"
    page_file.write_bytes(build_page(REPORT, results, mesh_glb(results["mesh.ply"]),
                                     _accuracy(results), scan=scan))
    plain_file = tmp_path / "plain.html"
    plain_file.write_bytes(build_page(REPORT, results, mesh_glb(results["mesh.ply"])))
    assert page_file.stat().st_size < 15 * 2**20
    with chromium() as browser:
        page = _opened(browser, page_file)
        page.click("[data-mode=accuracy]")
        one = _shot(page)
        assert page.evaluate("window.facecap.views") == 1
        page.click("#scan-button")
        two = _shot(page)
        assert page.evaluate("window.facecap.views") == 2
        assert page.get_attribute("#scan-button", "aria-pressed") == "true"
        h, w = two.shape[:2]
        right = two[h // 4: 3 * h // 4, w // 2 + w // 8: w - w // 8]
        grey = (np.abs(right - 184).max(axis=2) < 60) & \
            (np.abs(right - BACKGROUND).sum(axis=2) > 30)
        assert grey.mean() > 0.3, grey.mean()  # the scan, grey, fills the right's middle
        assert np.abs(two - one).mean() > 5.0
        page.screenshot(path=str(SHOTS / "scan-beside.png"))
        page.click("#scan-button")
        _shot(page)
        assert page.evaluate("window.facecap.views") == 1
        page = _opened(browser, plain_file)
        assert page.query_selector("#scan-button") is None
        assert page.evaluate("window.facecap.setScan(true)") is False


def test_the_scan_is_moved_onto_the_mesh(results, tmp_path):
    """The scan, turned and moved away in its own frame, is brought back onto the mesh by the
    inverse of the metric protocol's alignment, and thinned to the page's size."""
    from facecap.pages.scan import scan_in_mesh_frame, thinned
    from facecap_core.evaluation.alignment import align
    from facecap_core.meshio import load_landmarks, save_landmarks

    sphere = trimesh.load(results["mesh.ply"], process=False)
    head = _bumpy_head(sphere.vertices)
    mesh_ply = tmp_path / "mesh.ply"
    trimesh.Trimesh(head, sphere.faces, process=False).export(mesh_ply)
    angle = np.radians(20)
    R = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0],
                  [-np.sin(angle), 0, np.cos(angle)]])
    moved = head @ R.T + [30.0, -12.0, 400.0]
    scan_ply = tmp_path / "scan.ply"
    trimesh.Trimesh(moved, sphere.faces, process=False).export(scan_ply)
    ids = np.flatnonzero(head[:, 2] > 40)[:68]
    scan_lm = save_landmarks(tmp_path / "scan_landmarks.json", moved[ids])
    mesh_lm = save_landmarks(tmp_path / "mesh_landmarks.json", head[ids])
    fit = align(head, sphere.faces, moved, sphere.faces, load_landmarks(scan_lm),
                load_landmarks(mesh_lm), with_scale=False)
    vertices, faces = scan_in_mesh_frame(scan_ply, fit)
    assert np.abs(vertices - head).max() < 0.5
    assert np.array_equal(faces, sphere.faces)
    few, few_faces = thinned(vertices, faces, 1000)
    assert len(few_faces) <= 1000 and np.ptp(few, axis=0) == pytest.approx(np.ptp(head, axis=0),
                                                                            rel=0.05)


CHECKER = ((200, 40, 200), (40, 200, 80))
"""The textured sphere's two colours (magenta, green): neither is the heat map's red."""


def _seam_split_sphere(folder: Path) -> tuple[trimesh.Trimesh, object]:
    """A head-sized sphere as the fitting stage writes it: ``mesh.ply`` and a textured
    ``mesh.glb`` (a checker atlas) split at a UV seam down the middle of its front (x = 0,
    z > 0, where the page's view looks), the seam copies after the sphere's vertices."""
    from facecap_core.texture import UVLayout, glb_bytes

    sphere = trimesh.creation.icosphere(subdivisions=4, radius=80.0)
    x, y, z = sphere.vertices.T
    u = np.arctan2(x, -z) / (2 * np.pi) + 0.5  # 0 and 1 at the front's middle
    v = np.arccos(np.clip(-y / 80.0, -1, 1)) / np.pi
    faces = sphere.faces.copy()
    copies: dict[int, int] = {}
    for f in np.flatnonzero(np.ptp(u[faces], axis=1) > 0.5):  # across the seam
        for k in range(3):
            if u[faces[f, k]] < 0.5:  # this corner's copy lies past u = 1
                faces[f, k] = copies.setdefault(int(faces[f, k]), len(u) + len(copies))
    vertex = np.r_[np.arange(len(u)), list(copies)]
    uv = np.c_[np.r_[u, u[list(copies)] + 1.0] / 1.1, v[vertex]]
    layout = UVLayout(uv=uv, vertex=vertex, faces=faces)
    cells = (np.add.outer(np.arange(256) // 32, np.arange(256) // 32) % 2).astype(bool)
    atlas = np.where(cells[..., None], CHECKER[0], CHECKER[1]).astype(np.uint8)
    sphere.export(folder / "mesh.ply")
    (folder / "mesh.glb").write_bytes(glb_bytes(sphere.vertices, sphere.faces, layout, atlas))
    return sphere, layout


def _on_screen(page, corners, weights) -> tuple[float, float]:
    """The page's point at those weights of the glTF vertices ``corners`` on the screen."""
    box = page.locator("#canvas").bounding_box()
    at = np.array([page.evaluate(f"window.facecap.vertexOnScreen({int(i)})") for i in corners])
    x, y = np.asarray(weights) @ at
    return box["x"] + x, box["y"] + y


def test_a_textured_mesh_split_at_its_seams_shows_its_texture_heat_map_and_measures(tmp_path):
    """The fitting stage's mesh.glb (split at its UV seams, the copies named in its extras):
    Colour shows its texture; Accuracy (one value per mesh vertex) colours the seam copies'
    triangles as the others', without a console error; a click on a copy's triangle picks
    its mesh vertex, and the path along the surface crosses the seam."""
    from tests.browser import chromium

    sphere, layout = _seam_split_sphere(tmp_path)
    n = len(sphere.vertices)
    page_file = tmp_path / "index.html"
    page_file.write_bytes(build_page(REPORT, {"mesh.ply": tmp_path / "mesh.ply"},
                                     mesh_glb(tmp_path / "mesh.ply"), np.full(n, 5.0)))
    # A copy near the view's middle, one of its triangles, and one of the sphere's own
    # triangles away from the seam.
    copy = n + int(np.argmax(sphere.vertices[layout.vertex[n:], 2]
                             - np.abs(sphere.vertices[layout.vertex[n:], 1])))
    copy_face = layout.faces[np.flatnonzero((layout.faces == copy).any(axis=1))[0]]
    copy_face = np.r_[copy, [i for i in copy_face if i != copy]]
    centres = sphere.vertices[sphere.faces].mean(axis=1)
    own = (layout.faces < n).all(axis=1) & (np.abs(centres[:, 0] - 25.0) < 5) \
        & (np.abs(centres[:, 1]) < 10) & (centres[:, 2] > 0)
    own_face = layout.faces[np.flatnonzero(own)[0]]
    with chromium() as browser:
        page = browser.new_page(viewport={"width": 1100, "height": 700})
        errors = []
        # A draw WebGL refuses (an attribute shorter than the vertices) is only a warning.
        page.on("console", lambda m: errors.append(m.text) if m.type == "error"
                or "INVALID" in m.text else None)
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(page_file.as_uri())
        page.wait_for_function("window.facecap && window.facecap.ready", timeout=60_000)
        box = page.locator("#canvas").bounding_box()

        def patch(shot, point) -> np.ndarray:
            x, y = int(point[0] - box["x"]), int(point[1] - box["y"])
            return shot[y - 2: y + 3, x - 2: x + 3].reshape(-1, 3).mean(axis=0)

        at_copy = _on_screen(page, copy_face, [0.6, 0.2, 0.2])
        at_own = _on_screen(page, own_face, [1 / 3, 1 / 3, 1 / 3])
        colour = _shot(page)
        h, w = colour.shape[:2]
        middle = colour[h // 4: 3 * h // 4, w // 4: 3 * w // 4].reshape(-1, 3)
        r, g, b = middle.T
        magenta = ((r > g + 60) & (b > g + 60)).mean()
        green = ((g > r + 60) & (g > b + 40)).mean()
        assert magenta > 0.1 and green > 0.1, (magenta, green)  # the checker, both colours
        page.screenshot(path=str(SHOTS / "textured-colour.png"))

        page.click("[data-mode=accuracy]")
        heat = _shot(page)
        for point in (at_copy, at_own):
            r, g, b = patch(heat, point)
            assert r > g + 40 and r > b + 40, (point, r, g, b)  # 5 mm: the heat map's red
        page.screenshot(path=str(SHOTS / "textured-accuracy.png"))

        page.click("#measure-button")
        page.mouse.click(*at_copy)
        page.wait_for_timeout(100)
        assert page.evaluate("window.facecap.picked") == [int(layout.vertex[copy])]
        page.mouse.click(*at_own)
        page.wait_for_timeout(100)
        m = page.evaluate("window.facecap.measurement")
        assert m["a"] == layout.vertex[copy] and m["b"] in own_face
        assert m["straight"] <= m["surface"] < 1.05 * m["straight"], m  # across the seam
    assert errors == []
