"""``cameras.json`` through its model: what the pose stage writes reads back equal, byte for
byte, and a damaged file is one clear error naming it."""

import json

import numpy as np
import pytest

from facecap_core.camera import Intrinsics, rotation_matrix
from facecap_core.errors import InputError
from facecap_core.pose.cameras_json import Cameras, read_cameras_json
from facecap_core.pose.colmap_sfm import Poses
from facecap_core.pose.io import write_cameras_json

SOLVE = {"focal_px": 501.12, "principal_point_px": [320.25, 180.5],
         "field_of_view_deg": [65.1, 39.5], "reprojection_px": {"median": 0.412, "rms": 0.7},
         "track_length": 4.2, "turn_deg": 150.3, "largest_step_ratio": 1.234}


def _poses() -> Poses:
    angles = np.radians([-40.0, -10.0, 20.0, 50.0])
    R = [rotation_matrix([0.0, 1.0, 0.0], a) for a in angles]
    t = [np.array([0.1 * k, -0.02, 4.0 + 1e-5 * k]) for k in range(len(angles))]
    intr = Intrinsics(640, 360, 501.123456789, 501.123456789, 320.25, 180.5, 1e-05, -0.021)
    return Poses(intrinsics=intr, frame_indices=[0, 3, 7, 12], R=R, t=t)


def _write(path):
    return write_cameras_json(_poses(), path, seconds=12.34, method="pba",
                              dropped=[{"frame_index": 5, "reason": "not registered"}],
                              solve=SOLVE, wall_seconds=20.5, cpu_seconds=30.25)


def test_cameras_json_reads_back_equal_and_writes_the_same_bytes(tmp_path):
    path = _write(tmp_path / "cameras.json")
    cameras = Cameras.read(path)
    assert cameras.keyframes[2].frame_index == 7 and cameras.solve.turn_deg == 150.3
    assert cameras.dropped[0].reason == "not registered" and cameras.metric_scale is None
    again = cameras.write(tmp_path / "again.json")
    assert again.read_bytes() == path.read_bytes()
    assert Cameras.read(again) == cameras
    # What json.dumps(doc, indent=1) wrote before the model: same keys, order, numbers.
    doc = json.loads(path.read_text())
    assert path.read_text() == json.dumps(doc, indent=1)
    assert list(doc) == ["convention", "units", "intrinsics", "keyframes", "seconds", "method",
                         "dropped", "solve", "wall_seconds", "cpu_seconds"]
    assert "tracked_turn_deg" not in doc["solve"]  # unset fields stay out of the file
    cams = read_cameras_json(path)
    assert cams.frame_indices == [0, 3, 7, 12] and cams.intrinsics == _poses().intrinsics
    assert np.array_equal(cams.t, np.asarray(_poses().t)) and cams.units == cameras.units


def test_the_metric_cameras_keep_the_pose_stage_s_fields(tmp_path):
    cameras = Cameras.read(_write(tmp_path / "cameras.json"))
    metric = cameras.model_copy(update={"units": "mm", "metric_scale": 90.5})
    doc = json.loads(metric.write(tmp_path / "mm.json").read_text())
    assert list(doc)[-2:] == ["cpu_seconds", "metric_scale"] and doc["units"] == "mm"
    assert Cameras.read(tmp_path / "mm.json").metric_scale == 90.5


@pytest.mark.parametrize("damage, says", [
    (lambda d: d.pop("keyframes"), "keyframes: Field required"),
    (lambda d: d["keyframes"][1].update(t=[0.0, 1.0]), "keyframes.1.t"),
    (lambda d: d["intrinsics"].update(fx="500"), "intrinsics.fx: Input should be a valid"),
    (lambda d: d["intrinsics"].update(width=640.5), "intrinsics.width"),
    (lambda d: d.update(scale=2.0), "scale: Extra inputs are not permitted"),
    (lambda d: d["solve"].pop("turn_deg"), "solve.turn_deg: Field required"),
])
def test_a_damaged_cameras_json_is_a_clear_error_naming_the_file(tmp_path, damage, says):
    path = _write(tmp_path / "cameras.json")
    doc = json.loads(path.read_text())
    damage(doc)
    path.write_text(json.dumps(doc))
    with pytest.raises(InputError, match=rf"{path}.* is not a facecap cameras.json") as caught:
        Cameras.read(path)
    assert says in str(caught.value) and "rerun the pose stage" in str(caught.value)
    with pytest.raises(InputError, match=str(path)):
        read_cameras_json(path)


def test_a_cameras_json_that_is_no_json_or_missing_is_a_clear_error(tmp_path):
    path = tmp_path / "cameras.json"
    path.write_text('{"units": "mm", "keyframes": [')
    with pytest.raises(InputError, match="is not a facecap cameras.json.*JSONDecodeError"):
        Cameras.read(path)
    path.write_text(json.dumps({"units": "mm", "keyframes": [], "intrinsics": {
        "width": 640, "height": 360, "fx": float("nan"), "fy": 1.0, "cx": 1.0, "cy": 1.0}}))
    with pytest.raises(InputError, match="intrinsics.fx: Input should be a finite number"):
        Cameras.read(path)
    with pytest.raises(InputError, match="cameras.json not found.*run the pose stage"):
        Cameras.read(tmp_path / "none" / "cameras.json")
