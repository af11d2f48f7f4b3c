"""Each part of the face's support by its own cloud, without a reference."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from facecap_core.fitting.quality import PARTS, part_masks, part_quality
from facecap_core.render import vertex_normals
from facecap_core.template import Template

SHIFT_MM = 1.0


@pytest.fixture(scope="module")
def template():
    return Template.default()


@pytest.fixture(scope="module")
def surface_cloud(template):
    """Points on the template's surface (4 a mm², a phone's fused cloud is ~1), their
    normals, and each point's nearest template vertex."""
    mesh = trimesh.Trimesh(template.vertices, template.faces, process=False)
    points, face_ids = trimesh.sample.sample_surface(mesh, int(mesh.area * 4.0), seed=3)
    nearest = template.faces[face_ids][:, 0]
    return points, mesh.face_normals[face_ids], nearest


def test_the_parts_are_disjoint_and_cover_the_face(template):
    masks = part_masks(template)
    assert list(masks) == list(PARTS)
    stacked = np.stack([masks[p] for p in PARTS if p != "ears"])
    assert stacked.sum(0).max() == 1  # one part a vertex
    assert np.array_equal(stacked.any(0), template.regions["face"])
    # Each part holds its own landmarks' vertices.
    ids = template.landmarks
    assert masks["nose"][ids[30]] and masks["mouth"][ids[62]] and masks["eyes"][ids[37]]
    assert masks["forehead"][ids[19]] and masks["jaw"][ids[8]]


def test_a_part_that_stands_off_its_cloud_says_by_how_much(template, surface_cloud):
    points, normals, nearest = surface_cloud
    masks = part_masks(template)
    # The cloud under the nose lies 1 mm inside the mesh; everywhere else on it.
    inside = masks["nose"][nearest]
    moved = points - SHIFT_MM * inside[:, None] * normals
    errors = np.where(inside, 0.3, 0.1)
    # Landmarks: the nose's 2 mm out of the surface along its normal, the rest on it.
    L = template.landmark_points.copy()
    n = vertex_normals(template.vertices, template.faces)[template.landmarks]
    L[27:36] += 2.0 * n[27:36]
    q = part_quality(template.vertices, template, moved, normals, errors, L)
    nose, mouth = q["parts"]["nose"], q["parts"]["mouth"]
    # The curvature within the 1.5 mm of a vertex's normal line moves a median by < 0.1 mm.
    assert nose["mesh_to_cloud_mm"] == pytest.approx(SHIFT_MM, abs=0.1)
    assert mouth["mesh_to_cloud_mm"] == pytest.approx(0.0, abs=0.1)
    assert nose["cloud_noise_mm"] == pytest.approx(0.3) and mouth["cloud_noise_mm"] == 0.1
    # 2 mm out of the mesh, whose cloud lies 1 mm inside it there.
    assert nose["landmark_to_cloud_mm"] == pytest.approx(2.0 + SHIFT_MM, abs=0.15)
    assert mouth["landmark_to_cloud_mm"] == pytest.approx(0.0, abs=0.1)
    assert len(q["landmarks_to_cloud_mm"]) == 68
    assert all(p["supported"] and p["supported_share"] > 0.9 for name, p in q["parts"].items()
               if name != "ears") or pytest.fail(str(q["parts"]))


def test_a_part_without_cloud_is_not_supported(template, surface_cloud):
    points, normals, nearest = surface_cloud
    masks = part_masks(template)
    keep = ~(masks["ears"] | masks["forehead"])[nearest]
    q = part_quality(template.vertices, template, points[keep], normals[keep], None,
                     template.landmark_points)
    assert not q["parts"]["ears"]["supported"] and not q["parts"]["forehead"]["supported"]
    assert q["parts"]["forehead"]["supported_share"] < 0.1
    assert q["parts"]["nose"]["supported"]
    assert q["parts"]["nose"]["cloud_noise_mm"] is None  # a cloud without errors
