"""The camera solve's checks (facecap_core/pose/checks.py) on cameras whose truth is exact."""

import numpy as np
import pytest

from facecap_core.camera import Intrinsics, rotation_matrix
from facecap_core.errors import InputError
from facecap_core.keyframes import Keyframes
from facecap_core.pose import checks
from facecap_core.pose.colmap_sfm import Poses

PHONE = Intrinsics(240, 320, 298.6, 298.6, 120.4, 158.7)
"""The real 240×320 phone sweep of issue 48 (its own calibration): 43.8° × 56.4°."""


def _sweep(yaws_deg, tremor_deg=0.0, seed=0, distance=400.0):
    """Cameras on a circle round the origin (the head), looking at it, at these yaws, each
    tilted by a random rotation of ``tremor_deg`` (hand tremor)."""
    rng = np.random.default_rng(seed)
    R, t = [], []
    for yaw in yaws_deg:
        Rk = rotation_matrix([0, 1, 0], np.radians(yaw))
        if tremor_deg:
            Rk = rotation_matrix(rng.normal(size=3), np.radians(tremor_deg)) @ Rk
        R.append(Rk)
        t.append(np.array([0.0, 0.0, distance]))
    return R, t


def _keyframes(n, angles_deg, ordered=True):
    return Keyframes(indices=list(range(0, 4 * n, 4)), times=[k / 30 for k in range(n)],
                     sharpness=[1.0] * n, observations=np.zeros((0, 4)),
                     video_size=(PHONE.width, PHONE.height), frames_read=4 * n,
                     angles_deg=list(angles_deg), ordered=ordered)


def _nominal_angles(true_deg, intr=PHONE):
    """The tracker's angles for true turns: the image moves by fx × angle, which the tracker
    reads with its nominal focal length."""
    nominal = (intr.width / 2) / np.tan(np.radians(checks.NOMINAL_HFOV_DEG) / 2)
    return np.asarray(true_deg, float) * intr.fx / nominal


def test_the_solve_error_is_one_input_error_line_naming_the_camera_solve():
    error = checks.CameraSolveError("what went wrong", "what to try")
    assert isinstance(error, InputError)
    assert str(error) == "the camera solve failed: what went wrong — what to try"


def test_a_phone_focal_passes_and_a_field_of_view_outside_35_to_100_degrees_is_named():
    h, v = checks.fields_of_view_deg(PHONE)
    assert h == pytest.approx(2 * np.degrees(np.arctan(120 / 298.6)), abs=1e-12)
    assert checks.focal_problem(PHONE) is None
    lo, hi = checks.FOV_RANGE_DEG

    def with_fov(side, fov_deg):  # the focal giving that field of view across ``side`` px
        f = (side / 2) / np.tan(np.radians(fov_deg) / 2)
        return Intrinsics(PHONE.width, PHONE.height, f, f, PHONE.cx, PHONE.cy)

    # Just inside, across the long side: at the lower bound and at the upper.
    assert checks.focal_problem(with_fov(320, lo + 1e-6)) is None
    assert checks.focal_problem(with_fov(320, hi - 1e-6)) is None
    # Just outside, either way: a telephoto beyond phones' and the degenerate wide solve.
    assert "35–100°" in checks.focal_problem(with_fov(320, lo - 0.1))
    assert "outside" in checks.focal_problem(with_fov(320, hi + 0.1))
    # The short side is not held to the range: a 16:9 frame of a 56° lens is 34° across it.
    f = 112 / np.tan(np.radians(56) / 2)
    wide = Intrinsics(224, 128, f, f, 111.5, 63.5)
    assert checks.fields_of_view_deg(wide)[1] < lo and checks.focal_problem(wide) is None


def test_the_tracked_angles_become_the_solves_turns_at_its_focal_length():
    true = np.array([4.0, 3.5, 4.5, 4.0, 3.0])
    # The registered keyframes 0, 1, 3, 5 of six: keyframe 2 and 4 left out.
    steps = checks.tracked_steps_deg(_nominal_angles(true), [0, 1, 3, 5], PHONE.width, PHONE.fx)
    np.testing.assert_allclose(steps, [4.0, 3.5 + 4.5, 4.0 + 3.0], rtol=1e-12)
    # An angle the tracker could not measure counts as the others' median.
    with_nan = _nominal_angles(true)
    with_nan[1] = np.nan
    steps = checks.tracked_steps_deg(with_nan, [0, 2], PHONE.width, PHONE.fx)
    assert steps == pytest.approx([4.0 + 4.0], rel=1e-12)  # median of 4, 4.5, 4, 3
    # Mostly unmeasured: nothing to compare with.
    assert checks.tracked_steps_deg([np.nan, np.nan, 4.0], [0, 3], 240, 298.6) is None


def _video(yaws, tremor_deg=0.3, seed=0):
    R, t = _sweep(yaws, tremor_deg, seed)
    true = checks.rotation_angles_deg(R)
    keyframes = _keyframes(len(yaws), _nominal_angles(true))
    return Poses(PHONE, list(keyframes.indices), R, t), keyframes


def test_a_sweep_in_order_passes_and_two_keyframes_out_of_order_are_named():
    yaws = np.arange(-88.0, 56.0, 4.0)  # the real sweep's −88° to +55°, every 4°
    poses, keyframes = _video(yaws)
    assert checks.solve_problem(poses, keyframes) is None
    # The solve puts the views of frames 40 and 80 (keyframes 10 and 20) in each other's
    # places: 40° away from both neighbours, where the tracker saw 4° steps.
    R = list(poses.R)
    R[10], R[20] = R[20], R[10]
    swapped = Poses(PHONE, poses.frame_indices, R, poses.t)
    steps = checks.rotation_angles_deg(R)
    expected = checks.tracked_steps_deg(keyframes.angles_deg, range(len(yaws)), PHONE.width,
                                        PHONE.fx)
    assert checks.order_jumps(steps, expected).tolist() == [9, 10, 19, 20]
    problem = checks.solve_problem(swapped, keyframes)
    assert problem.startswith("4 of 35 steps between consecutive keyframes")
    assert "out of order" in problem and "frame 36 and frame 40" in problem


def test_a_step_is_a_jump_only_beyond_both_the_floor_and_twice_the_tracked_turn():
    expected = np.array([4.0, 4.0, 8.0, 8.0])
    steps = np.array([10.0, 10.0 + 1e-9, 16.0, 16.0 + 1e-9])
    assert checks.order_jumps(steps, expected).tolist() == [1, 3]


def test_a_solve_that_turns_further_than_the_tracking_all_along_keeps_its_order():
    """A camera circling a face: the tracker measures 1.7x less than the turn in every
    step, and one step is 2.1x the tracker's 6° (12.6°, over the 10° floor). Against the
    tracking alone that step is a jump; against the tracking scaled by the solve's own
    lower quartile of ratios it is a step like the others. Two views swapped still jump,
    and so do every two neighbours swapped (half the steps long); a solve turning 2.5x the
    tracking all along is refused by its span."""
    yaws = np.arange(-90.0, 91.0, 6.0 * 1.7)
    yaws[12:] += 12.6 - 6.0 * 1.7
    R, t = _sweep(yaws)
    true = checks.rotation_angles_deg(R)
    keyframes = _keyframes(len(yaws), _nominal_angles(np.full(len(true), 6.0)))
    poses = Poses(PHONE, list(keyframes.indices), R, t)
    expected = checks.tracked_steps_deg(keyframes.angles_deg, range(len(yaws)), PHONE.width,
                                        PHONE.fx)
    assert checks.order_jumps(true, expected).tolist() == [11]
    assert checks.circling_factor(true, expected) == pytest.approx(1.7, rel=1e-9)
    assert checks.solve_problem(poses, keyframes) is None
    figures = checks.solve_figures(poses, keyframes)
    assert figures["circling_factor"] == pytest.approx(1.7, abs=1e-3)
    assert figures["largest_step_ratio"] == pytest.approx(12.6 / (6.0 * 1.7), abs=1e-3)
    swapped = list(R)
    swapped[4], swapped[14] = swapped[14], swapped[4]
    problem = checks.solve_problem(Poses(PHONE, poses.frame_indices, swapped, t), keyframes)
    # The tracker's 6° scaled by the circling factor: 10° expected.
    assert "out of order" in problem and "where the sweep turns ~10° between them" in problem
    # Every two neighbours swapped (1, 0, 3, 2, ...): the steps alternate 1x and 3x.
    pairs = [R[k ^ 1] for k in range(len(R) - len(R) % 2)]
    n = len(pairs)
    problem = checks.solve_problem(Poses(PHONE, poses.frame_indices[:n], pairs, t[:n]),
                                   _keyframes(n, keyframes.angles_deg[:n]))
    assert "out of order" in problem
    # Scaled by twice at most; 2.5x all along is more than a circling camera explains.
    assert checks.circling_factor(true * 5, expected) == checks.CIRCLING_MAX
    R, t = _sweep(np.arange(-60.0, 61.0, 6.0 * 2.5))
    keyframes = _keyframes(len(R), _nominal_angles(np.full(len(R) - 1, 6.0)))
    problem = checks.solve_problem(Poses(PHONE, list(keyframes.indices), R, t), keyframes)
    assert "in all along the sweep where the video's tracking measured" in problem


def _tracked_video(frames, yaws, tremor_deg=0.3):
    """Cameras of keyframes at video ``frames`` and ``yaws``, and the keyframes with the
    tracker's angles of their true turns."""
    R, t = _sweep(yaws, tremor_deg)
    keyframes = Keyframes(indices=[int(f) for f in frames], times=[f / 30 for f in frames],
                          sharpness=[1.0] * len(frames), observations=np.zeros((0, 4)),
                          video_size=(PHONE.width, PHONE.height), frames_read=int(frames[-1]) + 1,
                          angles_deg=list(_nominal_angles(checks.rotation_angles_deg(R))),
                          ordered=True)
    return Poses(PHONE, [int(f) for f in frames], R, t), keyframes


def test_a_keyframe_forced_by_lost_tracks_is_judged_by_the_frames_between():
    """Where the tracks are lost the tracker forces the next keyframe with the angle the
    last tracks gave, down to a quarter of the turn on a 240×320 phone-like render. The frames
    between two keyframes, at the solve's typical turn per frame, say what the turn is. A
    view out of order still jumps against both, a sweep that speeds up is still covered by
    its tracking, and one that pauses cannot excuse a fold there."""
    frames = np.r_[np.arange(0, 60, 3), np.arange(66, 126, 3)]  # 9 frames from 57 to 66
    yaws = -60.0 + 2.0 * frames  # 2° a frame: 6° between keyframes, 18° across the gap
    poses, keyframes = _tracked_video(frames, yaws)
    gap = int(np.flatnonzero(np.diff(frames) == 9)[0])
    keyframes.angles_deg[gap] = _nominal_angles([3.0])[0]  # the lost tracks' angle: a sixth
    steps = checks.rotation_angles_deg(poses.R)
    expected = checks.tracked_steps_deg(keyframes.angles_deg, range(len(frames)), PHONE.width,
                                        PHONE.fx)
    # Against the tracking alone, the step over the gap is a jump ...
    assert checks.order_jumps(steps, expected * checks.circling_factor(steps, expected)
                              ).tolist() == [gap]
    # ... against the frames between, an ordinary step.
    assert checks.solve_problem(poses, keyframes) is None
    assert checks.solve_figures(poses, keyframes)["largest_step_ratio"] < checks.JUMP_FACTOR
    # Two views swapped across the head jump against both.
    swapped = list(poses.R)
    swapped[5], swapped[30] = swapped[30], swapped[5]
    problem = checks.solve_problem(Poses(PHONE, poses.frame_indices, swapped, poses.t),
                                   keyframes)
    assert "out of order" in problem and "frame 12 and frame 15" in problem
    # A sweep that speeds up threefold over the gap: the tracker saw it, the frames did not.
    fast = yaws.copy()
    fast[gap + 1:] += 2 * 18.0  # 54° over the gap's 9 frames
    assert checks.solve_problem(*_tracked_video(frames, fast)) is None
    # A camera that pauses 93 frames and goes on 6° further, where the solve joins the
    # second half of the sweep 50° off: 186° at the typical turn per frame, bounded by three
    # median steps (18°), so still a jump.
    paused = np.r_[np.arange(0, 60, 3), np.arange(150, 210, 3)]
    yaws = -60.0 + 2.0 * np.r_[np.arange(0, 60, 3), np.arange(60, 120, 3)]
    poses, keyframes = _tracked_video(paused, yaws)
    assert checks.solve_problem(poses, keyframes) is None
    folded = _sweep(yaws + 50.0 * (paused >= 150), 0.3)
    problem = checks.solve_problem(Poses(PHONE, poses.frame_indices, *folded), keyframes)
    assert "out of order" in problem and "frame 57 and frame 150" in problem


def test_a_solve_that_turns_half_as_far_as_the_tracking_is_named():
    yaws = np.arange(-60.0, 61.0, 4.0)
    poses, keyframes = _video(yaws, tremor_deg=0.0)
    # The same order, every turn halved: no step jumps, but the sweep is half as wide.
    R, t = _sweep(yaws / 2)
    half = Poses(PHONE, poses.frame_indices, R, t)
    steps = checks.rotation_angles_deg(R)
    expected = checks.tracked_steps_deg(keyframes.angles_deg, range(len(yaws)), PHONE.width,
                                        PHONE.fx)
    assert checks.span_ratio(steps, expected) == pytest.approx(0.5, rel=1e-9)
    assert not len(checks.order_jumps(steps, expected))
    assert "turn 60° in all along the sweep where the video's tracking measured ~120°" in \
        checks.solve_problem(half, keyframes)
    # A turn wider than the tracking's passes up to 2x: a camera circling a face sees the
    # face move less than the turn, so the tracker measures less (1.6x on a 50° phone-like
    # sweep).
    R, t = _sweep(yaws * 1.7)
    assert checks.solve_problem(Poses(PHONE, poses.frame_indices, R, t), keyframes) is None
    R, t = _sweep(yaws * 0.7)
    assert checks.solve_problem(Poses(PHONE, poses.frame_indices, R, t), keyframes) is None
    R, t = _sweep(yaws * 1.9)
    assert checks.solve_problem(Poses(PHONE, poses.frame_indices, R, t), keyframes) is None


def test_photo_names_give_an_order_only_as_a_videos_frames_do():
    frames = [f"frame_{i:05d}.jpg" for i in range(0, 360, 3)]
    assert checks.frame_numbers(frames).tolist() == list(range(0, 360, 3))
    # A photo set numbered as taken (gaps where photos were deleted) gives no order.
    assert checks.frame_numbers(["img_0000.jpg", "img_0001.jpg", "img_0003.jpg"]) is None
    assert checks.frame_numbers(["a_1.jpg", "b_2.jpg", "c_3.jpg"]) is None
    assert checks.frame_numbers(["face.jpg", "side.jpg", "back.jpg"]) is None
    assert checks.frame_numbers(["1.jpg", "2.png", "3.jpg"]) is None


def test_numbered_photos_scrambled_round_the_head_are_named_and_unnumbered_ones_pass():
    names = [f"frame_{i:05d}.jpg" for i in range(90)]
    numbers = checks.frame_numbers(names)
    yaws = np.linspace(-88.0, 55.0, 90)
    R, t = _sweep(yaws, tremor_deg=0.3, seed=1)
    keyframes = _keyframes(90, [], ordered=False)
    indices = list(range(90))
    poses = Poses(PHONE, indices, R, t)
    assert checks.solve_problem(poses, keyframes, numbers, names) is None
    # The degenerate folder solve: the views scrambled in yaw (here every third one moved
    # across the head), the order of its file names no longer that of the sweep.
    rng = np.random.default_rng(2)
    scrambled = yaws.copy()
    scrambled[::3] = rng.permutation(scrambled[::3])
    R, t = _sweep(scrambled, tremor_deg=0.3, seed=1)
    problem = checks.solve_problem(Poses(PHONE, indices, R, t), keyframes, numbers, names)
    assert "photos (by file name)" in problem and "frame_000" in problem
    # Without an order in their names the same cameras are not judged by it.
    assert checks.solve_problem(Poses(PHONE, indices, R, t), keyframes) is None


def _ict_face(coefficients):
    # The model is read here only: the other tests need no face.
    from facecap_core.assets import packaged_ict_model
    from facecap_core.template import ict_identity_vertices, load_ict_model

    model = load_ict_model(packaged_ict_model())
    return ict_identity_vertices(model, coefficients)[model["landmarks68"]]


def test_landmarks_of_real_faces_form_a_face_and_broken_ones_are_named():
    mean = checks.mean_face_landmarks()
    assert checks.face_shape_error(mean, mean) == (51, pytest.approx(0.0, abs=1e-12))
    # Any similarity of a face (camera units, the solve's world) is the same face.
    moved = 0.01 * mean @ rotation_matrix([0.2, 1, 0.3], 2.0).T + [3.0, -1.0, 7.0]
    assert checks.face_shape_error(moved, mean)[1] == pytest.approx(0.0, abs=1e-9)
    # Faces at 2 σ of the ICT model's identities, jaw contour missing, 2 mm of noise.
    rng = np.random.default_rng(3)
    for _ in range(5):
        face = _ict_face(2 * rng.normal(size=30)) + rng.normal(0, 2.0, (68, 3))
        face[:17] = np.nan
        assert checks.face_problem(face) is None
    # Scrambled: the inner points of one face in each other's places.
    scrambled = mean.copy()
    scrambled[17:] = mean[17:][rng.permutation(51)]
    assert "do not form a face" in checks.face_problem(scrambled)
    # Three times too deep (an affine solve's face), seen from any pose.
    deep = mean * [1, 1, 3] @ rotation_matrix([1, 0.5, 0], 0.4).T
    assert checks.face_shape_error(deep, mean)[1] > checks.FACE_SHAPE_MAX
    # Too few points in 3D to be a face (the coarse stage's need).
    few = np.full((68, 3), np.nan)
    few[[27, 30, 36, 45, 48]] = mean[[27, 30, 36, 45, 48]]
    assert checks.face_problem(few).startswith("only 5 of the face's 51 inner landmarks")


def test_the_solves_figures_are_its_reprojection_turn_and_order_against_the_tracking():
    from facecap_core.camera import project  # only this test projects points

    yaws = np.arange(-40.0, 41.0, 4.0)
    poses, keyframes = _video(yaws, tremor_deg=0.0)
    rng = np.random.default_rng(4)
    points = rng.uniform(-60, 60, (30, 3))
    rows = []
    for view, (R, t) in enumerate(zip(poses.R, poses.t)):
        pixels = project(points, R, t, PHONE)[0]
        rows += [(n, view, *pixels[n]) for n in range(len(points))]
    rows = np.array(rows)
    rows[0, 2] += 3.0  # one observation 3 px off
    exact = Poses(PHONE, poses.frame_indices, poses.R, poses.t, points, 0.0, rows)
    figures = checks.solve_figures(exact, keyframes)
    assert figures["focal_px"] == 298.6 and figures["principal_point_px"] == [120.4, 158.7]
    assert figures["reprojection_px"]["median"] == 0.0
    assert figures["reprojection_px"]["rms"] == pytest.approx(3 / np.sqrt(len(rows)), abs=1e-3)
    assert figures["track_length"] == len(yaws)
    assert figures["turn_deg"] == figures["tracked_turn_deg"] == 80.0
    # Every 4° step against the 5° floor (a jump is over 2).
    assert figures["largest_step_ratio"] == pytest.approx(0.8, abs=1e-3)
