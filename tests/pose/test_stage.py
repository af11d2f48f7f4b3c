import numpy as np
import pytest

from facecap.synthetic import load_gt_cameras
from facecap_core.camera import Intrinsics, rotation_matrix
from facecap_core.keyframes import load_keyframes
from facecap_core.keyframes import main as keyframes_main
from facecap_core.pose.cameras_json import Cameras
from facecap_core.pose.colmap_sfm import Poses, run_sfm
from facecap_core.pose.evaluate import head_surface, pose_errors, surface_error
from facecap_core.pose.geometric import triangulate
from facecap_core.pose.io import write_colmap_text, write_outputs
from facecap_core.pose.stage import PoseConfig, estimate_poses, track_hosts
from facecap_core.video import read_frames
from tests.tolerances import EPS, expect_equal_cameras, expect_exact_cameras


def _ring(n=8, seed=0):
    """Cameras on an arc looking at the origin, and points around it."""
    rng = np.random.default_rng(seed)
    R, t = [], []
    for a in np.linspace(-0.6, 0.6, n):
        Rk = rotation_matrix([0, 1, 0], a)
        R.append(Rk)
        t.append(np.array([0, 0, 400.0]) - Rk @ np.zeros(3))
    points = rng.uniform(-60, 60, (50, 3))
    return R, t, points


def test_pose_errors_ignore_a_similarity_of_the_world():
    rng = np.random.default_rng(0)
    R_gt = [rotation_matrix(rng.normal(size=3), rng.uniform(0, 1)) for _ in range(10)]
    t_gt = [rng.normal(size=3) * 100 for _ in range(10)]
    S = rotation_matrix([0.3, 1, 0.2], 0.7)
    s, b = 0.01, np.array([5.0, -2.0, 1.0])
    # World x' = s S x + b: cameras keep x_cam up to the scale of t.
    R_est = [R @ S.T for R in R_gt]
    t_est = [s * tg - Re @ b for Re, tg in zip(R_est, t_gt)]
    intr = Intrinsics(640, 360, 500, 500, 320, 180, 0.01, 0)
    err = pose_errors(R_est, t_est, intr, R_gt, t_gt, intr)
    expect_exact_cameras(err)
    assert err["focal_pct"] == 0


def _sphere(n=2000, radius=80.0):
    """Points evenly over a sphere round the origin and their outward normals."""
    i = np.arange(n) + 0.5
    polar, azimuth = np.arccos(1 - 2 * i / n), np.pi * (1 + 5 ** 0.5) * i
    normals = np.stack([np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth),
                        np.cos(polar)], 1)
    return radius * normals, normals


def test_the_surface_error_is_what_a_reconstruction_from_perfect_matches_sees():
    R, t, _ = _ring()
    points, normals = _sphere()
    intr = Intrinsics(640, 360, 500, 500, 320, 180, -0.05, 0.01)
    # Exact cameras in another world (a similarity of it) rebuild the surface exactly.
    S, s, b = rotation_matrix([0.3, 1, 0.2], 0.7), 0.01, np.array([5.0, -2.0, 1.0])
    R_sim = [Rk @ S.T for Rk in R]
    t_sim = [s * tk - Rk @ b for Rk, tk in zip(R_sim, t)]
    exact = surface_error(R_sim, t_sim, intr, R, t, intr, points, normals)
    assert exact["surface"] < 1e-6 and exact["consistency_px"] < 1e-6
    # The front of the sphere, seen by two views or more: about half of it.
    assert 0.3 * len(points) < exact["points"] < 0.6 * len(points)
    # The principal point 2 px off: the rays through the views miss each other and the
    # surface bends. The same shift with every camera turned by 2/f in its own frame (a
    # rotation error of 0.23°) casts nearly the same rays (to second order: the sphere spans
    # ~100 px from the centre at f = 500 px): a fraction of the error.
    shifted = Intrinsics(640, 360, 500, 500, 322, 180, -0.05, 0.01)
    alone = surface_error(R, t, shifted, R, t, intr, points, normals)
    turn = rotation_matrix([0, 1, 0], -2 / 500)
    R_turned, t_turned = [turn @ Rk for Rk in R], [turn @ tk for tk in t]
    assert pose_errors(R_turned, t_turned, shifted, R, t, intr)["rotation_deg"] == (
        pytest.approx(np.degrees(2 / 500), rel=1e-6))
    turned = surface_error(R_turned, t_turned, shifted, R, t, intr, points, normals)
    assert alone["consistency_px"] > 0.05 and alone["surface"] > 0.05
    assert turned["surface"] < alone["surface"] / 4
    assert turned["consistency_px"] < alone["consistency_px"] / 4
    # Cameras of another size are refused, not compared pixel for pixel.
    with pytest.raises(ValueError, match="scale them"):
        surface_error(R, t, intr.scaled(320, 180), R, t, intr, points, normals)


def test_triangulation_recovers_points_and_rejects_outliers():
    from facecap_core.camera import project

    R, t, points = _ring()
    intr = Intrinsics(640, 360, 500, 500, 321.3, 178.2, -0.05, 0.01)
    rows = []
    for k in range(len(R)):
        uv, _ = project(points, R[k], t[k], intr)
        rows += [(n + 100, k, *uv[n]) for n in range(len(points))]
    rows = np.array(rows)
    rows[(rows[:, 0] == 100) & (rows[:, 1] == 3), 2] += 15.0  # a gross error: track dropped
    X, obs = triangulate(rows, R, t, intr)
    assert len(X) == len(points) - 1
    np.testing.assert_allclose(X, points[1:], atol=1e-6)
    assert set(np.unique(obs[:, 0])) == set(range(len(X)))
    hosts = track_hosts(obs, len(X))
    assert np.all(hosts == len(R) // 2)  # the middle of every full-length track


def test_colmap_text_model_reads_back(tmp_path):
    import pycolmap

    from facecap_core.camera import project

    R, t, points = _ring()
    intr = Intrinsics(640, 360, 500, 500, 321.3, 178.2, -0.05, 0.01)
    rows = [(n, k, *project(points[n:n + 1], R[k], t[k], intr)[0][0])
            for k in range(len(R)) for n in range(len(points))]
    poses = Poses(intr, list(range(0, 80, 10)), R, t, points, 0.0, np.array(rows))
    folder = write_colmap_text(poses, tmp_path)
    assert sorted(p.name for p in folder.iterdir()) == [
        "cameras.txt", "frames.txt", "images.txt", "points3D.txt", "rigs.txt"]
    rec = pycolmap.Reconstruction(str(folder))
    assert rec.num_reg_images() == 8 and rec.num_points3D() == 50
    # Exact cameras and points reproject with no error in COLMAP's own model.
    assert rec.compute_mean_reprojection_error() < 1e-3
    # The text holds 17 significant digits: every number reads back as written.
    assert list(rec.cameras[1].params) == [500, 321.8, 178.7, -0.05, 0.01]
    for k in range(len(R)):
        image = rec.images[k + 1]
        assert image.name == f"frame_{10 * k:06d}.png"
        # (the rotation goes through a quaternion: a few roundings)
        np.testing.assert_allclose(image.cam_from_world().rotation.matrix(), R[k],
                                   rtol=0, atol=10 * EPS)
        assert np.array_equal(image.cam_from_world().translation, t[k])
        xy = np.array([p.xy for p in image.points2D])
        assert np.array_equal(xy, poses.observations[poses.observations[:, 1] == k, 2:] + 0.5)
        assert [p.point3D_id for p in image.points2D] == list(range(1, 51))
    for n in range(len(points)):
        assert np.array_equal(rec.points3D[n + 1].xyz, points[n])
        assert [(e.image_id, e.point2D_idx) for e in rec.points3D[n + 1].track.elements] == [
            (k + 1, n) for k in range(len(R))]


@pytest.fixture(scope="module")
def capture(ict4_sweep):
    return ict4_sweep


@pytest.mark.slow
def test_pose_stage_calibrates_every_keyframe(capture, tmp_path):
    kf_json = keyframes_main(capture.video, tmp_path / "kf")
    kf = load_keyframes(kf_json)
    intr_gt, gt = load_gt_cameras(capture.gt_cameras)
    steps, _ = estimate_poses(capture.video, kf, tmp_path / "work", PoseConfig(sfm_width=640))
    errors = {}
    for name, poses in steps.items():
        assert poses.frame_indices == kf.indices
        errors[name] = pose_errors(poses.R, poses.t, poses.intrinsics,
                                   [gt[i]["R"] for i in kf.indices],
                                   [gt[i]["t"] for i in kf.indices], intr_gt)
    assert list(errors) == ["sfm", "geometric", "pba"]
    # SfM holds the principal point at the image centre (rotations tilt to make up for it);
    # the long LK tracks with the principal point free find it.
    assert errors["sfm"]["rotation_deg"] < 1.0 and errors["sfm"]["focal_pct"] < 3.0
    # (the rendered principal point is jittered ~6 px from the centre; a 3 s sweep pins it
    # to a few pixels, so the check is that it moves most of the way, not an exact figure)
    assert (errors["geometric"]["principal_point_px"]
            < 0.6 * errors["sfm"]["principal_point_px"])
    assert errors["geometric"]["rotation_deg"] < errors["sfm"]["rotation_deg"]
    assert errors["geometric"]["centre_pct"] < 0.3 and errors["geometric"]["focal_pct"] < 1.0
    # A 3 s, 640x360 sweep: a few tenths of a degree (the 8 s 720p benchmark captures reach
    # ~0.07°). PBA starts from the geometric solution. What it must do from any start: stay
    # within the bounds, and not lose focal length, which the tracks and the photometric
    # residuals pin down together (measured from two SfM starts, on two CPUs: 0.65 % ->
    # 0.43 % and 0.33 % -> 0.23 %). Rotations are not pinned by the data alone: a shift of
    # the principal point and a common tilt of every camera reproject alike over a 3 s arc,
    # so from those two starts PBA moved them by -0.03° (0.195° -> 0.167°) and +0.10°
    # (0.271° -> 0.368°, the principal point 2.3 -> 3.4 px off). The bound is that spread
    # with room, not an improvement the data cannot promise.
    assert errors["pba"]["rotation_deg"] < 0.5 and errors["pba"]["centre_pct"] < 0.3
    assert errors["pba"]["focal_pct"] < errors["geometric"]["focal_pct"], errors
    assert errors["pba"]["rotation_deg"] < errors["geometric"]["rotation_deg"] + 0.15, errors
    # What a reconstruction from perfect matches sees of the cameras: the true head rebuilt
    # with them. Nine starts of this capture (benchmarks/bench_pose_starts.py, SfM seeds 0-2
    # on two threads, three runs; docs/poses.md) went 0.200-0.225 % -> 0.163-0.166 % of the
    # head's size, 18-26 % better, while their rotations got 34-46 % worse: PBA must not
    # rebuild a worse head than its start (5 %: the benchmark's verdict, 2 %, with room).
    head = head_surface(capture.gt_mesh)
    truth = [gt[i]["R"] for i in kf.indices], [gt[i]["t"] for i in kf.indices], intr_gt
    surface = {name: surface_error(poses.R, poses.t, poses.intrinsics, *truth,
                                   *head)["surface_pct"]
               for name, poses in steps.items() if name != "sfm"}
    assert surface["pba"] < 1.05 * surface["geometric"], surface

    # The stage's outputs.
    path = write_outputs(steps["pba"], tmp_path / "poses")
    assert [k.frame_index for k in Cameras.read(path).keyframes] == kf.indices
    sparse = np.load(tmp_path / "poses" / "sparse.npz")
    assert sparse["points"].shape[1] == 3 and len(sparse["points"]) > 500
    assert sparse["visibility"].shape == (len(kf.indices), len(sparse["points"]))
    assert sparse["visibility"].sum(0).min() >= 2
    for name in ("cameras.txt", "images.txt", "points3D.txt"):
        assert (tmp_path / "poses" / "colmap" / name).is_file()
    assert (tmp_path / "poses" / "points.ply").is_file()


@pytest.mark.slow
def test_sift_threads_do_not_change_the_cameras(capture, tmp_path):
    # SIFT extracts each image alone, so threads there cost no reproducibility (matching's
    # threads do: they stay at one).
    kf = load_keyframes(keyframes_main(capture.video, tmp_path / "kf"))
    images = read_frames(capture.video, kf.indices[: len(kf.indices) // 2], width=640)
    one, two = (run_sfm(images, tmp_path / f"sfm{n}", kf.video_size, extraction_threads=n)
                for n in (1, 2))
    expect_equal_cameras(one, two)


def test_pose_stage_needs_the_keyframe_stage(tmp_path):
    from facecap_core.errors import InputError
    from facecap_core.pose import main as pose_main

    with pytest.raises(InputError, match="run the keyframe stage first"):
        pose_main(tmp_path / "video.mp4", tmp_path / "kf" / "keyframes.json", tmp_path / "out")


def test_colmap_logs_go_to_the_log_not_the_terminal(capfd, caplog):
    """pycolmap's bundle adjustment writes glog lines to stderr whatever GLOG_minloglevel
    says; the refinement keeps them in facecap's log (DEBUG) instead."""
    import logging

    import pycolmap

    from facecap_core.native_logs import native_stderr_to_log

    # The module's log alone: handlers other tests left on the root logger (Prefect's
    # console) would print its WARNING line, formatted, as they print any warning.
    log = logging.getLogger("facecap_core.pose.geometric")
    log.addHandler(caplog.handler)
    propagate, log.propagate = log.propagate, False
    capfd.readouterr()
    try:
        with caplog.at_level(logging.DEBUG, logger="facecap_core.pose.geometric"):
            with native_stderr_to_log(log, prefix="colmap: "):
                pycolmap.bundle_adjustment(pycolmap.Reconstruction(),
                                           pycolmap.BundleAdjustmentOptions())
    finally:
        log.propagate = propagate
        log.removeHandler(caplog.handler)
    assert capfd.readouterr().err == ""
    assert any("bundle adjustment" in r.getMessage().lower() for r in caplog.records)
