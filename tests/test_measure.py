"""Distances on a mesh (:mod:`facecap_core.measure`): along the surface, against surfaces
whose geodesics are known, and the anatomical presets of ``report.json``."""

from __future__ import annotations

import json

import numpy as np
import trimesh

from facecap_core.fitting.stage import figures as fitting_figures
from facecap_core.measure import (
    PLACEMENT,
    PRESETS,
    SurfacePaths,
    distance_text,
    landmark_measurements,
    summary,
    under_scale,
)


def _grid(rows: int, cols: int, place) -> tuple[np.ndarray, np.ndarray]:
    """A grid of quads split in two, vertex (i, j) at ``place(i, j)``; columns wrap round
    when ``place`` does."""
    vertices = np.array([place(i, j) for i in range(rows) for j in range(cols)], float)
    faces = []
    for i in range(rows - 1):
        for j in range(cols - 1):
            a = i * cols + j
            faces += [[a, a + 1, a + cols + 1], [a, a + cols + 1, a + cols]]
    return vertices, np.array(faces)


def test_on_a_plane_the_surface_distance_is_the_straight_one():
    rng = np.random.default_rng(0)
    jitter = rng.normal(0, 0.3, (51, 51, 2))
    vertices, faces = _grid(51, 51, lambda i, j: [2 * j + jitter[i, j, 0],
                                                  2 * i + jitter[i, j, 1], 0.0])
    paths = SurfacePaths(vertices, faces)
    for a, b in ((0, 51 * 51 - 1), (10, 51 * 40 + 3), (5, 51 * 50 + 30)):
        length, points = paths.path(a, b)
        straight = np.linalg.norm(vertices[a] - vertices[b])
        assert straight <= length < straight * 1.001
        assert np.allclose(points[[0, -1]], vertices[[a, b]])


def test_round_a_cylinder_the_surface_distance_is_the_unrolled_one():
    """A polyhedral cylinder unrolls into a plane: its geodesic is a straight line there.
    The path found is never shorter and within 0.5 % of it."""
    n, radius = 128, 50.0
    width = 2 * radius * np.sin(np.pi / n)  # a side's width
    vertices, faces = _grid(81, n + 1, lambda i, j: [radius * np.cos(2 * np.pi * j / n),
                                                     radius * np.sin(2 * np.pi * j / n),
                                                     2.5 * i - 100])
    paths = SurfacePaths(vertices, faces)
    for (i1, j1), (i2, j2) in (((20, 0), (60, 32)), ((10, 5), (70, 20)), ((40, 0), (41, 40))):
        length, _ = paths.path(i1 * (n + 1) + j1, i2 * (n + 1) + j2)
        unrolled = np.hypot((j2 - j1) * width, 2.5 * (i2 - i1))
        assert unrolled * (1 - 1e-9) <= length < unrolled * 1.005


def test_the_presets_of_a_fitted_mesh_are_its_landmarks_distances(tmp_path):
    """``figures.measurements``: the fitting stage's measurements of its mesh (in
    ``fit.json``, its figures) under the scale's 1σ: each preset's straight distance is its
    two landmarks', the surface one no shorter; a fit.json without them gives none."""
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=80.0)
    ids = np.flatnonzero(sphere.vertices[:, 2] > 30)[:68]
    points = sphere.vertices[ids]
    (tmp_path / "fit.json").write_text(json.dumps({"timing": {}, "measurements":
                                                   landmark_measurements(sphere.vertices,
                                                                         sphere.faces, ids,
                                                                         None)}))
    found = under_scale(fitting_figures(tmp_path)["measurements"], 4.0)
    assert list(found) == [key for key, *_ in PRESETS]
    for key, name, i, j in PRESETS:
        m = found[key]
        straight = np.linalg.norm(points[i] - points[j])
        assert m["name"] == name and m["vertices"] == [int(ids[i]), int(ids[j])]
        assert abs(m["straight"]["mm"] - straight) < 1e-3
        assert m["surface"]["mm"] >= m["straight"]["mm"]
        assert abs(m["straight"]["sigma_mm"] - 0.04 * straight) < 1e-3
    outer = found["outer_eyes"]
    assert summary(found).startswith(
        f"Outer eye corners {outer['anatomical']['mm']:.1f} mm ± "
        f"{outer['anatomical']['sigma_mm']:.1f} mm (between its landmark vertices "
        f"{outer['straight']['mm']:.1f} mm straight, ")
    assert distance_text({"mm": 63.21, "sigma_mm": 2.53}, 4.0) == "63.2 mm ± 2.5 mm (±4.0 %, 1σ)"
    (tmp_path / "fit.json").write_text(json.dumps({"timing": {}}))
    assert "measurements" not in fitting_figures(tmp_path)


def test_a_presets_anatomical_figure_counts_where_the_landmarks_sit(monkeypatch):
    """A preset's anatomical figure: the straight distance less the placement's bias, ± the
    scale's 1σ and the placement's spread in quadrature; the scale's σ unknown, no ±; every
    preset has a placement."""
    from facecap_core import measure

    assert set(measure.PLACEMENT) == {key for key, *_ in PRESETS}
    monkeypatch.setitem(measure.PLACEMENT, "nose_width", (3.0, 4.0))
    got = measure.under_scale({"nose_width": {"straight": {"mm": 40.0}, "surface": {"mm": 45.0}}},
                              7.5)["nose_width"]
    assert got["anatomical"] == {"mm": 37.0, "sigma_mm": 5.0}  # 3 mm (7.5 % of 40) and 4 mm
    assert got["straight"] == {"mm": 40.0, "sigma_mm": 3.0}
    assert measure.anatomical("nose_width", 40.0, None) == {"mm": 37.0, "sigma_mm": None}


def test_the_measurements_row_says_which_uncertainty_it_gives():
    """The page's Measurements row: the anatomical figures with both errors named; a report
    from before them, the straight figures with the scale's alone, and no ± at all when the
    scale's σ is unknown."""
    from facecap.pages.figures import figure_rows

    made = {"nose_width": {"name": "Nose width", "straight": {"mm": 40.0}, "surface": {"mm": 45.0}}}

    def row(measurements):
        report = {"figures": {"measurements": measurements}}
        return dict((key, text) for key, _, text in figure_rows(report))["measurements"]

    with_both = under_scale(made, 7.5)
    bias, _ = PLACEMENT["nose_width"]
    assert row(with_both).startswith(f"Nose width {40.0 - bias:.1f} mm ± ")
    assert row(with_both).endswith("(anatomical: ± the metric scale's and the landmarks' "
                                   "placement 1σ)")
    before = {"nose_width": {**with_both["nose_width"]}}
    del before["nose_width"]["anatomical"]
    assert row(before).startswith("Nose width 40.0 mm ± 3.0 mm (between")
    assert row(before).endswith("(straight; ± the metric scale's 1σ)")
    assert row(under_scale(made, None)).startswith(f"Nose width {40.0 - bias:.1f} mm (between")
