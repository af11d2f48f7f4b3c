"""Renders of a mesh for figures and the UI: error heat maps and shaded previews."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from facecap_core.camera import Intrinsics, look_at
from facecap_core.errors import InputError
from facecap_core.render import RaycastScene, interpolate, shade_lambert, vertex_normals

#: Height in pixels of the colour-bar strip under the heat-map views.
COLORBAR_HEIGHT = 60


_VIEW_DIRS = {  # direction from the centre to the camera, in the data convention
    "front": np.array([0.0, 0.0, 1.0]),
    "left": np.array([1.0, 0.0, 0.0]),  # the subject's left profile
    "right": np.array([-1.0, 0.0, 0.0]),
}


_GREY = 0.62
"""Albedo of what has no colour of its own in a render (no value, no vertex colour)."""


def render_views(vertices: np.ndarray, faces: np.ndarray, albedo, framed: np.ndarray,
                 views: Sequence[str] = ("front", "left", "right"), size: int = 480,
                 centre: np.ndarray | None = None) -> np.ndarray:
    """Shaded renders of a mesh, one ``size``×``size`` pinhole view per entry of ``views``
    ("front" looks along -z at the face, "left"/"right" are the subject's profiles from
    +x/-x), side by side on white (BGR uint8).

    ``albedo(triangle, bary)`` gives the BGR colour (0..1) of each hit pixel; the views frame
    ``framed`` (the points that matter, e.g. the face) and what lies near them (the rest of a
    head, not the shoulders of a bust), around ``centre`` (default: their bounding-box
    centre, so that profiles are centred too). Lambert shading from a headlight."""
    v = np.asarray(vertices, float)
    f = np.asarray(faces, np.int64)
    unknown = [name for name in views if name not in _VIEW_DIRS]
    if unknown or not views:
        raise ValueError(f"unknown view(s) {unknown}; use {', '.join(_VIEW_DIRS)}")
    if centre is None:
        mid = (framed.min(0) + framed.max(0)) / 2.0
        reach = 1.6 * float(np.max(np.linalg.norm(framed - mid, axis=1)))
        near = v[np.linalg.norm(v - mid, axis=1) <= reach]
        centre = (near.min(0) + near.max(0)) / 2.0
    centre = np.asarray(centre, float).reshape(3)
    near = v[np.linalg.norm(v - centre, axis=1) <= 1.6 * float(
        np.max(np.linalg.norm(framed - centre, axis=1)))]
    extent = float(np.max(np.linalg.norm(near - centre, axis=1))) or 1.0
    half_fov = math.radians(15.0)
    distance = 1.1 * extent / math.sin(half_fov)  # the framed sphere fits with a margin
    focal = (size / 2.0) / math.tan(half_fov)
    intr = Intrinsics(size, size, focal, focal, (size - 1) / 2.0, (size - 1) / 2.0)

    scene = RaycastScene()
    scene.add(v, f)
    normals = vertex_normals(v, f)
    tiles = []
    for name in views:
        eye = centre + distance * _VIEW_DIRS[name]
        R, t = look_at(eye, centre, np.array([0.0, 1.0, 0.0]))
        hits = scene.cast_camera(intr, R, t)
        img = np.ones((size, size, 3))  # white background
        ok = hits.valid
        if np.any(ok):
            tri, bary = hits.triangle[ok], hits.bary[ok]
            n = interpolate(normals, f, tri, bary)
            n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
            to_cam = eye - hits.points[ok]
            to_cam /= np.maximum(np.linalg.norm(to_cam, axis=1, keepdims=True), 1e-12)
            img[ok] = shade_lambert(albedo(tri, bary), n, to_cam, [(_VIEW_DIRS[name], 0.7)],
                                    ambient=0.35)
        tiles.append(np.clip(img * 255.0, 0, 255).astype(np.uint8))
    return np.concatenate(tiles, axis=1)


def _write_png(image: np.ndarray, out_png: str | Path) -> Path:
    out = Path(out_png)
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        written = cv2.imwrite(str(out), image)
    except cv2.error:  # OpenCV knows no writer for the suffix
        written = False
    if not written:
        raise InputError(f"could not write {out} (is the folder writable, the suffix .png?)")
    return out


def error_heatmap(vertices: np.ndarray, faces: np.ndarray, per_vertex_mm: np.ndarray,
                  out_png: str | Path, max_mm: float = 5.0,
                  views: Sequence[str] = ("front", "left", "right"), size: int = 480,
                  centre: np.ndarray | None = None) -> Path:
    """Render per-vertex errors on the mesh as a turbo heat map; writes one PNG, returns it.

    The views of :func:`render_views`, framing the vertices that have a value. Errors are
    coloured 0..``max_mm`` with OpenCV's TURBO map, nan (outside the region) in grey, with a
    colour bar labelled "0 mm" / f"{max_mm} mm".
    """
    v = np.asarray(vertices, float)
    f = np.asarray(faces, np.int64)
    e = np.asarray(per_vertex_mm, float).reshape(-1)
    if len(e) != len(v):
        raise ValueError(f"per_vertex_mm has {len(e)} values for {len(v)} vertices")
    lut = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None],
                            cv2.COLORMAP_TURBO)[:, 0, :] / 255.0  # BGR
    grey = np.full(3, _GREY)

    def albedo(tri, bary):
        err = interpolate(e[:, None], f, tri, bary)[:, 0]  # nan if any corner is nan
        idx = np.clip(np.nan_to_num(err / max_mm, nan=0.0), 0.0, 1.0)
        return np.where(np.isfinite(err)[:, None], lut[np.round(idx * 255).astype(int)], grey)

    framed = v[np.isfinite(e)] if np.any(np.isfinite(e)) else v
    views_img = render_views(v, f, albedo, framed, views, size, centre)
    width = views_img.shape[1]
    bar = np.full((COLORBAR_HEIGHT, width, 3), 255, np.uint8)
    x0, x1 = 90, max(width - 110, 100)
    ramp = np.linspace(0, 255, x1 - x0).round().astype(np.uint8)[None, :]
    bar[15:35, x0:x1] = cv2.applyColorMap(np.repeat(ramp, 20, axis=0), cv2.COLORMAP_TURBO)
    font = cv2.FONT_HERSHEY_SIMPLEX
    cv2.putText(bar, "0 mm", (10, 31), font, 0.55, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(bar, f"{max_mm} mm", (x1 + 8, 31), font, 0.55, (0, 0, 0), 1, cv2.LINE_AA)
    return _write_png(np.concatenate([views_img, bar], axis=0), out_png)


def mesh_render(vertices: np.ndarray, faces: np.ndarray, out_png: str | Path,
                vertex_colours: np.ndarray | None = None,
                views: Sequence[str] = ("front", "left", "right"), size: int = 480,
                framed: np.ndarray | None = None) -> Path:
    """The mesh in its vertex colours (RGB 0..255; grey without), in the views of
    :func:`render_views` framing ``framed`` (default: every vertex); writes one PNG."""
    v = np.asarray(vertices, float)
    f = np.asarray(faces, np.int64)
    if vertex_colours is None:
        bgr = np.full((len(v), 3), _GREY)
    else:
        bgr = np.asarray(vertex_colours, float)[:, 2::-1] / 255.0
    image = render_views(v, f, lambda tri, bary: interpolate(bgr, f, tri, bary),
                         v if framed is None else framed, views, size)
    return _write_png(image, out_png)
