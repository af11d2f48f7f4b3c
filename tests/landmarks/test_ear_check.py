"""Ear points are checked before use: exact ICT ear contours pass, implausible ones are dropped
with a reason; reliability weights follow the triangulation's uncertainty."""

from __future__ import annotations

import numpy as np
import pytest

from facecap.ear_training.contour import load_contour_file
from facecap_core.landmarks import ear_check
from facecap_core.landmarks.ears import MODELS_DIR
from facecap_core.template import Template, head_frame, ict_identity_vertices, load_ict_model


@pytest.fixture(scope="module")
def head(ict_model):
    """An ICT identity's exact 68 landmarks and ear contour points (with their template
    vertex ids and sides) in a camera world: scaled to 1/80, turned and moved."""
    model = load_ict_model(ict_model)
    V = ict_identity_vertices(model, np.random.default_rng(5).standard_normal(100))
    contour = load_contour_file(MODELS_DIR / "ear_contour.json")
    ids = np.r_[contour["vertex_ids"]["left"], contour["vertex_ids"]["right"]]
    sides = np.array(["left"] * 12 + ["right"] * 12)
    points = np.r_[contour["ict"]["left"].on(V), contour["ict"]["right"].on(V)]
    angle = 0.7
    R = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    to_world = lambda p: (p @ R.T) / 80.0 + [0.3, -0.1, 4.0]  # noqa: E731
    return {"landmarks": to_world(V[model["landmarks68"]]), "ids": ids, "sides": sides,
            "points": to_world(points), "to_world": to_world, "R": R}


def _doc(head, points=None, inliers=None):
    return {"vertex_ids": head["ids"].tolist(), "sides": head["sides"].tolist(),
            "points": (head["points"] if points is None else points).tolist(),
            "observations": {"left": 60, "right": 60},
            "inliers": inliers or {"left": 60, "right": 60}}


def test_a_real_head_shape_keeps_both_ears(head):
    doc = ear_check.check_ears(_doc(head), head["landmarks"])
    assert doc["sides"] == head["sides"].tolist()
    for side in ("left", "right"):
        c = doc["checks"][side]
        assert c["used"] and c["points"] == 12 and c["offset_sigmas"] < ear_check.EAR_OFFSET_BOUND
        lo, hi = ear_check.EAR_WIDTH_RATIO_BOUNDS
        assert lo < c["width_ratio"] < hi


def test_ears_too_far_apart_are_both_dropped(head):
    """Ear points 20 % too far apart (the error a wrong detection scale gives) are dropped on
    both sides, and the reason names the width."""
    R, origin = head_frame(head["landmarks"])
    local = (head["points"] - origin) @ R.T
    local[:, 0] *= 1.2
    doc = ear_check.check_ears(_doc(head, local @ R + origin), head["landmarks"])
    assert doc["vertex_ids"] == [] and doc["points"] == []
    for side in ("left", "right"):
        assert not doc["checks"][side]["used"]
        assert "times the template's width" in doc["checks"][side]["reason"]


def test_an_ear_far_from_where_the_face_puts_it_is_dropped_alone(head):
    """The left ear moved 30 mm up (a detection on the hair above it): only it is dropped."""
    moved = head["points"].copy()
    moved[head["sides"] == "left"] += head["to_world"](np.array([0, 30.0, 0])) \
        - head["to_world"](np.zeros(3))
    doc = ear_check.check_ears(_doc(head, moved), head["landmarks"])
    assert set(doc["sides"]) == {"right"} and len(doc["sides"]) == 12
    assert "from where the face puts that ear" in doc["checks"]["left"]["reason"]
    assert doc["checks"]["right"]["used"]


def test_views_that_disagree_or_too_few_points_drop_a_side(head):
    doc = ear_check.check_ears(_doc(head, inliers={"left": 20, "right": 60}), head["landmarks"])
    assert "the views disagree" in doc["checks"]["left"]["reason"]
    assert set(doc["sides"]) == {"right"}
    few = _doc(head)
    keep = np.r_[np.arange(4), np.arange(12, 24)]
    few.update(vertex_ids=head["ids"][keep].tolist(), sides=head["sides"][keep].tolist(),
               points=head["points"][keep].tolist())
    doc = ear_check.check_ears(few, head["landmarks"])
    assert "4 of its contour points" in doc["checks"]["left"]["reason"]
    assert doc["checks"]["right"]["used"]


def test_reliability_is_the_inverse_variance_against_a_landmark():
    r = ear_check.EAR_RELIABLE_MM
    w = ear_check.reliability([0.0, 0.5 * r, r, 2 * r, 10 * r, np.nan])
    np.testing.assert_allclose(w, [1.0, 1.0, 1.0, 0.25, 0.01, 0.0])


def test_heads_outside_the_calibration_keep_their_ears(ict_model):
    """Heads drawn like the calibration's (seeds 1000-1199) but not among them keep both ears."""
    model = load_ict_model(ict_model)
    template = Template.default()
    contour = load_contour_file(MODELS_DIR / "ear_contour.json")
    ids = np.r_[contour["vertex_ids"]["left"], contour["vertex_ids"]["right"]]
    sides = np.array(["left"] * 12 + ["right"] * 12)
    for seed in range(1200, 1210):
        V = ict_identity_vertices(model, np.random.default_rng([seed, 1]).standard_normal(100))
        points = np.r_[contour["ict"]["left"].on(V), contour["ict"]["right"].on(V)]
        doc = ear_check.check_ears({"vertex_ids": ids.tolist(), "sides": sides.tolist(),
                                    "points": points.tolist(),
                                    "observations": {"left": 12, "right": 12},
                                    "inliers": {"left": 12, "right": 12}},
                                   V[model["landmarks68"]], template)
        assert all(c["used"] for c in doc["checks"].values()), (seed, doc["checks"])


def test_what_cannot_be_judged_is_said(head):
    """A side found in too few keyframes is reported; a document without the observation
    counts is not judged on them; too few face landmarks drop the ears with that reason;
    each kept point keeps its own uncertainty."""
    doc = _doc(head)
    keep = np.arange(12, 24)
    doc.update(vertex_ids=head["ids"][keep].tolist(), sides=["right"] * 12,
               points=head["points"][keep].tolist(), views={"left": 2, "right": 9},
               min_views=3, observations={"right": 60}, sigma=np.arange(12.0).tolist())
    out = ear_check.check_ears(doc, head["landmarks"])
    assert out["checks"]["left"] == {"points": 0, "used": False,
                                     "reason": "found in 2 keyframes (needs 3)"}
    assert out["checks"]["right"]["used"] and out["sigma"] == list(np.arange(12.0))
    bare = {k: v for k, v in _doc(head).items() if k not in ("observations", "inliers")}
    out = ear_check.check_ears(bare, head["landmarks"])
    assert all(c["used"] and "inlier_share" not in c for c in out["checks"].values())
    few = head["landmarks"].copy()
    few[20:] = np.nan
    out = ear_check.check_ears(_doc(head), few)
    assert out["vertex_ids"] == []
    assert all("too few face landmarks" in c["reason"] for c in out["checks"].values())
    # A dropped side takes its uncertainties with it.
    moved = head["points"].copy()
    moved[:12] += 40 * head["R"][:, 1] / 80.0
    out = ear_check.check_ears({**_doc(head, moved), "sigma": np.arange(24.0).tolist()},
                               head["landmarks"])
    assert out["sides"] == ["right"] * 12 and out["sigma"] == list(np.arange(12.0, 24.0))
