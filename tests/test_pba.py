"""Photometric bundle adjustment: its residual kernel against a direct numpy computation."""

import numba as nb
import numpy as np

from facecap_core.camera import Intrinsics, project, rotation_matrix, undistort
from facecap_core.pose import pba


def test_kernel_residuals_match_a_direct_warp():
    rng = np.random.default_rng(0)
    intr = Intrinsics(320, 240, 300.0, 300.0, 161.2, 118.7, -0.08, 0.02)
    # Two smooth random images; the point's true depth plays no role in this check.
    imgs = [np.asarray(__import__("cv2").GaussianBlur(rng.uniform(0, 255, (240, 320)).astype(
        np.float32), (0, 0), 2.0)) for _ in range(2)]
    R = [np.eye(3), rotation_matrix([0.1, 1.0, 0.0], 0.05)]
    t = [np.zeros(3), np.array([-20.0, 1.0, 2.0])]
    uv = rng.uniform([40, 40], [280, 200], (50, 2))
    rho = 1.0 / rng.uniform(300, 600, 50)
    host_values = np.stack([pba._sample(imgs[0], uv + d) for d in pba.PATTERN], 1)
    gx, gy = nb.typed.List(), nb.typed.List()
    for im in imgs:
        a, b = pba._gradients(im)
        gx.append(a)
        gy.append(b)
    R_rel, t_rel = pba._relative(R, t)
    n = len(uv)
    stats = np.zeros(2)
    pba._accumulate(np.zeros(n, np.int64), uv, rho, np.arange(n + 1, dtype=np.int64),
                    np.ones(n, np.int64), nb.typed.List(imgs), gx, gy, host_values,
                    np.ones((n, 8)), R_rel, t_rel, np.zeros((2, 2)),
                    np.array([intr.fx, intr.cx, intr.cy, intr.k1, intr.k2]), 1e9, 1e9, False,
                    np.zeros((13, 13)), np.zeros(13), np.zeros(n), np.zeros(n),
                    np.zeros((n, 21)), np.full((n, 21), -1, np.int64), stats)
    residuals = []
    for d in pba.PATTERN:
        u = uv + d
        xy = undistort(np.stack([(u[:, 0] - intr.cx) / intr.fx, (u[:, 1] - intr.cy) / intr.fy],
                                1), intr.k1, intr.k2)
        X = np.concatenate([xy, np.ones((n, 1))], 1) / rho[:, None]
        ut, _ = project(X, R[1], t[1], intr)
        residuals.append(pba._sample(imgs[1], ut) - pba._sample(imgs[0], u))
    residuals = np.concatenate(residuals)
    assert stats[1] == 8 * n
    np.testing.assert_allclose(stats[0], np.sum(residuals ** 2), rtol=1e-4)


def test_sparse_points_are_hosted_at_their_depth():
    intr = Intrinsics(320, 240, 300.0, 300.0, 161.2, 118.7, -0.08, 0.02)
    R = [np.eye(3), rotation_matrix([0.0, 1.0, 0.0], 0.1)]
    t = [np.zeros(3), np.array([-30.0, 0.0, 2.0])]
    rng = np.random.default_rng(1)
    points = np.column_stack([rng.uniform(-80, 80, 40), rng.uniform(-60, 60, 40),
                              rng.uniform(300, 500, 40)])
    points[0, 0] = 1e4  # outside every image: dropped
    hosts = np.array([0, 1] * 20)
    host, uv, rho = pba._points_from_sparse(points, hosts, R, t, intr, (240, 320))
    assert len(host) == 39 and set(host) == {0, 1}
    for k in (0, 1):
        sel = np.flatnonzero((hosts == k) & (np.arange(40) > 0))
        expected, z = project(points[sel], R[k], t[k], intr)
        np.testing.assert_allclose(uv[host == k], np.round(expected))
        np.testing.assert_allclose(rho[host == k], 1 / z)
