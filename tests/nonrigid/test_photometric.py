"""The photometric refinement against an exact scene: a sphere with a 3D texture seen by a
sweep of pinhole cameras, every pixel ray-traced (no rasteriser between truth and test)."""

from __future__ import annotations

import numpy as np
import trimesh

from facecap_core.camera import Intrinsics
from facecap_core.nonrigid.constraints import Keyframe
from facecap_core.nonrigid.photometric import PhotometricConfig, _patch_scores, refine
from facecap_core.precompile import _patch_scores_signature

RADIUS = 60.0  # mm
DISTANCE = 350.0  # camera centre to the sphere's centre, mm
INTR = Intrinsics(320, 240, 500.0, 500.0, 159.5, 119.5)
YAWS = np.radians(np.arange(-30.0, 30.1, 7.5))  # nine views over 60°
RNG = np.random.default_rng(7)
# Six plane waves of 4-8 mm: at 290 mm and f = 500 px a pixel is 0.58 mm of skin, so the
# finest wave spans 7 pixels (no aliasing in a point-sampled image).
WAVES = RNG.normal(size=(6, 3))
WAVES *= (RNG.uniform(2 * np.pi / 8, 2 * np.pi / 4, 6) / np.linalg.norm(WAVES, axis=1))[:, None]
PHASES = RNG.uniform(0, 2 * np.pi, 6)


def _look_at(centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    z = -centre / np.linalg.norm(centre)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    return R, -R @ centre


def _render(R: np.ndarray, t: np.ndarray, textured: bool) -> np.ndarray:
    u, v = np.meshgrid(np.arange(INTR.width), np.arange(INTR.height))
    rays = np.stack([(u - INTR.cx) / INTR.fx, (v - INTR.cy) / INTR.fy, np.ones_like(u, float)],
                    axis=-1) @ R  # R.T @ ray for each pixel
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    centre = -R.T @ t
    b = rays @ centre
    disc = b * b - (centre @ centre - RADIUS ** 2)
    hit = disc > 0
    s = -b - np.sqrt(np.where(hit, disc, 0.0))
    points = centre + s[..., None] * rays
    value = 128.0 + (12.0 * np.sin(points @ WAVES.T + PHASES).sum(-1) if textured else 0.0)
    return np.where(hit, value, 0.0).clip(0, 255).astype(np.uint8)


def _keyframes(textured: bool = True) -> list[Keyframe]:
    frames = []
    for yaw in YAWS:
        R, t = _look_at(DISTANCE * np.array([np.sin(yaw), 0.0, np.cos(yaw)]))
        frames.append(Keyframe(_render(R, t, textured), INTR, R, t))
    return frames


def _sphere(radius: float) -> tuple[np.ndarray, np.ndarray]:
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=radius)  # edges ~2 mm
    return np.asarray(mesh.vertices, float), np.asarray(mesh.faces, np.int64)


BUMP_CENTRES = np.array([[np.sin(a), 0.0, np.cos(a)] for a in np.radians([-15.0, 15.0])])
BUMP_SIGMA = 8.0  # mm


def _bumps(vertices: np.ndarray) -> np.ndarray:
    """(n, 2): each vertex's Gaussian weight (σ 8 mm of arc) around each bump's centre."""
    unit = vertices / np.linalg.norm(vertices, axis=1, keepdims=True)
    arc = RADIUS * np.arccos(np.clip(unit @ BUMP_CENTRES.T, -1, 1))
    return np.exp(-0.5 * (arc / BUMP_SIGMA) ** 2)


def _bumpy(height: float) -> tuple[np.ndarray, np.ndarray]:
    """The sphere with a bump of ``height`` mm left of the front and a dent as deep right of
    it: a wrong shape whose mean offset over the front is zero."""
    v, f = _sphere(RADIUS)
    g = _bumps(v)
    return v * (1.0 + height * (g[:, 0] - g[:, 1]) / RADIUS)[:, None], f


def _heights(vertices: np.ndarray) -> np.ndarray:
    """The surface's height over the true sphere at the bump's and the dent's centres (the
    median over the vertices within 3 mm of each)."""
    near = _bumps(vertices) > np.exp(-0.5 * (3.0 / BUMP_SIGMA) ** 2)
    r = np.linalg.norm(vertices, axis=1) - RADIUS
    return np.array([np.median(r[near[:, k]]) for k in range(2)])


def test_a_bump_and_a_dent_of_more_than_a_pixel_are_flattened_onto_the_truth():
    v, f = _bumpy(0.6)
    assert np.allclose(_heights(v), [0.6, -0.6], atol=0.05)
    # Little smoothing: the default's (16, some four rings of the face's 1.2 mm edges)
    # spreads over this sphere's 2 mm edges as far as the bump is wide, and halves it.
    refined, log = refine(v, f, _keyframes(), PhotometricConfig(fit_weight=0.0, smoothness=1.0))
    # What is left is the smoothing's (a ring's spread over a bump of four rings) and the
    # patch's, which spans a third of the bump (measured: under 0.09 mm).
    assert np.all(np.abs(_heights(refined)) < 0.12), _heights(refined)
    assert log["rounds"][0]["measured"] > 1000
    # The far side, which no view sees, follows the front only through the smoothing of
    # the offsets over the mesh: nearly still.
    far = v[:, 2] < -0.5 * RADIUS
    assert np.abs(np.linalg.norm(refined[far], axis=1) - RADIUS).max() < 0.05


def test_the_position_is_the_fits():
    """A surface off by the same amount everywhere keeps its offset: the refinement changes
    the shape, the fused cloud places it (the weighted mean offset is taken out)."""
    v, f = _sphere(RADIUS + 0.6)
    refined, log = refine(v, f, _keyframes(), PhotometricConfig(fit_weight=0.0))
    assert log["rounds"][0]["measured"] > 1000
    # Front and back alike: the measured offsets, all -0.6 mm, less their mean, are zero.
    assert np.abs(np.linalg.norm(refined, axis=1) - (RADIUS + 0.6)).max() < 0.05


def test_the_fit_weight_holds_the_surface_between_the_fit_and_the_images():
    """With exact images a measurement weighs ``min(confidence / confidence_scale, 2)``
    against ``fit_weight``: the bump and the dent end between the fit's 0.6 mm and the
    truth's 0, nearer the fit the more it weighs (at least 0.6 × w / (2 + w): 0.12 mm for
    w = 0.5, 0.3 mm for w = 2)."""
    v, f = _bumpy(0.6)
    ends = [_heights(refine(v, f, _keyframes(),
                            PhotometricConfig(fit_weight=w, smoothness=1.0))[0])
            for w in (0.5, 2.0)]
    assert 0.1 < ends[0][0] < ends[1][0] < 0.5, ends
    assert -0.1 > ends[0][1] > ends[1][1] > -0.5, ends


def test_texture_less_views_move_nothing():
    """Every view the same grey: every offset scores the same, the peak is the first
    candidate (no parabola through it), so no vertex is measured and none moves."""
    v, f = _sphere(RADIUS + 0.6)
    refined, log = refine(v, f, _keyframes(textured=False))
    assert all(r["measured"] == 0 for r in log["rounds"])
    assert np.array_equal(refined, v)


def test_one_keyframe_measures_nothing():
    """No pair of views, no agreement to measure: the mesh as given."""
    v, f = _sphere(RADIUS + 0.6)
    refined, log = refine(v, f, _keyframes()[:1])
    assert np.array_equal(refined, v) and log["rounds"] == []


def test_the_kernel_runs_with_its_precompiled_signature():
    """A call with other argument types would compile again in the user's first capture."""
    v, f = _sphere(RADIUS + 0.6)
    refine(v, f, _keyframes()[:3], PhotometricConfig(rounds=1))
    assert _patch_scores.signatures == [_patch_scores_signature()]
