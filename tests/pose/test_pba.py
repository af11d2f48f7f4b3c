"""Photometric bundle adjustment: its residual kernel against a direct numpy computation."""

import numpy as np
import pytest

from facecap_core.camera import Intrinsics, project, rotation_matrix, undistort
from facecap_core.pose import pba
from facecap_core.pose.pba import kernels, normal, problem
from tests.tolerances import expect_exact_cameras


def _smooth_images(rng, count: int):
    """``count`` smooth random 320x240 images and their gradients, as the kernel takes them
    ((count, 240, 320) each)."""
    imgs = np.stack([__import__("cv2").GaussianBlur(rng.uniform(0, 255, (240, 320)).astype(
        np.float32), (0, 0), 2.0) for _ in range(count)])
    grads = [problem.gradients(im) for im in imgs]
    return imgs, np.stack([g[0] for g in grads]), np.stack([g[1] for g in grads])


def test_kernel_residuals_match_a_direct_warp():
    rng = np.random.default_rng(0)
    intr = Intrinsics(320, 240, 300.0, 300.0, 161.2, 118.7, -0.08, 0.02)
    # Two smooth random images; the point's true depth plays no role in this check.
    imgs, gx, gy = _smooth_images(rng, 2)
    R = [np.eye(3), rotation_matrix([0.1, 1.0, 0.0], 0.05)]
    t = [np.zeros(3), np.array([-20.0, 1.0, 2.0])]
    uv = rng.uniform([40, 40], [280, 200], (50, 2))
    rho = 1.0 / rng.uniform(300, 600, 50)
    R_rel, t_rel = normal.relative_poses(R, t)
    n = len(uv)
    stats = np.zeros(3)
    kernels.accumulate(np.zeros(n, np.int64), uv, rho, np.arange(n + 1, dtype=np.int64),
                       np.ones(n, np.int64), imgs, gx, gy, np.ones((n, 8)),
                       np.zeros((2, 6)), 9, np.zeros((2, 6)), 0.0, 240, R_rel, t_rel,
                       np.zeros((2, 2)),
                       np.array([intr.fx, intr.cx, intr.cy, intr.k1, intr.k2]), 1e9, 1e9, False,
                       True, np.zeros((13, 13)), np.zeros(13), np.zeros(n), np.zeros(n),
                       np.zeros((n, 21)), np.full((n, 21), -1, np.int64), stats, np.zeros(0))
    residuals = []
    for d in kernels.PATTERN:
        u = uv + d
        xy = undistort(np.stack([(u[:, 0] - intr.cx) / intr.fx, (u[:, 1] - intr.cy) / intr.fy],
                                1), intr.k1, intr.k2)
        X = np.concatenate([xy, np.ones((n, 1))], 1) / rho[:, None]
        ut, _ = project(X, R[1], t[1], intr)
        residuals.append(problem.sample(imgs[1], ut) - problem.sample(imgs[0], u))
    residuals = np.concatenate(residuals)
    assert stats[1] == 8 * n
    np.testing.assert_allclose(stats[0], np.sum(residuals ** 2), rtol=1e-4)


def test_the_normal_equations_do_not_depend_on_how_the_points_are_split():
    # The photometric system is summed over fixed runs of points on threads: the same
    # system (to rounding) as one run, and per-point blocks written where one run writes them.
    rng = np.random.default_rng(3)
    intr = Intrinsics(320, 240, 300.0, 300.0, 161.2, 118.7, -0.08, 0.02)
    imgs, gx, gy = _smooth_images(rng, 3)
    R = [np.eye(3), rotation_matrix([0.1, 1.0, 0.0], 0.05), rotation_matrix([0, 1.0, 0], -0.05)]
    t = [np.zeros(3), np.array([-20.0, 1.0, 2.0]), np.array([20.0, -1.0, 1.0])]
    n = 61
    uv = rng.uniform([40, 40], [280, 200], (n, 2))
    rho = 1.0 / rng.uniform(300, 600, n)
    host = rng.integers(0, 3, n)
    targets = np.array([k for h in host for k in range(3) if k != h], np.int64)
    target_start = np.arange(0, 2 * n + 1, 2, dtype=np.int64)
    R_rel, t_rel = normal.relative_poses(R, t)
    n_cam, local = kernels.N_INTR + 2 * kernels.N_FRAME, kernels.N_INTR + 3 * kernels.N_FRAME

    def system(chunks, jacobians=True):
        out = [np.zeros((n_cam, n_cam)), np.zeros(n_cam), np.zeros(n), np.zeros(n),
               np.zeros((n, local)), np.full((n, local), -1, np.int64), np.zeros(3),
               np.zeros(8 * len(targets))]
        normal.accumulate_in_chunks(
            host, uv, rho, target_start, targets, imgs, gx, gy,
            np.ones((n, 8)), np.zeros((3, 6)), 9,
            np.zeros((3, 6)), 0.0, 240, R_rel, t_rel, np.zeros((3, 2)),
            np.array([intr.fx, intr.cx, intr.cy, intr.k1, intr.k2]), 4.0, 12.0, True, *out,
            chunks=chunks, jacobians=jacobians)
        return out

    one, two, five = system(1), system(2), system(5)
    assert one[6][1] > 8 * n  # residuals in both targets of most points
    # A step's test asks for the cost alone: the same cost, count and residuals, no system.
    cost_only = system(2, jacobians=False)
    np.testing.assert_array_equal(cost_only[6], two[6])
    np.testing.assert_array_equal(cost_only[7], two[7])
    assert not cost_only[0].any() and not cost_only[2].any()
    for other in (two, five):
        for a, b in zip(one[:6], other[:6]):
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(one[6], other[6], rtol=1e-12)
        count = int(one[6][2])
        np.testing.assert_array_equal(np.sort(one[7][:count]), np.sort(other[7][:count]))


def test_sparse_points_are_hosted_at_their_depth():
    intr = Intrinsics(320, 240, 300.0, 300.0, 161.2, 118.7, -0.08, 0.02)
    R = [np.eye(3), rotation_matrix([0.0, 1.0, 0.0], 0.1)]
    t = [np.zeros(3), np.array([-30.0, 0.0, 2.0])]
    rng = np.random.default_rng(1)
    points = np.column_stack([rng.uniform(-80, 80, 40), rng.uniform(-60, 60, 40),
                              rng.uniform(300, 500, 40)])
    points[0, 0] = 1e4  # outside every image: dropped
    hosts = np.array([0, 1] * 20)
    host, uv, rho = problem.points_from_sparse(points, hosts, R, t, intr, (240, 320))
    assert len(host) == 39 and set(host) == {0, 1}
    for k in (0, 1):
        sel = np.flatnonzero((hosts == k) & (np.arange(40) > 0))
        expected, z = project(points[sel], R[k], t[k], intr)
        np.testing.assert_allclose(uv[host == k], np.round(expected))
        np.testing.assert_allclose(rho[host == k], 1 / z)


def test_pba_improves_on_its_starting_point():
    """Eight exact renders of a textured head over 70°: PBA started from poses with every
    rotation but the first (the gauge) turned 0.4° about a random axis, the centres exact,
    ends within a quarter of that (measured 0.04°: the images are renders of a per-vertex
    albedo sampled bilinearly, so not exactly photo-consistent)."""
    from facecap_core.assets import packaged_ict_model
    from facecap_core.camera import camera_center, look_at
    from facecap_core.pose.evaluate import pose_errors
    from facecap_core.pose.pba import PBAConfig
    from facecap_core.render import RaycastScene, interpolate
    from facecap_core.template import Template

    head = Template.from_ict(packaged_ict_model())
    V, F = head.vertices - head.landmark_points[30], head.faces
    rng = np.random.default_rng(0)
    # A smooth albedo: 40 plane waves with periods of 20-80 mm.
    waves = rng.normal(size=(40, 3))
    waves *= rng.uniform(0.08, 0.3, (40, 1)) / np.linalg.norm(waves, axis=1, keepdims=True)
    albedo = 128 + 100 / np.sqrt(40) * np.sin(V @ waves.T + rng.uniform(0, 6.3, 40)).sum(1)
    intr = Intrinsics(320, 240, 380.0, 380.0, 161.0, 118.0)
    scene = RaycastScene()
    scene.add(V, F)
    R, t, images, points, hosts = [], [], [], [], []
    for k, yaw in enumerate(np.radians(np.linspace(-35, 35, 8))):
        Rk, tk = look_at([450 * np.sin(yaw), 15.0, 450 * np.cos(yaw)], [0, 0, -40.0], [0, 1, 0])
        hits = scene.cast_camera(intr, Rk, tk)
        image = np.full(hits.depth.shape, 40.0, np.float32)
        image[hits.valid] = interpolate(albedo[:, None], F, hits.triangle[hits.valid],
                                        hits.bary[hits.valid])[:, 0]
        grid = hits.points[8:-8:10, 8:-8:10].reshape(-1, 3)
        grid = grid[np.isfinite(grid).all(1)]
        R.append(Rk), t.append(tk), images.append(image), points.append(grid)
        hosts.append(np.full(len(grid), k))
    turned = [R[0]] + [rotation_matrix(rng.normal(size=3), np.radians(0.4)) @ r for r in R[1:]]
    start_t = [-r @ camera_center(r0, x) for r, r0, x in zip(turned, R, t)]
    before = pose_errors(turned, start_t, intr, R, t, intr)["rotation_deg"]
    result = pba.photometric_bundle_adjustment(images, intr, turned, start_t,
                                               np.concatenate(points), PBAConfig(),
                                               sparse_hosts=np.concatenate(hosts),
                                               centre_prior=True)
    after = pose_errors(result.R, result.t, result.intrinsics, R, t, intr)
    assert before == pytest.approx(0.4, rel=1e-6)
    assert after["rotation_deg"] < 0.25 * before, after
    assert after["centre_pct"] < 0.1 and result.rms_after < result.rms_before


def _plane_scene(width: int, height: int, views: int = 6, blur_deg: float = 0.0):
    """Exact views of a textured plane (z = 0, mm) from 450 mm, turning ±15°: the images
    (float32 grey), their cameras, and points on the plane with a host view each. With
    ``blur_deg`` each view is the mean of 15 views spread over that much of the turn around
    its own (motion blur of a camera moving along the arc during the exposure)."""
    import cv2

    from facecap_core.camera import look_at

    rng = np.random.default_rng(3)
    texture = cv2.GaussianBlur(rng.uniform(0, 255, (800, 800)).astype(np.float32), (0, 0), 4)
    texture = (texture - texture.mean()) * 100 / texture.std() + 128  # 0.5 mm a texel
    s = width / 320
    intr = Intrinsics(width, height, 380.0 * s, 380.0 * s, (160.5 + 0.5) * s - 0.5,
                      (118.0 + 0.5) * s - 0.5, -0.05, 0.01)
    u, v = np.meshgrid(np.arange(width, dtype=float), np.arange(height, dtype=float))
    xy = undistort(np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy], -1),
                   intr.k1, intr.k2)
    R, t, images, points, hosts = [], [], [], [], []
    grid = np.stack(np.meshgrid(np.linspace(-120, 120, 25), np.linspace(-90, 90, 19)),
                    -1).reshape(-1, 2)
    def view(yaw):
        Rk, tk = look_at([450 * np.sin(yaw), 20.0, 450 * np.cos(yaw)], [0, 0, 0], [0, 1, 0])
        rays = np.concatenate([xy, np.ones(xy.shape[:2] + (1,))], -1) @ Rk  # world directions
        centre = -Rk.T @ tk
        hit = centre + (-centre[2] / rays[..., 2:]) * rays
        maps = (hit[..., :2] * 2 + 400).astype(np.float32)
        return Rk, tk, cv2.remap(texture, maps[..., 0], maps[..., 1], cv2.INTER_LINEAR)

    for k, yaw in enumerate(np.radians(np.linspace(-15, 15, views))):
        Rk, tk, image = view(yaw)
        if blur_deg:
            spread = np.radians(np.linspace(-blur_deg / 2, blur_deg / 2, 15))
            image = np.mean([view(yaw + d)[2] for d in spread], 0).astype(np.float32)
        images.append(image)
        R.append(Rk), t.append(tk)
        points.append(np.c_[grid, np.zeros(len(grid))]), hosts.append(np.full(len(grid), k))
    return images, intr, R, t, np.concatenate(points), np.concatenate(hosts)


def test_a_width_bound_adjusts_at_the_bounded_size():
    """PBA of 640×480 keyframes with ``max_width`` 320 is PBA of the same keyframes
    area-filtered to 320×240 with the intrinsics scaled to them: the same computation, so the
    same poses bit for bit and intrinsics that scale back exactly (to float rounding). It
    brings poses turned 0.4° back to within a quarter of that (measured 0.03°); a bound at
    the width changes nothing."""
    import cv2

    from facecap_core.camera import camera_center
    from facecap_core.pose.evaluate import pose_errors
    from facecap_core.pose.pba import PBAConfig

    images, intr, R, t, points, hosts = _plane_scene(640, 480)
    rng = np.random.default_rng(0)
    turned = [R[0]] + [rotation_matrix(rng.normal(size=3), np.radians(0.4)) @ r for r in R[1:]]
    start_t = [-r @ camera_center(r0, x) for r, r0, x in zip(turned, R, t)]
    config = PBAConfig(max_width=320)
    bounded = pba.photometric_bundle_adjustment(images, intr, turned, start_t, points, config,
                                                sparse_hosts=hosts, centre_prior=True)
    small = [cv2.resize(im, (320, 240), interpolation=cv2.INTER_AREA) for im in images]
    direct = pba.photometric_bundle_adjustment(
        small, intr.scaled(320, 240), turned, start_t, points,
        config.model_copy(update={"max_width": None}), sparse_hosts=hosts, centre_prior=True)
    for a, b in zip(bounded.R + bounded.t, direct.R + direct.t):
        np.testing.assert_array_equal(a, b)
    assert (bounded.intrinsics.width, bounded.intrinsics.height) == (640, 480)
    back = bounded.intrinsics.scaled(320, 240)
    for name in ("fx", "fy", "cx", "cy", "k1", "k2"):
        assert getattr(back, name) == pytest.approx(getattr(direct.intrinsics, name),
                                                    rel=0, abs=1e-9)
    before = pose_errors(turned, start_t, intr, R, t, intr)["rotation_deg"]
    after = pose_errors(bounded.R, bounded.t, bounded.intrinsics, R, t, intr)["rotation_deg"]
    assert before == pytest.approx(0.4, rel=1e-6) and after < 0.25 * before, after
    # At (or above) the width the bound is no bound: the very same result.
    same = pba.photometric_bundle_adjustment(small, intr.scaled(320, 240), turned, start_t,
                                             points, config, sparse_hosts=hosts,
                                             centre_prior=True)
    for a, b in zip(same.R + same.t, direct.R + direct.t):
        np.testing.assert_array_equal(a, b)


def test_the_blur_model_undoes_what_motion_blur_does_to_the_poses():
    """Six views of a textured plane 6° apart, each blurred by the camera turning 5° during
    its exposure (streaks of up to ~8 px at 320×240), started 0.4° off: without the blur
    model the photometric optimum lies 0.15° from the truth (measured), with it (the
    velocity from the neighbouring views' poses and times, the exposure given) 0.09°; the
    centres 0.078 % and 0.029 %. The bounds sit halfway."""
    from facecap_core.camera import camera_center
    from facecap_core.pose.evaluate import pose_errors
    from facecap_core.pose.pba import PBAConfig

    images, intr, R, t, points, hosts = _plane_scene(320, 240, blur_deg=5.0)
    rng = np.random.default_rng(0)
    turned = [R[0]] + [rotation_matrix(rng.normal(size=3), np.radians(0.4)) @ r for r in R[1:]]
    start_t = [-r @ camera_center(r0, x) for r, r0, x in zip(turned, R, t)]
    times = [0.1 * k for k in range(len(R))]  # 6° in 0.1 s: a 5° exposure is 5/6 of a frame
    errors = {}
    for blur in (False, True):
        config = PBAConfig(motion_blur=blur, exposure_fraction=5 / 6)
        result = pba.photometric_bundle_adjustment(images, intr, turned, start_t, points,
                                                   config, sparse_hosts=hosts, times=times,
                                                   frame_interval_s=0.1)
        errors[blur] = pose_errors(result.R, result.t, result.intrinsics, R, t, intr)
        assert result.exposure_fraction == (pytest.approx(5 / 6) if blur else None)
    assert errors[True]["rotation_deg"] < 0.8 * errors[False]["rotation_deg"], errors
    assert errors[True]["centre_pct"] < 0.6 * errors[False]["centre_pct"], errors


def _arc_scene(arc_deg: float, pp: tuple[float, float], noise_px: float, seed: int = 0,
               turn_deg: float = 0.3):
    """Twelve cameras on an arc of ``arc_deg`` round 300 points, their observations with
    Gaussian noise, and a start: the cameras turned ``turn_deg``, the principal point at
    (165.5, 113.5) (the image centre plus 6 px), the focal length 1 % off."""
    from facecap_core.camera import look_at

    rng = np.random.default_rng(seed)
    intr = Intrinsics(320, 240, 300.0, 300.0, pp[0], pp[1], -0.05, 0.01)
    R, t = [], []
    for yaw in np.radians(np.linspace(-arc_deg / 2, arc_deg / 2, 12)):
        Rk, tk = look_at([400 * np.sin(yaw), 10.0, 400 * np.cos(yaw)], [0, 0, 0], [0, 1, 0])
        R.append(Rk), t.append(tk)
    points = rng.uniform(-80, 80, (300, 3))
    rows = []
    for k in range(len(R)):
        uv, _ = project(points, R[k], t[k], intr)
        uv = uv + rng.normal(0, noise_px, uv.shape)
        inside = np.all((uv > 10) & (uv < [310, 230]), 1)
        rows += [(n, k, *uv[n]) for n in np.flatnonzero(inside)]
    turned = [R[0]] + [rotation_matrix(rng.normal(size=3), np.radians(turn_deg)) @ r
              for r in R[1:]]
    start_t = [tr @ (r.T @ x) for tr, r, x in zip(turned, R, t)]
    start = Intrinsics(320, 240, 303.0, 303.0, 159.5 + 6.0, 119.5 - 6.0, -0.05, 0.01)
    return intr, R, t, points, np.array(rows), turned, start_t, start


def test_the_tracks_alone_recover_exact_cameras_and_intrinsics():
    """The reprojection part of the joint solve on its own (blank keyframes: no photometric
    information): twelve cameras on a 80° arc, exact observations of 300 points, the start
    turned 0.5° with the focal length 1 % and the principal point 4 px off, and the points
    moved by 1 mm. Gauss-Newton on exact data converges to the exact cameras: the bounds
    are float rounding (tests/tolerances.py)."""
    from facecap_core.pose.evaluate import pose_errors
    from facecap_core.pose.pba import PBAConfig

    intr, R, t, points, rows, turned, start_t, start = _arc_scene(80.0, (163.0, 117.0), 0.0,
                                                                   turn_deg=0.5)
    rng = np.random.default_rng(1)
    moved = points + rng.normal(0, 1.0, points.shape)
    blank = [np.full((240, 320), 100.0, np.float32) for _ in R]
    config = PBAConfig(iterations=30, pyramid_levels=1, motion_blur=False,
                       principal_point_prior_pct=0.0)  # exact data: nothing but the data
    result = pba.photometric_bundle_adjustment(blank, start, turned, start_t, moved, config,
                                               sparse_hosts=np.full(len(points), 5),
                                               tracks=(moved, rows))
    before = pose_errors(turned, start_t, start, R, t, intr)
    after = pose_errors(result.R, result.t, result.intrinsics, R, t, intr)
    assert before["rotation_deg"] == pytest.approx(0.5) and before["focal_pct"] > 0.99
    expect_exact_cameras(after)


def test_a_held_principal_point_stays_where_it_started():
    """``hold_principal_point``: from the scene above (the start turned 0.5°, its focal length
    1 % and its principal point 4 px off), the principal point ends where it started while
    the focal length is still refined (towards the truth: the data pin it)."""
    from facecap_core.pose.evaluate import pose_errors
    from facecap_core.pose.pba import PBAConfig

    intr, R, t, points, rows, turned, start_t, start = _arc_scene(80.0, (163.0, 117.0), 0.0,
                                                                   turn_deg=0.5)
    blank = [np.full((240, 320), 100.0, np.float32) for _ in R]
    config = PBAConfig(iterations=30, pyramid_levels=1, motion_blur=False,
                       hold_principal_point=True)
    result = pba.photometric_bundle_adjustment(blank, start, turned, start_t, points, config,
                                               sparse_hosts=np.full(len(points), 5),
                                               tracks=(points, rows))
    got = result.intrinsics
    assert abs(got.cx - start.cx) < 1e-6 and abs(got.cy - start.cy) < 1e-6, got
    before = pose_errors(turned, start_t, start, R, t, intr)
    after = pose_errors(result.R, result.t, got, R, t, intr)
    assert after["focal_pct"] < 0.5 * before["focal_pct"], (before, after)


def test_a_principal_point_the_geometric_refinement_held_stays_held():
    """A principal point held at the image centre by the geometric refinement (the tracks put
    it beyond a phone's) is held by PBA too, through the pose stage's own call, and the
    cameras say so after any reordering; without the flag the same data move it (towards
    the truth, 4 px away)."""
    from facecap_core.pose.colmap_sfm import Poses
    from facecap_core.pose.pba import PBAConfig
    from facecap_core.pose.stage import PoseConfig, photometric_refinement, reorder

    intr, R, t, points, rows, turned, start_t, start = _arc_scene(80.0, (163.0, 117.0), 0.0,
                                                                   turn_deg=0.5)
    blank = [np.full((240, 320), 100.0, np.float32) for _ in R]
    config = PoseConfig(pba=PBAConfig(iterations=30, pyramid_levels=1, motion_blur=False,
                                      principal_point_prior_pct=0.0))
    for held in (True, False):
        poses = Poses(start, list(range(len(R))), turned, start_t, points, 0.0, rows,
                      principal_point_held=held)
        refined = photometric_refinement(poses, blank, config)
        shift = np.hypot(refined.intrinsics.cx - start.cx, refined.intrinsics.cy - start.cy)
        assert bool(shift < 1e-6) is held, shift
        assert refined.principal_point_held is held
        assert reorder(refined, np.arange(len(R))[::-1]).principal_point_held is held


@pytest.mark.parametrize("noise_px", [0.5, 0.01], ids=["noisy tracks", "exact tracks"])
def test_the_principal_point_prior_gives_way_to_the_data(noise_px):
    """Twelve cameras on an 80° arc: a tilt of every camera and a shift of the principal
    point reproject almost alike, so tracks with half a pixel of noise leave the principal
    point several pixels off from a bundle adjustment with it free (what the geometric
    refinement hands PBA). From that start, the prior (1 % of the image) brings it back to
    the true one (at the centre here) and the rotations with it. Where the tracks are nearly
    exact the prior gives way: a principal point 5 px off the centre (1.25 % across) is kept."""
    from facecap_core.pose.evaluate import pose_errors
    from facecap_core.pose.geometric import triangulate
    from facecap_core.pose.pba import PBAConfig

    pp = (159.5, 119.5) if noise_px > 0.1 else (163.5, 116.5)
    intr, R, t, points, rows, turned, start_t, start = _arc_scene(80.0, pp, noise_px)
    blank = [np.full((240, 320), 100.0, np.float32) for _ in R]
    config = PBAConfig(iterations=30, pyramid_levels=1, motion_blur=False,
                       principal_point_prior_pct=0.0)
    free = pba.photometric_bundle_adjustment(blank, start, turned, start_t, points, config,
                                             sparse_hosts=np.full(len(points), 5),
                                             tracks=(points, rows))
    X, obs = triangulate(rows, free.R, free.t, free.intrinsics, min_views=2, max_error_px=3.0)
    prior = pba.photometric_bundle_adjustment(
        blank, free.intrinsics, free.R, free.t, X,
        config.model_copy(update={"principal_point_prior_pct": 1.0}),
        sparse_hosts=np.full(len(X), 5), tracks=(X, obs))
    before = pose_errors(free.R, free.t, free.intrinsics, R, t, intr)
    after = pose_errors(prior.R, prior.t, prior.intrinsics, R, t, intr)
    if noise_px > 0.1:
        assert before["principal_point_px"] > 3.0, before
        assert after["principal_point_px"] < 1.5, after
        assert after["rotation_deg"] < 0.5 * before["rotation_deg"], (before, after)
    else:
        # Both within half a pixel of the truth; the centre is 5 px from it.
        assert before["principal_point_px"] < 0.5, before
        assert after["principal_point_px"] < 0.5, after


def test_the_tracks_under_a_rolling_shutter_recover_the_cameras():
    """Twelve cameras turning 40°/s, each image read out top to bottom in 30 ms: the
    observations are the points seen by the camera moved for their row's time (a constant
    velocity through the neighbouring cameras). Adjusted to the tracks with the true readout
    from cameras turned 0.2°, they come back exactly (float rounding, as above); a global
    shutter model cannot explain the same observations (its cost stays orders higher)."""
    from facecap_core.camera import look_at

    rng = np.random.default_rng(1)
    intr = Intrinsics(320, 240, 300.0, 300.0, 161.0, 118.0, -0.05, 0.01)
    K, readout = 12, 0.03
    times = 0.1 * np.arange(K)
    R, t = [], []
    for yaw in np.radians(np.linspace(-20, 20, K)):
        Rk, tk = look_at([400 * np.sin(yaw), 10.0, 400 * np.cos(yaw)], [0, 0, 0], [0, 1, 0])
        R.append(Rk), t.append(tk)
    velocity = pba.camera_motion(R, t, times, 1.0)
    points = rng.uniform(-80, 80, (300, 3))
    rows = []
    for k in range(K):
        Xc = points @ R[k].T + t[k]
        uv, _ = project(points, R[k], t[k], intr)
        for _ in range(5):  # the row that sees each point, by fixed-point iteration
            tau = readout * (uv[:, 1] / intr.height - 0.5)
            w, v = velocity[k, :3], velocity[k, 3:]
            moved = Xc + tau[:, None] * (np.cross(w, Xc) + v)
            uv, _ = project(moved, np.eye(3), np.zeros(3), intr)
        inside = np.all((uv > 10) & (uv < [310, 230]), 1)
        rows += [(n, k, *uv[n]) for n in np.flatnonzero(inside)]
    rows = np.array(rows)
    order = np.argsort(rows[:, 0], kind="stable")
    obs_start = np.searchsorted(rows[order, 0].astype(np.int64), np.arange(len(points) + 1))
    frames, xy = rows[order, 1].astype(np.int64), rows[order, 2:4]
    intr_v = np.array([intr.fx, intr.cx, intr.cy, intr.k1, intr.k2])

    def velocity_of(R_, t_):
        return pba.camera_motion(R_, t_, times, 1.0)

    turned = [R[0]] + [rotation_matrix(rng.normal(size=3), np.radians(0.2)) @ r for r in R[1:]]
    start_t = [tr @ (r.T @ x) for tr, r, x in zip(turned, R, t)]
    costs = {}
    for model in (0.0, readout):
        cost, R_, t_, intr_, _ = normal.adjust_to_tracks(
            turned, start_t, intr_v, points.copy(), obs_start, frames, xy, intr.height,
            velocity_of, model, 1.0, 40)
        costs[model] = cost
    from facecap_core.pose.evaluate import pose_errors

    got = Intrinsics(320, 240, intr_[0], intr_[0], intr_[1], intr_[2], intr_[3], intr_[4])
    after = pose_errors(R_, t_, got, R, t, intr)
    expect_exact_cameras(after)
    # The scale is the gauge's: the first baseline keeps its length.
    baseline = [np.linalg.norm(r[1].T @ x[1] - r[0].T @ x[0]) for r, x in ((R_, t_), (R, t))]
    assert baseline[0] == pytest.approx(baseline[1], rel=1e-9)
    # Exact under the true readout (float rounding, ~1e-24 px² in all); a global shutter
    # folds most of the shear into the cameras but cannot reach zero (measured 0.016 px²).
    assert costs[readout] < 1e-12 and costs[0.0] > 1e-3, costs
