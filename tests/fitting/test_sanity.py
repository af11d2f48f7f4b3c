"""Mesh sanity checks of a fit against its template, and the relaxation that restores it."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from facecap_core.camera import rotation_matrix
from facecap_core.fitting.sanity import MAX_EDGE_STRETCH, check_mesh, relax_folds


@pytest.fixture(scope="module")
def sphere():
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=50.0)
    return np.asarray(mesh.vertices, float), np.asarray(mesh.faces, np.int64)


def _smooth_fit(vertices):
    """The template moved by a similarity and deformed smoothly (a bump of a few mm)."""
    bump = 4.0 * np.exp(-np.sum((vertices - [0, 0, 50]) ** 2, 1) / 400.0)[:, None]
    deformed = vertices + bump * vertices / 50.0
    return 1.3 * deformed @ rotation_matrix([0.2, 1, 0.1], 0.8).T + [10.0, -4.0, 2.0]


def test_a_smooth_deformation_is_sane(sphere):
    vertices, faces = sphere
    sanity = check_mesh(_smooth_fit(vertices), faces, vertices)
    assert sanity.ok and sanity.flipped == 0 and sanity.stretched_edges == 0
    assert sanity.self_intersecting_pairs == 0 and sanity.max_edge_stretch < 1.5


def test_a_spike_and_a_fold_are_found_and_relaxed(sphere):
    vertices, faces = sphere
    fit = _smooth_fit(vertices)
    centre = fit.mean(0)
    spike, fold = 100, 400
    # A spike: one vertex pulled out to twice the radius (its edges ~20x their length).
    fit[spike] = centre + 2.0 * (fit[spike] - centre)
    # A fold: a vertex slid sideways past its ring of neighbours (1.8 edge lengths), so the
    # triangles on the far side turn over.
    ring = np.unique(faces[np.any(faces == fold, axis=1)])
    neighbour = ring[ring != fold][0]
    fit[fold] += 1.8 * (fit[neighbour] - fit[fold])
    sanity = check_mesh(fit, faces, vertices)
    assert not sanity.ok
    assert sanity.stretched_edges >= 5 and sanity.max_edge_stretch > MAX_EDGE_STRETCH
    assert sanity.flipped >= 2  # the two triangles on the edge it slid across

    relaxed, info = relax_folds(fit, faces, vertices)
    after = check_mesh(relaxed, faces, vertices)
    assert after.ok, after
    # Only the neighbourhoods of the two defects moved; the rest of the fit is kept.
    moved = np.linalg.norm(relaxed - fit, axis=1) > 1e-9
    assert moved[spike] and moved[fold]
    assert 0 < info["relaxed_vertices"] < len(vertices) // 4
    assert moved.sum() <= info["relaxed_vertices"]


def test_a_surface_pushed_through_another_is_a_self_intersection(sphere):
    vertices, faces = sphere
    fit = vertices.copy()
    # A patch around the north pole pushed down through the south pole, its triangles kept
    # the right way round (no flip) but cutting the far side of the sphere.
    north = vertices[:, 2] > 45
    fit[north] -= [0, 0, 110.0]
    sanity = check_mesh(fit, faces, vertices)
    assert sanity.self_intersecting_pairs > 0


def test_a_fold_the_membrane_leaves_is_moved_with_its_template_triangle(sphere):
    """Without membrane rounds, a folded triangle is moved as its template triangle is (its
    three corners share their mean deformation): unfolded, and nothing else moves."""
    vertices, faces = sphere
    fit = _smooth_fit(vertices)
    tri = faces[0]
    a, b, c = fit[tri]
    fit[tri[2]] = a + b - c  # the apex reflected through the opposite edge: flipped
    assert check_mesh(fit, faces, vertices).flipped >= 1
    relaxed, info = relax_folds(fit, faces, vertices, rounds=0, check_intersections=False)
    sanity = check_mesh(relaxed, faces, vertices)
    assert sanity.flipped == 0 and info["snapped_triangles"] >= 1
    untouched = np.setdiff1d(np.arange(len(fit)), faces[np.any(np.isin(faces, tri), 1)])
    assert np.array_equal(relaxed[untouched], fit[untouched])
