import numpy as np
import pytest

from facecap.synthetic import load_gt_cameras, synthesize
from facecap.synthetic.config import SynthConfig
from facecap_core.camera import camera_center
from facecap_core.errors import InputError
from facecap_core.keyframes import KeyframeConfig, load_keyframes, main, select_keyframes
from tests.media import write_video


@pytest.fixture(scope="module")
def sweep(ict4_sweep):
    return ict4_sweep  # a 3 s 640x360 sweep (tests/conftest.py)


@pytest.mark.slow
def test_keyframes_are_spaced_by_angle(sweep):
    kf = select_keyframes(sweep.video)
    _, poses = load_gt_cameras(sweep.gt_cameras)
    centres = np.array([camera_center(poses[i]["R"], poses[i]["t"]) for i in kf.indices])
    yaw = np.degrees(np.arctan2(centres[:, 0], centres[:, 2]))
    steps = np.diff(yaw)
    # ~185° in 4° steps: 30-80 keyframes, ordered, no gap much wider than the step.
    assert 30 <= len(kf.indices) <= 80 and np.all(np.diff(kf.indices) > 0)
    assert np.median(steps) == pytest.approx(KeyframeConfig().keyframe_angle_deg, rel=0.4)
    assert steps.max() < 8.0
    # Consecutive keyframes share enough tracks to be matched.
    assert min(len(kf.tracks_between(a, a + 1)[0]) for a in range(len(kf.indices) - 1)) > 100
    obs = kf.observations
    assert obs[:, 2].max() < 640 and obs[:, 3].max() < 360 and obs[:, 2:].min() >= 0


@pytest.mark.slow
def test_more_keyframes_for_smaller_angles(sweep):
    coarse = select_keyframes(sweep.video, KeyframeConfig(keyframe_angle_deg=8.0))
    fine = select_keyframes(sweep.video)
    assert len(coarse.indices) < 0.7 * len(fine.indices)


def test_static_camera_is_refused(tmp_path, ict_model):
    config = SynthConfig(subject="ict:2", ict_model=ict_model, width=320, height=180,
                         duration_s=1.0, yaw_start_deg=0, yaw_end_deg=0, hand_jitter_mm=0,
                         hand_jitter_deg=0, elevation_wobble_deg=0, roll_deg=0)
    cap = synthesize(config, tmp_path, progress=False)
    with pytest.raises(InputError, match="barely moves"):
        select_keyframes(cap.video)



def test_too_short_video_is_refused(tmp_path):
    rng = np.random.default_rng(0)
    texture = rng.integers(0, 255, (90, 160, 3), np.uint8)
    frames = [np.roll(texture, 2 * i, axis=1) for i in range(10)]
    video = write_video(tmp_path / "short.mp4", frames)
    with pytest.raises(InputError, match="10 frames") as err:
        select_keyframes(video)
    assert "\n" not in str(err.value)


def test_flat_colour_video_is_refused(tmp_path):
    frames = [np.full((180, 320, 3), 120 + i % 3, np.uint8) for i in range(40)]
    video = write_video(tmp_path / "flat.mp4", frames)
    with pytest.raises(InputError, match="too little texture") as err:
        select_keyframes(video)
    assert "\n" not in str(err.value)


@pytest.mark.slow
def test_main_writes_keyframes_that_load_back(sweep, tmp_path):
    path = main(sweep.video, tmp_path / "kf")
    assert path == tmp_path / "kf" / "keyframes.json"
    kf = load_keyframes(path)
    assert 30 <= len(kf.indices) <= 80 and np.all(np.diff(kf.indices) > 0)
    assert kf.video_size == (640, 360) and kf.frames_read == 90
    assert len(kf.times) == len(kf.sharpness) == len(kf.indices)
    assert kf.observations.shape[1] == 4 and kf.observations[:, 0].max() == len(kf.indices) - 1
    with pytest.raises(InputError, match="not found"):
        load_keyframes(tmp_path / "none" / "keyframes.json")


def test_a_head_turning_before_a_still_camera_is_told_from_a_moving_camera():
    """The head-motion probe: tracks on the face move, tracks clear of it hold still, in
    most sampled moments (a tripod and a turning head); the opposite with a moving camera
    (the scene behind moves more than the face)."""
    from facecap_core.keyframes import HeadMotionProbe

    rng = np.random.default_rng(0)
    box = (200, 100, 300, 220)  # left, top, right, bottom (tracking pixels)
    face = rng.uniform([210, 110], [290, 210], (40, 2))
    scene = np.r_[rng.uniform([0, 0], [60, 360], (30, 2)), rng.uniform([560, 0], [640, 360],
                                                                       (30, 2))]
    before = np.r_[face, scene]
    ids = np.arange(len(before))

    def probe(face_shift, scene_shift, windows=6):
        p = HeadMotionProbe(starts=set(), span=5)
        for _ in range(windows):
            after = before + np.r_[np.tile(face_shift, (40, 1)), np.tile(scene_shift, (60, 1))]
            after += rng.normal(0, 0.1, after.shape)  # tracking noise
            p._close(box, dict(zip(ids.tolist(), before)), ids, after)
        return p

    assert probe([4.0, 0.5], [0.0, 0.0]).head_moves()  # tripod, turning head
    assert not probe([4.0, 0.5], [12.0, 0.0]).head_moves()  # camera round a still head
    assert not probe([0.3, 0.0], [0.0, 0.0]).head_moves()  # nothing moves: not this case
    assert not probe([4.0, 0.5], [0.0, 0.0], windows=2).head_moves()  # too few to tell
