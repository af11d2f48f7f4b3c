"""Synthetic captures: the video decodes, and the ground truth agrees with what was rendered."""

import json

import av
import numpy as np
import pytest

from facecap_core.camera import camera_center, project
from facecap_core.config import SynthConfig
from facecap_core.errors import InputError
from facecap_core.landmarks import detect_68
from facecap_core.meshio import load_landmarks, load_mesh
from facecap_core.render import RaycastScene
from facecap_core.synthetic import load_gt_cameras, synthesize


def _frames(video):
    with av.open(str(video)) as c:
        return [f.to_ndarray(format="rgb24") for f in c.decode(video=0)]


@pytest.fixture(scope="module")
def sweep(tmp_path_factory, ict_model):
    """A 1.5 s, 640x360 ear-to-ear sweep of a random ICT identity."""
    config = SynthConfig(subject="ict:3", ict_model=ict_model, width=640, height=360,
                         duration_s=1.5, fps=30, seed=3)
    return config, synthesize(config, tmp_path_factory.mktemp("sweep"), progress=False)


@pytest.mark.slow
def test_video_and_ground_truth_files(sweep):
    config, cap = sweep
    frames = _frames(cap.video)
    assert len(frames) == cap.frames == 45
    assert frames[0].shape == (360, 640, 3)
    intr, poses = load_gt_cameras(cap.gt_cameras)
    assert len(poses) == 45 and 58 < intr.horizontal_fov_deg < 72
    assert config.k1_range[0] <= intr.k1 <= config.k1_range[1] and intr.k2 == -0.25 * intr.k1
    for p in poses:
        np.testing.assert_allclose(p["R"] @ p["R"].T, np.eye(3), atol=1e-9)
    mesh = load_mesh(cap.gt_mesh)
    assert 60 < np.ptp(mesh.vertices[:, 1]) < 400  # a head in mm
    saved = SynthConfig.model_validate(
        __import__("yaml").safe_load((cap.folder / "gt" / "config.yaml").read_text()))
    assert saved == config


@pytest.mark.slow
def test_camera_sweeps_ear_to_ear_at_arm_length(sweep):
    config, cap = sweep
    _, poses = load_gt_cameras(cap.gt_cameras)
    centres = np.array([camera_center(p["R"], p["t"]) for p in poses])
    yaw = np.degrees(np.arctan2(centres[:, 0], centres[:, 2]))
    assert yaw[0] < -80 and yaw[-1] > 80 and np.all(np.diff(yaw) > 0)
    dist = np.linalg.norm(centres - centres.mean(0) * [0, 1, 0], axis=1)
    assert dist.min() > 320 and dist.max() < 540


@pytest.mark.slow
def test_ground_truth_matches_the_rendered_pixels(sweep):
    """Landmarks projected with the GT camera hit the GT mesh at the landmark itself, and the
    rendered head covers exactly the pixels where the GT mesh is closer than the room."""
    _, cap = sweep
    intr, poses = load_gt_cameras(cap.gt_cameras)
    mesh = load_mesh(cap.gt_mesh)
    landmarks = load_landmarks(cap.gt_landmarks)
    assert np.abs(__import__("facecap_core.evaluation", fromlist=["distances"]).distances(
        landmarks, mesh.vertices, mesh.faces)).max() < 0.01  # landmarks lie on the surface
    scene = RaycastScene()
    scene.add(mesh.vertices, mesh.faces)
    frontal = min(range(len(poses)), key=lambda i: abs(camera_center(poses[i]["R"], poses[i]["t"])[0]))
    pose = poses[frontal]
    hits = scene.cast_camera(intr, pose["R"], pose["t"])
    uv, depth = project(landmarks[17:], pose["R"], pose["t"], intr)
    px = np.round(uv).astype(int)
    seen = hits.depth[px[:, 1], px[:, 0]] > depth - 1.0  # not hidden behind the nose
    gap = np.linalg.norm(hits.points[px[seen, 1], px[seen, 0]] - landmarks[17:][seen], axis=1)
    # One pixel is ~0.7 mm on the face here: rounding to the pixel centre moves < 1 mm
    # (a rounded pixel on the lip line may look through the mouth: hence the 90 %).
    assert seen.sum() > 40 and np.median(gap) < 0.5 and np.mean(gap < 1.0) > 0.9


@pytest.mark.parametrize("subject", ["james", "ict:0"])
def test_landmark_detector_agrees_with_projected_ground_truth(tmp_path, subject, ict_model):
    """On frontal 720p frames dlib's 68 points land near the projected GT landmarks."""
    config = SynthConfig(subject=subject, ict_model=ict_model, width=1280, height=720,
                         duration_s=0.1, fps=30, yaw_start_deg=-8, yaw_end_deg=8)
    cap = synthesize(config, tmp_path, progress=False)
    intr, poses = load_gt_cameras(cap.gt_cameras)
    landmarks = load_landmarks(cap.gt_landmarks)
    errors = []
    for frame, pose in zip(_frames(cap.video), poses):
        det = detect_68(frame)
        assert det is not None, "no face found on a frontal frame"
        uv, _ = project(landmarks, pose["R"], pose["t"], intr)
        errors.append(np.linalg.norm(det.points[17:] - uv[17:], axis=1))
    # The inner 51 points; the jaw contour is a silhouette, not a surface point.
    assert np.median(errors) < 8.0


def test_same_seed_same_capture(tmp_path, ict_model):
    config = SynthConfig(subject="ict:5", ict_model=ict_model, width=160, height=90,
                         duration_s=0.2, room=False)
    a = synthesize(config, tmp_path / "a", progress=False)
    b = synthesize(config, tmp_path / "b", progress=False)
    assert json.loads(a.gt_cameras.read_text()) == json.loads(b.gt_cameras.read_text())
    # The rendered frames are identical, but x264 does not always encode identical input to
    # identical bytes: the decoded frames agree to within the encoder's own error (~2 grey
    # levels here), far below the scene's texture.
    diff = np.abs(_frames(a.video)[2].astype(int) - _frames(b.video)[2])
    assert diff.mean() < 4.0


def test_bad_subjects_are_named(tmp_path, monkeypatch):
    monkeypatch.setenv("FACECAP_ICT_MODEL", str(tmp_path / "missing.npz"))
    with pytest.raises(InputError, match="not found"):
        synthesize(SynthConfig(subject="ict:1"), tmp_path, progress=False)
    with pytest.raises(InputError, match="not found"):
        synthesize(SynthConfig(subject="ict:1", ict_model=tmp_path / "none.npz"), tmp_path)
    with pytest.raises(InputError, match="landmarks"):
        synthesize(SynthConfig(subject=str(tmp_path / "head.obj")), tmp_path)
    with pytest.raises(InputError, match="even"):
        synthesize(SynthConfig(subject="james", width=641), tmp_path)
