"""Ear detector + contour predictor: shipped model, held-out renders, contour definition, inputs."""

from __future__ import annotations

import numpy as np
import pytest

import facecap.ear_training as et
from facecap_core.errors import InputError
from facecap_core.landmarks import ears


@pytest.fixture(scope="module")
def held_out_renderer(ict_model):
    """ICT identity 0 (never used for training) in a textured room."""
    from facecap.synthetic import Room

    transfer = et.load_contour_file(ears.MODELS_DIR / et.CONTOUR_FILE)["ict"]
    return et.ict_ear_renderer(ict_model, 0, transfer,
                               room=Room.random(np.random.default_rng(11)))


def test_model_ships_inside_the_package():
    assert ears.model_available()
    for name in (et.DETECTOR_FILE, et.PREDICTOR_FILE, et.CONTOUR_FILE):
        path = ears.MODELS_DIR / name
        assert path.is_file() and path.stat().st_size < 8_000_000
    k = len(ears.EAR_VERTEX_IDS["left"])
    assert 8 <= k <= 15 and len(ears.EAR_VERTEX_IDS["right"]) == k


def test_contour_vertices_are_the_template_ear_rims():
    from facecap_core.template import Template, head_frame

    template = Template.default()
    R, origin = head_frame(template.landmark_points)
    for side, sign in (("left", 1), ("right", -1)):
        ids = ears.EAR_VERTEX_IDS[side]
        # The shipped ids are what the definition gives (reproducible from the template).
        np.testing.assert_array_equal(ids, et.template_ear_contour(template, side, len(ids)))
        assert template.regions["ears"][ids].all()
        p = (template.vertices[ids] - origin) @ R.T
        assert np.all(np.sign(p[:, 0]) == sign)
        # Ordered helix root -> top -> back -> lobe: starts high, ends at the lowest point,
        # and passes behind both ends.
        assert p[0, 1] > p[-1, 1] + 30 and np.argmin(p[:, 1]) >= len(ids) - 2
        assert p[len(ids) // 2, 2] < min(p[0, 2], p[-1, 2]) - 10


@pytest.mark.parametrize("side", ["left", "right"])
def test_finds_a_held_out_ear_in_profile(held_out_renderer, side):
    rng = np.random.default_rng(5 if side == "left" else 6)
    sample = held_out_renderer.view(side, yaw_deg=85.0, elevation_deg=5.0, roll_deg=3.0,
                                    distance_mm=420.0, ear_height_px=120.0, size=400, rng=rng,
                                    look_jitter=0.1)
    held_out_renderer.render(sample, rng, mirror_right=False)
    det = ears.detect_ears(sample.image, side)
    assert det is not None and det.side == side
    assert det.points.shape == (len(ears.EAR_VERTEX_IDS[side]), 2)
    score = et.score_detection(sample, det)
    assert score["detected"], score
    assert score["nme"] < 0.08, score
    # The model is side-specific: asked for the other ear, it finds none in this view.
    assert ears.detect_ears(sample.image, "right" if side == "left" else "left") is None


def test_rendered_set_is_reused_only_for_the_same_rendering_settings():
    from facecap.ear_training.config import EarTrainingConfig

    base = EarTrainingConfig()
    assert et.render_key(base) == et.render_key(EarTrainingConfig(detector_c=5.0, threads=1))
    assert et.render_key(base) != et.render_key(EarTrainingConfig(yaw_deg=(40.0, 100.0)))
    assert et.render_key(base) != et.render_key(EarTrainingConfig(seed=1))


def test_no_ear_in_a_plain_image():
    rng = np.random.default_rng(0)
    flat = np.full((240, 320, 3), 128, np.uint8) + rng.integers(0, 3, (240, 320, 3), np.uint8)
    assert ears.detect_ears(flat, "left") is None


@pytest.mark.parametrize("image, side, words", [
    (np.zeros((0, 0), np.uint8), "left", "too small"),
    (np.zeros((64, 64, 3), np.float32), "left", "uint8"),
    (np.zeros((64, 64, 2), np.uint8), "left", "shape"),
    ([[0, 1], [2, 3]], "left", "image array"),
    (np.zeros((64, 64), np.uint8), "front", "'left' or 'right'"),
])
def test_bad_inputs_raise_one_line(image, side, words):
    with pytest.raises(InputError) as err:
        ears.detect_ears(image, side)
    assert words in str(err.value) and "\n" not in str(err.value)


def test_james_hand_labelled_contour_is_reproducible_and_on_his_scan():
    """benchmarks/data/james_ear_contour.json: 12 points per side on the scan's surface, and
    tools/james_ear_contour.py rebuilds them from the stored hand traces."""
    import copy
    import importlib.util
    import json
    from pathlib import Path

    import trimesh

    from facecap.synthetic import make_subject
    from facecap.synthetic.config import SynthConfig

    root = Path(__file__).resolve().parents[2]
    doc = json.loads((root / "benchmarks/data/james_ear_contour.json").read_text())
    spec = importlib.util.spec_from_file_location("james_ear_contour",
                                                  root / "tools/james_ear_contour.py")
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    subject = make_subject(SynthConfig(subject="james"))
    mesh = trimesh.Trimesh(subject.vertices, subject.faces, process=False)
    rebuilt = tool.build(copy.deepcopy(doc), subject)
    for side, sign in (("left", 1), ("right", -1)):
        points = np.asarray(doc["contour"][side])
        assert points.shape == (12, 3) and np.all(np.sign(points[:, 0]) == sign)
        assert trimesh.proximity.closest_point(mesh, points)[1].max() < 0.05
        np.testing.assert_allclose(rebuilt["contour"][side], points, atol=0.01)
        assert doc["summary"][side]["reprojection_rms_px_all"] < 8
