"""The trimmed ICT Face Model that ships in the package, and how the loader reads it."""

from __future__ import annotations

import hashlib
import re

import numpy as np

from facecap.synthetic import make_subject
from facecap.synthetic.config import SynthConfig
from facecap_core.assets import packaged_ict_model
from facecap_core.template import (
    ICT_SKIN_VERTEX_END,
    Template,
    ict_identity_vertices,
    ict_skin_faces,
    load_ict_model,
)

DATA = packaged_ict_model().parent


def test_packaged_model_is_the_documented_file():
    """The bytes are the ones tools/trim_ict_model.py made and data/README.md records."""
    readme = (DATA / "README.md").read_text()
    digest = hashlib.sha256(packaged_ict_model().read_bytes()).hexdigest()
    assert re.search(rf"This file.*sha256\s+`{digest}`", readme, re.S), "README: another sha256"
    assert "MIT License" in (DATA / "LICENSE-ict-face-model").read_text()
    assert packaged_ict_model().stat().st_size < 4_000_000


def test_packaged_model_loads_as_float32_with_the_skin_topology():
    model = load_ict_model(packaged_ict_model())
    assert model["identity_basis"].dtype == np.float32  # stored as float16
    assert model["identity_basis"].shape == (30, len(model["mean_vertices"]), 3)
    # Skin and socket vertices keep their indices: the skin faces and landmarks are the
    # full model's (11,248 skin vertices, 22,288 skin triangles).
    skin = ict_skin_faces(model)
    assert len(skin) == 22288 and np.unique(skin).size == ICT_SKIN_VERTEX_END
    assert np.all(model["landmarks68"] < ICT_SKIN_VERTEX_END)
    assert np.array_equal(model["source_vertex_ids"][:ICT_SKIN_VERTEX_END],
                          np.arange(ICT_SKIN_VERTEX_END))
    t = Template.from_ict(packaged_ict_model())
    assert t.vertices.shape == (ICT_SKIN_VERTEX_END, 3)
    # Metric (mm): the outer eye corners of the mean face are 89.2 mm apart.
    assert abs(np.linalg.norm(t.landmark_points[36] - t.landmark_points[45]) - 89.2) < 0.5


def test_coefficients_beyond_the_trimmed_modes_are_ignored():
    model = load_ict_model(packaged_ict_model())
    c = np.random.default_rng(0).standard_normal(100)
    np.testing.assert_array_equal(ict_identity_vertices(model, c),
                                  ict_identity_vertices(model, c[:30]))
    # The modes do change the head.
    assert np.abs(ict_identity_vertices(model, c) - ict_identity_vertices(model, None)).max() > 5


def test_ict_subjects_default_to_the_packaged_model(monkeypatch):
    monkeypatch.delenv("FACECAP_ICT_MODEL", raising=False)
    subject = make_subject(SynthConfig(subject="ict:1"))
    assert subject.info["identity_modes"] == 30
    monkeypatch.setenv("FACECAP_ICT_MODEL", str(packaged_ict_model()))
    again = make_subject(SynthConfig(subject="ict:1"))
    np.testing.assert_array_equal(subject.vertices, again.vertices)
