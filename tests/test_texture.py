"""Vertex colours and the UV atlas from the keyframes (``facecap_core/texture.py``); the
colours of a fitted head are tested with the fitting (``tests/fitting/test_fitting.py``)."""

from __future__ import annotations

import numpy as np
import trimesh

from facecap_core.camera import Intrinsics, look_at
from facecap_core.fitting.run import write_mesh
from facecap_core.nonrigid.constraints import Keyframe
from facecap_core.render import RaycastScene
from facecap_core.template import Template
from facecap_core.texture import UVLayout, bake_texture, sample_atlas, template_uv, vertex_colours

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


# --- UV atlas -----------------------------------------------------------------------------

PLANE_MM = 100.0


def _plane(cells: int = 10) -> tuple[np.ndarray, np.ndarray, UVLayout]:
    """A 100 mm square in z = 0 as a grid, its UVs the planar map u = x / 100 + 1/2 (one
    chart, no seams: the first N UV rows are the vertices)."""
    g = np.linspace(-PLANE_MM / 2, PLANE_MM / 2, cells + 1)
    x, y = np.meshgrid(g, g)
    v = np.c_[x.ravel(), y.ravel(), np.zeros(x.size)]
    i = np.arange(cells * (cells + 1)).reshape(cells, cells + 1)[:, :-1].ravel()
    f = np.concatenate([np.c_[i, i + 1, i + cells + 2], np.c_[i, i + cells + 2, i + cells + 1]])
    layout = UVLayout(v[:, :2] / PLANE_MM + 0.5, np.arange(len(v)), f)
    return v, f, layout


def _pattern(xy: np.ndarray) -> np.ndarray:
    """The plane's true colour at (x, y) mm: smooth waves of 40-50 mm, 68-188."""
    return np.stack([128 + 60 * np.sin(2 * np.pi * xy[..., 0] / 40.0),
                     128 + 60 * np.sin(2 * np.pi * xy[..., 1] / 50.0),
                     128 + 60 * np.cos(2 * np.pi * (xy[..., 0] + xy[..., 1]) / 45.0)], -1)


def _plane_views(v, f, yaws=(-20.0, 20.0), gains=(1.0, 1.0)) -> list[Keyframe]:
    """The plane ray-cast from 300 mm at each yaw (256 px, f = 300 px: 1 mm per pixel),
    its colour the pattern at the hit, times the view's exposure gain."""
    intr = Intrinsics(256, 256, 300.0, 300.0, 127.5, 127.5)
    scene = RaycastScene()
    scene.add(v, f)
    views = []
    for yaw, gain in zip(yaws, gains):
        a = np.radians(yaw)
        R, t = look_at(np.array([300 * np.sin(a), 0.0, 300 * np.cos(a)]), np.zeros(3),
                       np.array([0, 1.0, 0]))
        hits = scene.cast_camera(intr, R, t)
        img = np.zeros((256, 256, 3))
        img[hits.valid] = gain * _pattern(hits.points[hits.valid][:, :2])
        views.append(Keyframe(np.clip(np.round(img), 0, 255).astype(np.uint8), intr, R, t))
    return views


def _texel_truth(size: int) -> np.ndarray:
    """The pattern at the atlas's texel centres (row 0 at v = 1)."""
    c = (np.arange(size) + 0.5) / size
    u, v = np.meshgrid(c, 1.0 - c)
    return _pattern(np.stack([(u - 0.5) * PLANE_MM, (v - 0.5) * PLANE_MM], -1))


def test_the_template_uvs_lie_in_the_unit_square_and_map_every_face():
    """Every template triangle has UV corners in [0, 1] that are copies of its own vertices,
    with an area in the atlas; the first rows are the template's vertices in order."""
    template = Template.default()
    layout = template_uv(template.faces)
    assert layout is not None
    assert layout.uv.min() >= 0.0 and layout.uv.max() <= 1.0
    assert len(layout.faces) == len(template.faces)
    assert np.array_equal(layout.vertex[layout.faces], template.faces)
    assert np.array_equal(layout.vertex[:len(template.vertices)], np.arange(len(template.vertices)))
    corners = layout.uv[layout.faces]
    e1, e2 = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    assert (np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]) > 0).all()
    assert template_uv(template.faces[:, ::-1]) is None  # another topology has no UVs


def test_a_known_texture_is_recovered_from_two_views():
    """A plane whose colour is a known pattern, seen from ±20°: the baked atlas matches the
    pattern at the texel centres. The error budget per channel: the views' uint8 rounding
    (0.5), bilinear interpolation of the image at 1.06 mm per pixel (the pattern's second
    derivative is at most 60 (2π/40 mm)² = 1.5 per mm², so h²/8 per axis, 0.4 in all) and
    the atlas's rounding (0.5): 1.4 at most, far less on average. The outermost texels
    (centres 0.4 mm from the edge) are left out: their pixel straddles the plane's outline,
    and bilinear sampling mixes in the black beyond it."""
    v, f, layout = _plane()
    atlas, info = bake_texture(v, f, _plane_views(v, f), layout, size=128)
    err = np.abs(atlas.astype(float) - _texel_truth(128))[1:-1, 1:-1]
    assert info["texels_seen"] == info["texels"]
    assert err.max() <= 1.4 and err.mean() < 0.6, (err.max(), err.mean())


def test_views_of_unequal_exposure_are_evened_out():
    """The second view 20 % darker: the solved gains undo the ratio (within 1 %), and the
    atlas is the pattern at the views' mean exposure, without a step between the halves."""
    v, f, layout = _plane()
    views = _plane_views(v, f, gains=(1.0, 0.8))
    atlas, info = bake_texture(v, f, views, layout, size=128)
    gains = np.array(info["gains"])
    assert np.allclose(gains[1] / gains[0], 1 / 0.8, rtol=0.01), gains
    level = (atlas.astype(float) / _texel_truth(128))[1:-1, 1:-1]
    # One exposure over the whole atlas: left and right halves alike.
    assert abs(level[:, :64].mean() - level[:, 64:].mean()) < 0.01
    assert 0.8 <= level.mean() <= 1.0


def test_the_textured_obj_and_glb_read_back_with_their_image(tmp_path):
    """``mesh.obj`` keeps the vertices in order (its ``v`` lines) and reads back in trimesh
    with the atlas as its material's image; ``mesh.glb`` starts with the mesh's vertices and
    carries the atlas as baseColorTexture."""
    v, f, layout = _plane()
    atlas = np.zeros((64, 64, 3), np.uint8)
    atlas[:, :, 0] = np.arange(64)[None] * 4
    colours = np.full((len(v), 3), 200, np.uint8)
    write_mesh(tmp_path, v, f, colours, (layout, atlas))
    text = (tmp_path / "mesh.obj").read_text()
    assert "mtllib mesh.mtl" in text and text.count("\nv ") == len(v)
    assert (tmp_path / "mesh.mtl").read_text().strip().endswith("map_Kd texture.png")
    obj = trimesh.load(tmp_path / "mesh.obj", process=False, force="mesh")
    assert np.asarray(obj.visual.material.image).shape[:2] == (64, 64)
    assert len(obj.faces) == len(f) and np.allclose(obj.bounds, [[-50, -50, 0], [50, 50, 0]])
    glb = trimesh.load(tmp_path / "mesh.glb", process=False, force="mesh")
    image = np.asarray(glb.visual.material.baseColorTexture.convert("RGB"))
    assert np.array_equal(image, atlas)
    assert np.allclose(glb.vertices[:len(v)], v) and len(glb.faces) == len(f)
    assert np.allclose(glb.visual.uv, layout.uv, atol=1e-6)


def test_the_glb_names_the_vertex_of_each_seam_copy():
    """On the default template the glTF's vertices are the template's, then the seam copies,
    each named in the mesh's extras; a copy sits where its vertex does."""
    import io
    import json
    import struct

    from facecap_core.texture import glb_bytes

    template = Template.default()
    layout = template_uv(template.faces)
    data = glb_bytes(template.vertices, template.faces, layout, np.zeros((8, 8, 3), np.uint8))
    length = struct.unpack("<I", data[12:16])[0]
    extras = json.loads(data[20:20 + length])["meshes"][0]["extras"]
    n = extras["template_vertices"]
    assert n == len(template.vertices) and len(extras["seam_vertex"]) == len(layout.uv) - n
    glb = trimesh.load(io.BytesIO(data), file_type="glb", process=False, force="mesh")
    assert np.allclose(glb.vertices[n:], template.vertices[extras["seam_vertex"]], atol=1e-4)


def test_an_atlas_point_is_its_texel():
    """Sampling the atlas at a mesh point reads the texel at that point's UV."""
    v, f, layout = _plane()
    atlas = np.zeros((100, 100, 3), np.uint8)
    atlas[30, 70] = 255  # the texel centred on u = 0.705, v = 0.695
    tri = np.flatnonzero((layout.uv[f].mean(1) > 0.6).all(1) & (layout.uv[f].mean(1) < 0.8).all(1))
    # Barycentrics of the point (u, v) = (0.705, 0.695) in each candidate triangle.
    for t in tri:
        a, b, c = layout.uv[f[t]]
        m = np.c_[b - a, c - a]
        w = np.linalg.solve(m, np.array([0.705, 0.695]) - a)
        bary = np.array([1 - w.sum(), *w])
        if (bary >= 0).all():
            assert np.allclose(sample_atlas(atlas, layout, np.array([t]), bary[None]), 255)
            return
    raise AssertionError("no triangle holds the point")
