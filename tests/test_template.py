import json

import numpy as np
import pytest

from facecap_core import assets
from facecap_core.errors import FacecapError, InputError
from facecap_core.geometry import umeyama
from facecap_core.meshio import load_landmarks
from facecap_core.template import Template, head_frame


@pytest.fixture(scope="module")
def default_template():
    return Template.default()


def test_assets_are_verified_and_cached(monkeypatch, tmp_path):
    folder = assets.menpo3d_data()
    for name in assets.MENPO3D_FILES:
        assert (folder / name).stat().st_size > 0
    # A tampered cached download is refused, not unpacked.
    monkeypatch.setenv("FACECAP_HOME", str(tmp_path))
    (tmp_path / "downloads").mkdir()
    (tmp_path / "downloads" / assets.MENPO3D_SDIST).write_bytes(b"not the sdist")
    with pytest.raises(FacecapError, match="sha256"):
        assets.menpo3d_data()
    assert not (tmp_path / "assets" / "menpo3d-0.8.6").exists()


def test_default_template_is_metric_with_68_landmarks(default_template):
    t = default_template
    assert t.vertices.shape == (53349, 3)
    eye_corners = np.linalg.norm(t.landmark_points[36] - t.landmark_points[45])
    assert 80 < eye_corners < 100  # mm, an adult's outer canthi
    regions = t.regions
    assert sum(regions.values()).max() == 1 and sum(regions.values()).min() == 1  # a partition
    R, origin = head_frame(t.landmark_points)
    x = (t.vertices[regions["ears"]] - origin) @ R[0]
    assert (x < -70).sum() > 500 and (x > 70).sum() > 500  # one ear each side
    assert regions["face"][t.landmarks[17:]].all()  # inner landmarks are on the face


def test_james_landmarks_follow_the_template_order(default_template):
    mesh, lm_path = assets.james_files()
    james = load_landmarks(lm_path)
    s, R, t = umeyama(default_template.landmark_points[17:], james[17:])
    moved = s * default_template.landmark_points @ R.T + t
    # In the right order the same landmarks of two faces are a few mm apart after alignment.
    assert np.median(np.linalg.norm(moved - james, axis=1)) < 6.0


def test_template_from_ict_is_skin_only_in_mm(ict_model):
    t = Template.from_ict(ict_model)
    assert len(t.vertices) == 11248
    assert 85 < np.linalg.norm(t.landmark_points[36] - t.landmark_points[45]) < 95
    assert t.regions["ears"].sum() > 200 and t.regions["scalp_neck"].sum() > 1000


def test_template_from_files_round_trip(tmp_path, ict_model):
    t = Template.from_ict(ict_model)
    t.save(tmp_path)
    again = Template.from_files(tmp_path / "template.ply", tmp_path / "template.json")
    np.testing.assert_array_equal(again.landmarks, t.landmarks)
    np.testing.assert_allclose(again.vertices, t.vertices, atol=1e-4)
    points = tmp_path / "points.json"
    points.write_text(json.dumps({"landmarks": t.landmark_points.tolist()}))
    snapped = Template.from_files(tmp_path / "template.ply", points)
    np.testing.assert_array_equal(snapped.landmarks, t.landmarks)


def test_template_errors(tmp_path):
    with pytest.raises(InputError, match="not found"):
        Template.from_files(tmp_path / "missing.ply", tmp_path / "missing.json")
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"ply\nformat garbage\n\x00\x01")
    with pytest.raises(InputError):
        Template.from_files(bad, tmp_path / "missing.json")
    with pytest.raises(InputError, match="68 landmark"):
        Template(np.zeros((10, 3)), np.array([[0, 1, 2]]), np.arange(5))
