"""Tolerances the tests share, each derived from the arithmetic behind it, and the
comparisons built on them (as pycolmap's ``expect_equal_reconstructions``)."""

from __future__ import annotations

import math

import numpy as np

EPS = float(np.finfo(np.float64).eps)

EXACT_ROTATION_DEG = 1e-5
"""A rotation angle is arccos((trace - 1) / 2): near 0 a rounding error e in the trace
becomes sqrt(e) in the angle. A few float64 roundings (e ~ 10 eps) give sqrt(2 * 10 eps) rad
= 3.8e-6 degrees, so exact poses read as up to ~4e-6 degrees; the bound leaves a factor 2.5."""
assert math.degrees(math.sqrt(2 * 10 * EPS)) < EXACT_ROTATION_DEG / 2.5

EXACT_RELATIVE = 1e-6
"""Centres, focal lengths and principal points of exact cameras, as a fraction or a percent
of their size: the solves that make them accumulate ~1e3 roundings of ~1e-16 each, and
their conditioning (~1e5 on these scenes) brings that to ~1e-8; the bound leaves 100."""


def expect_exact_cameras(errors: dict) -> None:
    """``pose_errors(...)`` of cameras that should be the truth up to float rounding."""
    assert errors["rotation_deg"] < EXACT_ROTATION_DEG, errors
    assert errors["centre_pct"] < EXACT_RELATIVE, errors
    assert errors["focal_pct"] < EXACT_RELATIVE, errors
    assert errors.get("principal_point_px", 0.0) < EXACT_RELATIVE, errors


def expect_equal_cameras(one, two) -> None:
    """Two sets of cameras (``frame_indices``, ``R``, ``t``, ``intrinsics``) bit for bit."""
    assert list(one.frame_indices) == list(two.frame_indices)
    assert np.array_equal(np.asarray(one.R), np.asarray(two.R))
    assert np.array_equal(np.asarray(one.t), np.asarray(two.t))
    assert one.intrinsics == two.intrinsics
