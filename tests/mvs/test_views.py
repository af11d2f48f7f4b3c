"""View selection: evenly spread reference views, the paper's Gaussian score, pair scores."""

from __future__ import annotations

import math

import numpy as np
import pytest

from facecap_core.errors import InputError
from facecap_core.mvs import (
    gaussian_score,
    pair_scores,
    select_sources,
)


def test_reference_views_are_evenly_spread_over_the_sweep():
    from facecap_core.mvs.views import reference_views

    picked = reference_views(73, 40)
    assert len(picked) == 40 and picked[0] == 0 and picked[-1] == 72
    assert set(np.diff(picked)) <= {1, 2}
    assert reference_views(12, 40) == list(range(12))
    assert reference_views(5, 2) == [0, 4]


def test_gaussian_score_matches_the_paper():
    g = gaussian_score(np.array([10.0, 5.0, 20.0, 0.0, 30.0]))
    assert g[0] == pytest.approx(1.0)
    assert g[1] == pytest.approx(math.exp(-0.5))  # (5 - 10)^2 / (2 * 5^2)
    assert g[2] == pytest.approx(math.exp(-0.5))  # (20 - 10)^2 / (2 * 10^2)
    assert g[3] == pytest.approx(math.exp(-2.0))
    assert g[4] == pytest.approx(math.exp(-2.0))


def test_pair_scores_on_hand_made_geometry():
    # Cameras on a circle of radius 1 around two points at the origin, at 0°, 10°, 20°, 45°.
    angles = np.radians([0.0, 10.0, 20.0, 45.0])
    centres = np.stack([np.sin(angles), np.zeros(4), np.cos(angles)], 1) * 1000.0
    points = np.zeros((2, 3))
    vis = np.ones((4, 2), bool)
    vis[3, 1] = False  # camera 3 sees only the first point
    s = pair_scores(points, vis, centres)
    assert s[0, 1] == pytest.approx(2 * 1.0)
    assert s[0, 2] == pytest.approx(2 * math.exp(-0.5))
    assert s[1, 2] == pytest.approx(2 * 1.0)
    assert s[0, 3] == pytest.approx(math.exp(-(35.0 ** 2) / 200.0))
    assert np.allclose(s, s.T) and np.all(np.diag(s) == 0)
    assert list(select_sources(s, 2)[0]) == [1, 2]
    with pytest.raises(InputError, match="visibility"):
        pair_scores(points, vis[:, :1], centres)
