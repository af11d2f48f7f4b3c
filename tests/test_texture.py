"""Vertex colours from the keyframes (``facecap_core/texture.py``); the colours of a fitted
head are tested with the fitting (``tests/fitting/test_fitting.py``)."""

from __future__ import annotations

import numpy as np

from facecap_core.camera import Intrinsics, look_at
from facecap_core.nonrigid.constraints import Keyframe
from facecap_core.texture import vertex_colours

SQUARE = np.array([[-50, -50, 0], [50, -50, 0], [50, 50, 0], [-50, 50, 0]], float)
SQUARE_FACES = np.array([[0, 1, 2], [0, 2, 3]])


def _frontal(image: np.ndarray) -> Keyframe:
    R, t = look_at(np.array([0, 0, 200.0]), np.zeros(3), np.array([0, 1.0, 0]))
    return Keyframe(image, Intrinsics(64, 64, 60.0, 60.0, 31.5, 31.5), R, t)


def test_each_vertex_takes_the_sharpest_view_and_a_view_left_nothing_samples_nothing():
    """Two keyframes see the same square from the front: the sharp one colours every vertex
    (its grey where the corners project, 16.5 to 46.5 px), so the featureless one is left no
    vertex and samples no pixel (an empty map, which OpenCV's remap refuses)."""
    sharp = np.full((64, 64, 3), 90, np.uint8)
    sharp[:4, ::2] = 250  # texture away from the corners: a sharpness above the other's 0
    flat = np.full((64, 64, 3), 200, np.uint8)
    colours, view = vertex_colours(SQUARE, SQUARE_FACES, [_frontal(sharp), _frontal(flat)])
    assert view.tolist() == [0, 0, 0, 0]
    assert colours.tolist() == [[90, 90, 90]] * 4


def test_vertices_no_keyframe_sees_are_filled_from_their_neighbours_or_grey():
    """Without keyframes every vertex is grey (128) and coloured by none (-1)."""
    colours, view = vertex_colours(SQUARE, SQUARE_FACES, [])
    assert view.tolist() == [-1] * 4 and colours.tolist() == [[128, 128, 128]] * 4
