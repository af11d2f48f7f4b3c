"""The geometric refinement (facecap_core/pose/geometric.py) on exact synthetic observations."""

import numpy as np
import pytest

from facecap_core.camera import Intrinsics, project, rotation_matrix
from facecap_core.keyframes import Keyframes
from facecap_core.pose import checks, geometric
from facecap_core.pose.colmap_sfm import Poses

PHOTOS = Keyframes(indices=list(range(16)), times=[0.0] * 16, sharpness=[1.0] * 16,
                   observations=np.zeros((0, 4)), video_size=(240, 320), frames_read=16,
                   ordered=False)
"""Sixteen photos without an order: the solve's figures without the order check's."""


def _orbit(intr, n=16, seed=0):
    """Cameras 400 mm from the origin, turning 150° round it (a sweep round a head), and the
    points of a 240 mm box round the origin with each view's exact pixels."""
    rng = np.random.default_rng(seed)
    R = [rotation_matrix([0, 1, 0], a) @ rotation_matrix([1, 0, 0], 0.1 * np.sin(3 * a))
         for a in np.radians(np.linspace(-75, 75, n))]
    t = [np.array([0.0, 0.0, 400.0]) for _ in R]
    points = rng.uniform(-120, 120, (400, 3))
    rows = []
    for v, (Rk, tk) in enumerate(zip(R, t)):
        uv, z = project(points, Rk, tk, intr)
        seen = (z > 0) & np.all((uv >= 0) & (uv <= [intr.width - 1, intr.height - 1]), axis=1)
        rows += [(j, v, *uv[j]) for j in np.flatnonzero(seen)]
    return R, t, points, np.array(rows, float)


def _refined(true, tmp_path):
    """The refinement of SfM-like cameras (principal point at the image centre, every
    camera turned by 0.3°) over exact observations of cameras with ``true``."""
    R, t, points, obs = _orbit(true)
    rng = np.random.default_rng(1)
    start_R = [rotation_matrix(rng.normal(size=3), np.radians(0.3)) @ Rk for Rk in R]
    centred = Intrinsics(true.width, true.height, true.fx, true.fy, (true.width - 1) / 2,
                         (true.height - 1) / 2)
    sfm = Poses(centred, list(range(len(R))), start_R, t, points, 0.0, obs)
    return geometric.refine_with_tracks(sfm, np.zeros((0, 4)), list(range(len(R))), tmp_path)


def test_a_phones_principal_point_is_found_and_one_no_phone_has_is_held_at_the_centre(
        tmp_path):
    # 1 % and 2 % off the centre: within the bound, the adjustment finds it (exact pixels).
    phone = Intrinsics(240, 320, 300.0, 300.0, 119.5 + 2.4, 159.5 - 6.4)
    assert geometric.principal_point_offset_pct(phone) == pytest.approx([1.0, 2.0])
    refined = _refined(phone, tmp_path / "phone")
    assert not refined.principal_point_held
    assert refined.intrinsics.cx == pytest.approx(phone.cx, abs=0.05)
    assert refined.intrinsics.cy == pytest.approx(phone.cy, abs=0.05)
    assert not checks.solve_figures(refined, PHOTOS)["principal_point_held"]
    # 5 % off in y (16 px), as far as the tracks of a rolling shutter put it: beyond the
    # bound, held at the centre, and the solve's figures say so.
    sheared = Intrinsics(240, 320, 300.0, 300.0, 119.5, 159.5 + 16.0)
    assert geometric.principal_point_offset_pct(sheared)[1] > geometric.PRINCIPAL_POINT_MAX_PCT
    refined = _refined(sheared, tmp_path / "sheared")
    assert refined.principal_point_held
    assert (refined.intrinsics.cx, refined.intrinsics.cy) == (119.5, 159.5)
    assert checks.solve_figures(refined, PHOTOS)["principal_point_held"]
