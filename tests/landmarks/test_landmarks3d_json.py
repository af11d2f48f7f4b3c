"""``landmarks3d.json`` through its model: the landmark stage's document reads back equal,
byte for byte, and a damaged file is one clear error naming it."""

import json

import numpy as np
import pytest

from facecap_core.errors import InputError
from facecap_core.landmarks.landmarks3d_json import Landmarks3d, load_landmarks3d


def _document() -> dict:
    """What the landmark stage writes (its key order; numpy floats where it has them)."""
    rng = np.random.default_rng(0)
    points = [None] * 17 + [[round(float(x), 6) for x in p] for p in rng.normal(size=(51, 3))]
    points[20] = None  # a point too uncertain
    return {
        "convention": "ibug68", "units": "arbitrary (monocular)", "landmarks": points,
        "convention_correction": {"what": "median offset", "captures": ["ict:101"],
                                  "spread": [0.01, 0.02]},
        "triangulated": points,
        "views": [3, 5, 9], "dropped_uncertain": [20],
        "spread_rel": [None] * 17 + [round(float(x), 5) for x in rng.uniform(0, 0.02, 51)],
        "inlier_views": [0] * 17 + [3] * 51,
        "reprojection_px": {"median": 0.8993513109458431, "rms": 1.264705155493277},
        "head_frame": {"R": np.eye(3).tolist(), "origin": [-2.93, 0.15, 0.98]},
        "irises": {"detector": "face mesh", "units": "arbitrary (monocular)", "views": [3, 5],
                   "pupils": {"right": [-2.4, 0.11, 0.5], "left": None},
                   "pupil_distance": None, "iris_diameter": 0.121,
                   "iris_diameter_spread_rel": 0.01234,
                   "iris_diameter_views": [[3, "right", round(np.float64(0.1210571), 6)],
                                           [5, "right", 0.119067]],
                   "reason": None},
        "detected": 3, "keyframes": 4,
        "coverage": {"yaw_min_deg": -91.4, "yaw_max_deg": round(np.float64(89.14), 1),
                     "yaw_span_deg": 180.5, "yaw_by_frame": [[3, -91.37], [5, 0.0], [9, 89.1]]},
        "seconds": {"wall": 7.175, "cpu": 1.763, "cpu_detection": 0.586}}


def test_landmarks3d_json_reads_back_equal_and_writes_the_same_bytes(tmp_path):
    doc = _document()
    path = Landmarks3d.model_validate(doc).write(tmp_path / "landmarks3d.json")
    # The bytes json.dumps(doc, indent=1) wrote before the model.
    assert path.read_text() == json.dumps(doc, indent=1)
    points, landmarks = load_landmarks3d(path)
    assert points.shape == (68, 3) and np.isnan(points[:17]).all() and np.isnan(points[20]).all()
    assert np.array_equal(points[17], doc["landmarks"][17])
    assert landmarks.irises.pupils.left is None and landmarks.coverage.yaw_by_frame[2] == (9, 89.1)
    assert landmarks.write(tmp_path / "again.json").read_bytes() == path.read_bytes()
    assert Landmarks3d.read(tmp_path / "again.json") == landmarks


@pytest.mark.parametrize("damage, says", [
    (lambda d: d.pop("irises"), "irises: Field required"),
    (lambda d: d["landmarks"].pop(), "landmarks: List should have at least 68 items"),
    (lambda d: d["landmarks"].__setitem__(30, [1.0, 2.0]), "landmarks.30"),
    (lambda d: d.update(detected=3.0), "detected: Input should be a valid integer"),
    (lambda d: d["irises"]["pupils"].update(right="none"), "irises.pupils.right"),
    (lambda d: d["coverage"].update(yaw_by_frame=[[3]]), "coverage.yaw_by_frame.0"),
    (lambda d: d.update(scale=2.0), "scale: Extra inputs are not permitted"),
])
def test_a_damaged_landmarks3d_json_is_a_clear_error_naming_the_file(tmp_path, damage, says):
    doc = _document()
    damage(doc)
    path = tmp_path / "landmarks3d.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(InputError, match=rf"{path}.* is not a facecap landmarks3d.json") as caught:
        load_landmarks3d(path)
    assert says in str(caught.value) and "rerun the landmark stage" in str(caught.value)


def test_a_missing_or_truncated_landmarks3d_json_is_a_clear_error(tmp_path):
    with pytest.raises(InputError, match="3D landmark file not found.*run the landmark stage"):
        load_landmarks3d(tmp_path / "landmarks3d.json")
    (tmp_path / "landmarks3d.json").write_text(json.dumps(_document())[:100])
    with pytest.raises(InputError, match="is not a facecap landmarks3d.json.*JSONDecodeError"):
        load_landmarks3d(tmp_path / "landmarks3d.json")
