import cv2
import numpy as np

from facecap_core.camera import (
    Intrinsics,
    camera_center,
    distort,
    look_at,
    pixel_rays,
    project,
    rotation_angle_deg,
    rotation_matrix,
    undistort,
)

INTR = Intrinsics(640, 360, 500.0, 502.0, 321.3, 178.9, k1=0.08, k2=-0.02)


def test_undistort_inverts_distort():
    rng = np.random.default_rng(0)
    xy = rng.uniform(-0.7, 0.7, (1000, 2))
    np.testing.assert_allclose(undistort(distort(xy, 0.08, -0.02), 0.08, -0.02), xy, atol=1e-10)


def test_project_matches_opencv():
    rng = np.random.default_rng(1)
    pts = rng.uniform([-200, -150, 300], [200, 150, 600], (200, 3))
    R = rotation_matrix([0.2, 1.0, 0.1], 0.3)
    t = np.array([10.0, -5.0, 20.0])
    uv, z = project(pts, R, t, INTR)
    ref, _ = cv2.projectPoints(pts, cv2.Rodrigues(R)[0], t, INTR.K, INTR.dist)
    np.testing.assert_allclose(uv, ref.reshape(-1, 2), atol=1e-6)
    np.testing.assert_allclose(z, (pts @ R.T + t)[:, 2])


def test_pixel_rays_project_back_to_their_pixels():
    rays = pixel_rays(INTR)
    uv, _ = project(rays.reshape(-1, 3) * 400.0, np.eye(3), np.zeros(3), INTR)
    grid = np.stack(np.meshgrid(np.arange(640.0), np.arange(360.0)), -1).reshape(-1, 2)
    np.testing.assert_allclose(uv, grid, atol=1e-6)
    assert np.allclose(rays[..., 2], 1.0)


def test_look_at_convention():
    eye = np.array([0.0, 0.0, 500.0])
    R, t = look_at(eye, np.zeros(3), [0, 1, 0])
    np.testing.assert_allclose(camera_center(R, t), eye)
    assert np.isclose(np.linalg.det(R), 1.0)
    intr = Intrinsics(100, 100, 100, 100, 49.5, 49.5)
    uv, z = project(np.array([[0.0, 0, 0], [0, 50, 0], [50, 0, 0]]), R, t, intr)
    assert np.allclose(uv[0], [49.5, 49.5]) and z[0] > 0
    assert uv[1, 1] < 49.5  # world up is image up
    assert uv[2, 0] > 49.5  # camera looks down -z, so world +x is image right


def test_scaled_intrinsics_keep_the_field_of_view():
    half = INTR.scaled(320, 180)
    assert np.isclose(half.horizontal_fov_deg, INTR.horizontal_fov_deg)
    assert np.isclose(half.cx, (INTR.cx + 0.5) / 2 - 0.5)


def test_rotation_angle():
    assert np.isclose(rotation_angle_deg(rotation_matrix([0, 0, 1], np.radians(7)), np.eye(3)), 7)
