"""Similarity transforms: exact recovery, proper rotations, weights and robustness."""

from __future__ import annotations

import math

import numpy as np
import pytest

from facecap_core.camera import rotation_matrix
from facecap_core.geometry import robust_similarity, umeyama


def similarity(seed: int):
    rng = np.random.default_rng(seed)
    R = rotation_matrix(rng.normal(size=3), math.radians(rng.uniform(10, 30)))
    t, s = rng.uniform(-20, 20, 3), rng.uniform(0.9, 1.1)
    return (lambda x: s * np.asarray(x) @ R.T + t), s, R, t


def test_umeyama_recovers_similarity_and_never_reflects():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(50, 3)) * 30
    T, s, R, t = similarity(3)
    s_hat, R_hat, t_hat = umeyama(src, T(src))
    assert s_hat == pytest.approx(s, rel=1e-12)
    np.testing.assert_allclose(R_hat, R, atol=1e-12)
    np.testing.assert_allclose(t_hat, t, atol=1e-10)
    s_rigid, R_rigid, _ = umeyama(src, src @ R.T + t, with_scale=False)
    assert s_rigid == 1.0 and np.allclose(R_rigid, R, atol=1e-12)
    # A mirror image is fitted by a proper rotation, not by the reflection.
    _, R_m, _ = umeyama(src, src * np.array([-1.0, 1.0, 1.0]))
    assert np.linalg.det(R_m) == pytest.approx(1.0)


def test_zero_weights_ignore_points_exactly():
    rng = np.random.default_rng(2)
    src = rng.normal(size=(40, 3)) * 30
    T, s, R, t = similarity(4)
    dst = T(src)
    dst[:5] += 50.0  # five points far off
    weights = np.r_[np.zeros(5), np.ones(35)]
    s_hat, R_hat, t_hat = umeyama(src, dst, weights=weights)
    assert s_hat == pytest.approx(s, rel=1e-12)
    np.testing.assert_allclose(R_hat, R, atol=1e-12)
    np.testing.assert_allclose(t_hat, t, atol=1e-10)


def test_robust_similarity_ignores_outliers():
    rng = np.random.default_rng(0)
    src = rng.normal(0, 40, (51, 3))
    R = rotation_matrix([1.0, 2.0, 0.5], 0.8)
    dst = 0.02 * src @ R.T + [1.0, -2.0, 3.0]
    dst[:6] += rng.normal(0, 0.5, (6, 3))  # 6 of 51 points 25 template-mm off
    s, R_est, t, w = robust_similarity(src, dst, iterations=10, cauchy_mm=2.0)
    assert s == pytest.approx(0.02, rel=2e-3) and np.allclose(R_est, R, atol=2e-3)
    assert np.all(w[:6] < 0.05) and np.all(w[6:] > 0.8)
    s_plain, _, _ = umeyama(src, dst)
    assert abs(s_plain - 0.02) > 10 * abs(s - 0.02)
