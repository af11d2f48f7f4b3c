import json
from pathlib import Path

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


def _index_with_sdist(tmp_path, setup_py: str) -> tuple[Path, bytes]:
    """A PEP 503 package index in a folder (a page per project) whose menpo3d page links to
    a menpo3d-0.8.6.tar.gz holding ``setup_py``."""
    import io
    import tarfile

    data = io.BytesIO()
    with tarfile.open(fileobj=data, mode="w:gz") as tar:
        for name, text in (("setup.py", setup_py),
                           ("PKG-INFO", "Metadata-Version: 2.1\nName: menpo3d\nVersion: 0.8.6\n")):
            info = tarfile.TarInfo(f"menpo3d-0.8.6/{name}")
            info.size = len(text.encode())
            tar.addfile(info, io.BytesIO(text.encode()))
    index = tmp_path / "index"
    (index / "menpo3d").mkdir(parents=True)
    (index / "files").mkdir()
    (index / "files" / assets.MENPO3D_SDIST).write_bytes(data.getvalue())
    (index / "menpo3d" / "index.html").write_text(
        f'<html><body><a href="../files/{assets.MENPO3D_SDIST}">{assets.MENPO3D_SDIST}</a>'
        '<a href="../files/menpo3d-0.8.5.tar.gz">menpo3d-0.8.5.tar.gz</a></body></html>')
    return index, data.getvalue()


def test_an_sdist_from_the_index_is_checked_before_anything_in_it_runs(monkeypatch, tmp_path):
    """An index serves a different menpo3d-0.8.6.tar.gz whose setup.py would leave a mark:
    it is refused by its sha256 and nothing in it has run (pip download would have run
    setup.py to prepare its metadata first)."""
    mark = tmp_path / "setup.py ran"
    index, _ = _index_with_sdist(tmp_path, f"open({str(mark)!r}, 'w').write('ran')\n"
                                           "from setuptools import setup\nsetup()\n")
    monkeypatch.setenv("FACECAP_HOME", str(tmp_path / "home"))
    monkeypatch.setenv("PIP_INDEX_URL", index.as_uri())
    monkeypatch.setenv("PIP_EXTRA_INDEX_URL", index.as_uri())
    with pytest.raises(FacecapError) as refused:
        assets.menpo3d_data()
    assert "sha256" in str(refused.value) and "\n" not in str(refused.value)
    assert not mark.exists(), "code from the unverified sdist ran"
    assert not (tmp_path / "home" / "assets" / "menpo3d-0.8.6").exists()


def test_the_sdist_is_fetched_from_pips_index_over_http(monkeypatch, tmp_path):
    """pip's configured index (here served over HTTP) gives the file itself, checked against
    the pinned sha256 (pinned here to the test's own sdist)."""
    import hashlib
    import http.server
    import threading
    from functools import partial

    index, data = _index_with_sdist(tmp_path, "raise SystemExit('never run')\n")
    handler = partial(http.server.SimpleHTTPRequestHandler, directory=str(index))
    handler.log_message = lambda *args: None
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        monkeypatch.setenv("FACECAP_HOME", str(tmp_path / "home"))
        monkeypatch.setenv("PIP_INDEX_URL", f"http://127.0.0.1:{server.server_address[1]}/")
        monkeypatch.setenv("PIP_EXTRA_INDEX_URL", f"http://127.0.0.1:{server.server_address[1]}/")
        monkeypatch.setattr(assets, "MENPO3D_SHA256", hashlib.sha256(data).hexdigest())
        (tmp_path / "dest").mkdir()
        sdist = assets._download_sdist(tmp_path / "dest")
        assert sdist.read_bytes() == data
    finally:
        server.shutdown()


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
