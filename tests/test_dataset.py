"""Dataset layout: subjects, captures, scans; odd names; nothing outside the root."""

from __future__ import annotations

import json

import numpy as np
import pytest

from facecap.flows.evaluate import regressions
from facecap_core.dataset import mesh_consistency, scan_dataset
from facecap_core.errors import InputError


def _touch(path, data=b"x"):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)


def test_layout_with_odd_names(tmp_path):
    _touch(tmp_path / "Zoë Ångström" / "take 1.mp4")
    _touch(tmp_path / "Zoë Ångström" / "take 2.MOV")
    _touch(tmp_path / "Zoë Ångström" / "scan.ply")
    _touch(tmp_path / "Zoë Ångström" / "scan_landmarks.json")
    _touch(tmp_path / "bob" / "capture.mp4")
    _touch(tmp_path / "bob" / "notes.txt")
    _touch(tmp_path / ".hidden" / "x.mp4")
    entries = scan_dataset(tmp_path)
    assert [(e.subject, e.capture) for e in entries] == [
        ("Zoë Ångström", "take 1"), ("Zoë Ångström", "take 2"), ("bob", "capture")]
    assert entries[2].scan is None and entries[0].scan.name == "scan.ply"
    assert entries[0].scan_landmarks.name == "scan_landmarks.json"
    out = entries[0].out_dir(tmp_path / "out")
    assert out == (tmp_path / "out" / "Zoë Ångström" / "take 1").resolve()


def test_photo_folders_are_captures_and_names_do_not_collide(tmp_path):
    _touch(tmp_path / "ann" / "morning" / "IMG_0001.JPG")
    _touch(tmp_path / "ann" / "morning" / "IMG_0002.heic")
    _touch(tmp_path / "ann" / "evening.mp4")
    _touch(tmp_path / "ann" / "empty folder" / "notes.txt")
    entries = scan_dataset(tmp_path)
    assert [(e.capture, e.video.is_dir()) for e in entries] == [("evening", False),
                                                                 ("morning", True)]
    _touch(tmp_path / "ann" / "morning.mov")
    with pytest.raises(InputError, match="both capture 'morning'"):
        scan_dataset(tmp_path)


def test_a_photo_linked_from_outside_the_root_is_refused(tmp_path):
    _touch(tmp_path / "elsewhere" / "face.jpg")
    _touch(tmp_path / "root" / "ann" / "take" / "a.jpg")
    (tmp_path / "root" / "ann" / "take" / "b.jpg").symlink_to(tmp_path / "elsewhere" / "face.jpg")
    with pytest.raises(InputError, match="outside the dataset folder"):
        scan_dataset(tmp_path / "root")


def test_links_out_of_the_root_are_refused(tmp_path):
    outside = tmp_path / "elsewhere"
    _touch(outside / "secret.mp4")
    root = tmp_path / "root"
    _touch(root / "ann" / "a.mp4")
    (root / "ann" / "b.mp4").symlink_to(outside / "secret.mp4")
    with pytest.raises(InputError, match="outside the dataset folder"):
        scan_dataset(root)


def test_empty_or_missing_dataset_is_a_clear_error(tmp_path):
    with pytest.raises(InputError, match="no captures"):
        scan_dataset(tmp_path)
    with pytest.raises(InputError, match="not found"):
        scan_dataset(tmp_path / "nope")


def test_consistency_ignores_the_rigid_motion_between_captures():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(500, 3)) * 50
    from scipy.spatial.transform import Rotation

    R = Rotation.from_euler("xyz", [20, -35, 10], degrees=True).as_matrix()
    b = a @ R.T + [10.0, -4.0, 300.0]
    assert mesh_consistency(a, b)["max_mm"] < 1e-9
    noisy = b + rng.normal(scale=0.1, size=b.shape)
    figures = mesh_consistency(a, noisy)
    assert 0.1 < figures["mean_mm"] < 0.2
    with pytest.raises(InputError, match="vertex count"):
        mesh_consistency(a, b[:-1])


def _score(acc, comp):
    return {"accuracy": {"median": acc}, "completion": {"median": comp}}


def test_regressions_need_both_tolerances():
    previous = {"a/1": _score(1.0, 1.0), "b/1": _score(0.5, 0.5)}
    current = {"a/1": _score(1.2, 1.01), "b/1": _score(0.53, 0.5), "c/1": _score(9.0, 9.0)}
    flagged = regressions(current, previous, tolerance_mm=0.05, tolerance_rel=0.05)
    assert flagged == [{"capture": "a/1", "measure": "accuracy median", "previous_mm": 1.0,
                        "now_mm": 1.2}]


def test_a_scored_capture_that_lost_its_mesh_is_a_regression():
    """A capture scored last night with a scan but no mesh now (a failed or cut-short run)
    is flagged, not quietly skipped; one never scored is not."""
    previous = {"a/1": _score(1.0, 1.0)}
    flagged = regressions({}, previous, 0.05, 0.05, without_mesh=["a/1", "new/1"])
    assert flagged == [{"capture": "a/1", "measure": "mesh missing", "previous_mm": 1.0,
                        "now_mm": None}]


def test_a_capture_without_a_mesh_keeps_its_last_score_as_the_baseline(tmp_path):
    """The night after "mesh missing", the capture is compared with its last score again
    (carried forward), so neither its absence nor a worse mesh on its return goes unseen."""
    from facecap.flows.evaluate import previous_evaluation

    (tmp_path / "20261101T020000000000Z.json").write_text(json.dumps(
        {"captures": {"b/1": _score(0.5, 0.5)}, "carried": {"a/1": _score(1.0, 1.0)}}))
    previous = previous_evaluation(tmp_path, "20261102T020000000000Z")
    assert set(previous) == {"a/1", "b/1"}
    assert regressions({"a/1": _score(1.5, 1.0)}, previous, 0.05, 0.05)[0]["capture"] == "a/1"


def test_scale_error_is_the_meshs_size_against_the_scans():
    """A mesh 2 % too large: the similarity protocol shrinks it by 1/1.02 onto the scan, and
    the reported scale error is +2 %."""
    import trimesh

    from facecap.flows.evaluate import scale_error_pct
    from facecap_core.evaluation import score, score_json

    scan = trimesh.creation.icosphere(subdivisions=3, radius=80.0)
    landmarks = np.asarray(scan.vertices[:68])
    record = score_json(score(1.02 * scan.vertices, scan.faces, scan.vertices, scan.faces,
                              landmarks, 1.02 * landmarks, protocol="similarity"))
    assert scale_error_pct(record) == pytest.approx(2.0, abs=0.01)


def test_the_dataset_page_checks_and_escapes_what_out_holds(tmp_path):
    """What a results folder holds is anyone's to write: a figure that is markup is shown as
    text, a figure of the wrong type as none, a ``failed`` entry naming a folder outside OUT
    (``../x``) or a link out of OUT neither adds a row nor shows a picture from there; the
    page is written all the same."""
    import cv2

    from facecap.pages.dataset import rewrite_dataset_page

    out, outside = tmp_path / "out", tmp_path / "x"
    picture = cv2.imencode(".png", np.full((40, 120, 3), 200, np.uint8))[1].tobytes()
    _touch(outside / "preview.png", picture)
    _touch(outside / "report.json", b'{"figures": {"keyframes": 7}}')
    attack = '<img src=x onerror=alert(1)>'
    _touch(out / "anna" / "take1" / "report.json", json.dumps(
        {"figures": {"keyframes": attack, "metric_scale": attack, "roughness": [attack],
                     "evaluation": {"similarity": {"accuracy": {"median": "1e308"}}}}}).encode())
    _touch(out / "bob" / "take1" / "report.json", b'{"figures": "damaged"}')
    _touch(out / "carl" / "take1" / "report.json", b"[1, 2]")
    (out / "carl" / "linked").symlink_to(outside, target_is_directory=True)
    (out / "dora").symlink_to(tmp_path, target_is_directory=True)  # dora/x is outside
    (out / "evaluations").mkdir()
    (out / "evaluations" / "20260101T000000000000Z.json").write_text(json.dumps(
        {"captures": {"anna/take1": {"accuracy": {"median": "high"}}},
         "regressions": [{"capture": ["anna/take1"]}, "bob/take1"]}))
    (out / "dataset.json").write_text(json.dumps(
        {"failed": {"../x": "no face", "anna/take2": attack, "bob/take2": {"a": 1},
                    "./x": "?", "evaluations/x": "?", "dora/x": "failed"}}))
    rewrite_dataset_page(out)
    page = (out / "index.html").read_text()
    assert "<img src=x" not in page
    assert "&lt;img src=x onerror=alert(1)&gt;" in page  # anna/take2's reason, as text
    rows = sorted(part.split('"', 1)[0] for part in page.split('data-capture="')[1:])
    assert rows == ["anna/take1", "anna/take2", "bob/take1", "carl/take1", "dora/x"]
    assert "data:image/png" not in page  # no picture from outside OUT
    dora = page.split('data-capture="dora/x"', 1)[1].split("</tr>", 1)[0]
    assert ">7<" not in dora  # nor a figure of the report there


def test_the_dataset_run_s_last_line_says_what_it_made_and_names_its_page(tmp_path):
    """``facecap dataset``'s closing line: reconstructed only where there is a mesh; a run
    stopped before it (``--until keyframes``) says so; the dataset page is named."""
    from facecap.flows.dataset import summary_line

    out = tmp_path / "out"
    done = ["anna/take1", "anna/take2", "bob/take1"]
    for name in done:
        (out / name).mkdir(parents=True)
        (out / name / "mesh.ply").write_text("ply")
    full = {"captures": 3, "done": done, "until": "evaluation"}
    assert summary_line(full, out) == (f"3 of 3 captures reconstructed into {out}; their "
                                       f"page: {out / 'index.html'}")
    for name in done:  # what a run that stopped at the keyframes leaves
        (out / name / "mesh.ply").unlink()
    early = {**full, "until": "keyframes"}
    line = summary_line(early, out)
    assert "reconstructed" not in line
    assert "stopped after keyframes with no mesh" in line and line.endswith(
        f"their page: {out / 'index.html'}")


def test_the_dataset_page_is_titled_by_the_dataset_and_a_row_shows_its_warnings(tmp_path):
    """The title is the dataset's (its ROOT folder's name, as the dataset run and the
    evaluations record it), not the results folder's; a row with warnings on its capture's
    page says so: a mark, their count and the worst one in words; a row without says
    nothing more than its status."""
    from facecap.pages.dataset import rewrite_dataset_page

    out = tmp_path / "nightly results"
    warned = {"mesh_sanity": {"ok": False, "flipped": 2, "stretched_edges": 0,
                              "self_intersecting_pairs": 314},
              "cloud_noise": {"noise_mm": 0.4, "reference_mm": 0.2}}
    _touch(out / "anna" / "take1" / "report.json",
           json.dumps({"figures": {"keyframes": 20, **warned}}).encode())
    _touch(out / "anna" / "take1" / "mesh.ply", b"ply")
    _touch(out / "bob" / "take1" / "report.json", b'{"figures": {"keyframes": 21}}')
    _touch(out / "bob" / "take1" / "mesh.ply", b"ply")
    rewrite_dataset_page(out)
    assert "<h1>nightly results</h1>" in (out / "index.html").read_text()  # nothing recorded
    _touch(out / "evaluations" / "20261101T020000000000Z.json",
           json.dumps({"dataset": "study <1>", "captures": {}}).encode())
    rewrite_dataset_page(out)
    assert "<h1>study &lt;1&gt;</h1>" in (out / "index.html").read_text()
    (out / "dataset.json").write_text(json.dumps({"dataset": "study", "failed": {}}))
    rewrite_dataset_page(out)
    page = (out / "index.html").read_text()
    assert "<title>study · facecap</title>" in page and "<h1>study</h1>" in page
    assert "1 with warnings" in page
    anna = page.split('data-capture="anna/take1"', 1)[1].split("</tr>", 1)[0]
    assert 'data-warnings="2"' in anna and "⚠ 2 warnings" in anna
    worst = anna.split('<div class="worst">', 1)[1].split("</div>", 1)[0]
    assert worst.startswith("The mesh fails its checks: 314 self-intersecting triangle pairs")
    bob = page.split('data-capture="bob/take1"', 1)[1].split("</tr>", 1)[0]
    assert ">done</td>" in bob and "⚠" not in bob
