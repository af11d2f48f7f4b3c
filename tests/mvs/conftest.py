"""The small rendered capture the MVS tests share (built once for the package): its views,
ground-truth and coarse meshes, and each view's sources."""

from __future__ import annotations

import numpy as np
import pytest

from facecap.synthetic.config import SynthConfig
from facecap.synthetic.ground_truth import coarse_from_gt, load_views
from facecap_core.evaluation import region_sphere
from facecap_core.meshio import load_landmarks, load_mesh
from facecap_core.mvs import choose_sources, sparse_from_mesh
from facecap_core.mvs.depth import DepthMapConfig
from facecap_core.mvs.views import ViewSelectionConfig

# 320x180: 1 px ≈ 1.6 mm on the face, a quarter of the benchmark's pixels (docs/mvs.md).
WIDTH, HEIGHT, FRAMES = 320, 180, 18
KEYFRAMES = list(range(5, 13))  # the frontal half of an 18-frame ear-to-ear sweep


@pytest.fixture(scope="package")
def scene(tmp_path_factory, ict_model):
    """A small capture, its views, GT mesh, coarse mesh and sources."""
    from facecap.synthetic import synthesize

    folder = tmp_path_factory.mktemp("mvs")
    fps = FRAMES / 6.0
    # Same exposure time (1/120 s) as a 30 fps default capture: same motion blur.
    config = SynthConfig(subject="ict:2", ict_model=ict_model, width=WIDTH, height=HEIGHT,
                         fps=fps, duration_s=6.0, exposure_fraction=0.25 * fps / 30, seed=2)
    cap = synthesize(config, folder, progress=False)
    mesh = load_mesh(cap.gt_mesh)
    V, F = np.asarray(mesh.vertices, float), np.asarray(mesh.faces)
    views = load_views(folder, KEYFRAMES, WIDTH)
    cfg = DepthMapConfig(processing_width=WIDTH, window_radius=3, iterations=4)
    points, vis = sparse_from_mesh(views, V, F, count=1500)
    sources = choose_sources(views, points, vis, ViewSelectionConfig(num_sources=6))
    return {"views": views, "V": V, "F": F, "coarse": coarse_from_gt(V, F, seed=1),
            "config": cfg, "sources": sources,
            "sphere": region_sphere(load_landmarks(cap.gt_landmarks))}
