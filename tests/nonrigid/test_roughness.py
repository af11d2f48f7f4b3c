"""Reference-free measures of a fitted face: the bend across its edges and the split-half
distance, against geometry whose answer is known exactly."""

from __future__ import annotations

import numpy as np
import pytest

from facecap_core.evaluation import split_half_distance
from facecap_core.nonrigid.roughness import (
    BENT_DEG,
    bend_angles,
    face_edges,
    face_vertices,
    roughness,
)
from facecap_core.render import vertex_normals
from facecap_core.template import Template


def _grid(n: int = 101, spacing: float = 2.0):
    """A flat square grid (mm) in z = 0, two triangles a cell, and 68 'landmark' ids: the
    centre for 17-67 and two vertices 90 mm apart for the eye corners 36 and 45."""
    x, y = np.meshgrid(np.arange(n) * spacing, np.arange(n) * spacing)
    half = spacing * (n - 1) / 2
    V = np.c_[x.ravel() - half, y.ravel() - half, np.zeros(n * n)]
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), \
        idx[1:, 1:].ravel()
    F = np.r_[np.c_[a, b, d], np.c_[a, d, c]]
    centre = idx[n // 2, n // 2]
    landmarks = np.full(68, centre)
    landmarks[36], landmarks[45] = idx[n // 2, n // 2 - 22], idx[n // 2, n // 2 + 23]
    return V, F, landmarks


def test_a_flat_sheet_has_no_bend_and_a_crease_bends_exactly_there():
    V, F, lm = _grid()
    edges = face_edges(V, F, lm)
    assert len(edges) > 1000
    flat = roughness(V, F, edges)
    assert flat["bent_share_pct"] == 0 and flat["median_bend_deg"] == pytest.approx(0, abs=1e-6)
    # Fold the sheet along x = 0 by 30°: only the edges on the fold line bend, by 30°.
    folded = V.copy()
    right = V[:, 0] > 0
    angle = np.radians(30)
    folded[right, 0], folded[right, 2] = V[right, 0] * np.cos(angle), V[right, 0] * np.sin(angle)
    bends = bend_angles(folded, F, edges)
    on_fold = np.isclose(bends, 30.0, atol=1e-4)  # arccos near 1: ~1e-6°
    assert np.all(on_fold | np.isclose(bends, 0.0, atol=1e-4))
    # One fold edge per 2 mm cell row inside the region (70 mm either side of the centre,
    # less the rows whose triangles cross the circle), and each crosses the bend threshold.
    assert 60 <= on_fold.sum() <= 70
    rough = roughness(folded, F, edges)
    assert rough["bent_share_pct"] == pytest.approx(100 * on_fold.mean(), abs=0.01)
    assert BENT_DEG < 30


def test_the_region_is_the_templates_face_and_noise_makes_it_rough():
    t = Template.default()
    inside = face_vertices(t.vertices, t.landmarks)
    # The face region holds the nose, eyes and mouth, not the ears (nor the jaw's top, L0/L16).
    assert inside[t.landmarks[27:68]].all()
    assert not inside[t.landmarks[0]] and not inside[t.landmarks[16]]
    assert not inside[t.regions["ears"]].any()
    edges = face_edges(t.vertices, t.faces, t.landmarks)
    own = roughness(t.vertices, t.faces, edges)
    assert own["bent_share_pct"] < 3 and own["median_bend_deg"] < 1.5  # 2.2 % and 1.2°
    # 0.3 mm of independent noise along the normals over ~1.5 mm edges bends them by
    # ~atan(0.3 sqrt(2) / 1.5) ≈ 16° each: far rougher than any face.
    n = vertex_normals(t.vertices, t.faces)
    noisy = t.vertices + n * np.random.default_rng(0).normal(0, 0.3, (len(n), 1))
    rough = roughness(noisy, t.faces, edges)
    assert rough["bent_share_pct"] > 5 * own["bent_share_pct"]
    assert rough["median_bend_deg"] > 5 * own["median_bend_deg"]


def test_split_half_distance_ignores_the_frame_and_scale_and_measures_the_noise():
    t = Template.default()
    face = face_vertices(t.vertices, t.landmarks)
    c, s = np.cos(0.3), np.sin(0.3)
    R = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    moved = 1.04 * t.vertices @ R.T + [5.0, -3.0, 40.0]
    same = split_half_distance(t.vertices, moved, t.faces, face)
    assert same["median_mm"] < 1e-3 and same["p95_mm"] < 1e-3
    assert same["scale_ratio"] == pytest.approx(1 / 1.04, rel=1e-4)
    # Every vertex 0.2 mm in front of or behind the surface at random: a vertex lies at
    # most 0.2 mm from the other surface through its own position (plus the other's own
    # offset there), and the triangles between offsets pass nearer.
    n = vertex_normals(t.vertices, t.faces)
    sign = np.random.default_rng(1).choice([-1.0, 1.0], (len(n), 1))
    noisy = t.vertices + 0.2 * sign * n
    d = split_half_distance(t.vertices, noisy, t.faces, face)
    assert 0.05 < d["median_mm"] < 0.2 and d["p95_mm"] <= 0.21
    with pytest.raises(ValueError, match="vertex count"):
        split_half_distance(t.vertices, t.vertices[:-1], t.faces, face)
