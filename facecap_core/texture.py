"""Colour for the fitted mesh from the keyframes: per-vertex colours and a UV texture atlas.

:func:`vertex_colours` gives every vertex the colour of its best view: among the keyframes
where the vertex is visible (a ray from the camera centre reaches it unoccluded — the
z-buffer by ray casting) and faces the camera (``cos >= min_cos``), the one with the highest
``cos(view angle) × sharpness`` (sharpness: the frame's variance of the Laplacian, relative
to the sharpest keyframe), sampled bilinearly. Vertices no view sees take the mean colour of
their coloured neighbours (diffused over the mesh), then grey.

:func:`bake_texture` fills a UV atlas instead: the default template's UV layout is made once
(``tools/make_template_uv.py``, stored in ``facecap_core/data/template_uv.npz``) and, as the
fit keeps the template's topology, texel (u, v) is the same skin point on every face. Each
texel's point on the fitted mesh (the UV triangles rasterised with barycentric coordinates)
is seen by the keyframes where it faces the camera and passes a depth test against the
mesh's depth map; it takes their colours blended by a soft maximum of the same score,
``cos × sharpness``, so the best view rules and views of nearly equal score cross-fade
(no hard seam where the best view changes). A per-view, per-channel gain, solved from the
texels several views see, evens out exposure and white balance between the views. Texels
no view sees take the per-vertex colours; the gutters between charts are filled by
push-pull, so mip-maps and bilinear sampling show no seams.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import cv2
import numba
import numpy as np

from facecap_core.camera import Intrinsics, camera_center, distort, pixel_rays
from facecap_core.keyframes import sharpness
from facecap_core.render import RaycastScene, vertex_normals, visible_vertices

__all__ = ["ATLAS_SIZE", "UVLayout", "template_uv", "bake_texture", "vertex_colours"]

TEMPLATE_UV = Path(__file__).parent / "data" / "template_uv.npz"
ATLAS_SIZE = 1024
"""Texels on a side of the atlas: about 0.3 mm of skin per texel on the default template,
finer than a keyframe's pixel (0.4-0.6 mm at 960 px wide)."""
BLEND_SOFTNESS = 0.1
"""Views whose score (``cos × relative sharpness``) is this much below the best view's weigh
1/e of it: views of about equal score cross-fade (their noise averages out), a clearly worse
view adds little. On a synthetic 720p sweep (``benchmarks/bench_texture.py``) held-out frames
score 28.4, 28.9, 29.3 and 29.5 dB PSNR at 0.02, 0.05, 0.1 and 0.2; the larger the value,
the more a view's misregistration would blur a real capture, so 0.1."""
DEPTH_MAP_SCALE = 0.5
"""The visibility depth maps are cast at this fraction of the keyframe's resolution."""
GAIN_RANGE = (0.5, 2.0)
"""Per-view exposure gains are kept within this range (a larger one is a wrong match)."""


def _bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    img = image if image.ndim == 3 else np.repeat(image[..., None], 3, axis=2)
    if len(uv) == 0:  # cv2.remap refuses an empty map
        return np.zeros((0, 3), np.float32)
    # The maps are laid out in rows: OpenCV's remap takes at most 32767 rows or columns.
    n, cols = len(uv), min(len(uv), 4096)
    pad = -n % cols
    mx = np.pad(uv[:, 0].astype(np.float32), (0, pad)).reshape(-1, cols)
    my = np.pad(uv[:, 1].astype(np.float32), (0, pad)).reshape(-1, cols)
    out = cv2.remap(img.astype(np.float32), mx, my, cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(-1, 3)[:n]


def _diffuse(colours: np.ndarray, known: np.ndarray, faces: np.ndarray, rounds: int = 50
             ) -> tuple[np.ndarray, np.ndarray]:
    """Fill unknown vertex colours with the mean of known neighbours, ring by ring."""
    c, k = colours.copy(), known.copy()
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = np.concatenate([e, e[:, ::-1]])
    for _ in range(rounds):
        if k.all():
            break
        src = k[e[:, 0]] & ~k[e[:, 1]]
        if not src.any():
            break
        acc = np.zeros_like(c)
        cnt = np.zeros(len(c))
        np.add.at(acc, e[src, 1], c[e[src, 0]])
        np.add.at(cnt, e[src, 1], 1.0)
        new = cnt > 0
        c[new] = acc[new] / cnt[new, None]
        k = k | new
    return c, k


def _relative_sharpness(keyframes) -> np.ndarray:
    sharp = np.array([sharpness(kf.image) for kf in keyframes]) if len(keyframes) else np.zeros(0)
    return sharp / sharp.max() if len(sharp) and sharp.max() > 0 else np.ones(len(sharp))


def vertex_colours(vertices: np.ndarray, faces: np.ndarray, keyframes, min_cos: float = 0.25,
                   depth_tol_mm: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Per-vertex RGB (n, 3) uint8 and the keyframe index that coloured each vertex (-1:
    filled from neighbours or grey). ``keyframes`` are :class:`~facecap_core.fitting.Keyframe`
    (RGB uint8 images with cameras)."""
    v = np.asarray(vertices, float)
    f = np.asarray(faces, np.int64)
    n = len(v)
    normals = vertex_normals(v, f)
    scene = RaycastScene()
    scene.add(v, f)
    sharp_rel = _relative_sharpness(keyframes)
    best = np.full(n, -np.inf)
    view = np.full(n, -1)
    colours = np.zeros((n, 3))
    for k, kf in enumerate(keyframes):
        ids, cos, uv, _ = visible_vertices(scene, v, normals, kf.R, kf.t, kf.intrinsics,
                                           min_cos, depth_tol_mm)
        score = cos * sharp_rel[k]
        better = score > best[ids]
        ids, uv = ids[better], uv[better]
        best[ids] = score[better]
        view[ids] = k
        colours[ids] = _bilinear(kf.image, uv)
    known = view >= 0
    colours, known = _diffuse(colours, known, f)
    colours[~known] = 128.0
    return np.clip(np.round(colours), 0, 255).astype(np.uint8), view


# --- UV atlas ---------------------------------------------------------------------------


@dataclass(frozen=True)
class UVLayout:
    """Texture coordinates of a mesh topology, split at the seams."""

    uv: np.ndarray
    """float (M, 2) in [0, 1], OBJ convention: origin bottom-left, v up."""
    vertex: np.ndarray
    """int (M,): the mesh vertex of each UV vertex; the first N are the mesh's vertices in
    order, the rest copies of seam vertices."""
    faces: np.ndarray
    """int (F, 3): each triangle's corners as rows of :attr:`uv`, in the mesh's face order."""


def faces_digest(faces: np.ndarray) -> str:
    """What identifies a topology: the sha256 of its faces as int64."""
    return hashlib.sha256(np.ascontiguousarray(faces, np.int64).tobytes()).hexdigest()


@lru_cache(maxsize=1)
def _stored_layout() -> tuple[str, UVLayout] | None:
    if not TEMPLATE_UV.is_file():
        return None
    with np.load(TEMPLATE_UV) as z:
        return str(z["template_faces_sha256"]), UVLayout(
            z["uv"].astype(np.float64), z["vertex"].astype(np.int64), z["faces"].astype(np.int64))


def template_uv(faces: np.ndarray) -> UVLayout | None:
    """The stored UV layout if ``faces`` are the default template's (else None: a template
    of another topology has no UVs, and its mesh gets per-vertex colour only)."""
    stored = _stored_layout()
    if stored is None or len(faces) != len(stored[1].faces) or stored[0] != faces_digest(faces):
        return None
    return stored[1]


@dataclass
class Texels:
    """The atlas texels covered by the UV triangles: where each lies on the mesh."""

    index: np.ndarray  # (T,) flat index into the (size, size) image, row 0 at the top (v = 1)
    face: np.ndarray  # (T,) triangle
    bary: np.ndarray  # (T, 3) barycentric weights of its corners


def rasterise_uv(layout: UVLayout, size: int) -> Texels:
    """The texels whose centre lies in a UV triangle (a ray cast onto the flat atlas), and
    those within 0.75 texel of one (their closest point on it), so bilinear sampling at a
    chart's border reads the surface's colour."""
    import open3d as o3d  # heavy (a second to load): only a mesh with an atlas bakes one

    flat = np.c_[layout.uv[:, 0] * size - 0.5, (1.0 - layout.uv[:, 1]) * size - 0.5,
                 np.zeros(len(layout.uv))]
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(flat.astype(np.float32)),
                        o3d.core.Tensor(layout.faces.astype(np.uint32)))
    y, x = np.divmod(np.arange(size * size), size)
    rays = np.zeros((size * size, 6), np.float32)
    rays[:, 0], rays[:, 1], rays[:, 2], rays[:, 5] = x, y, 1.0, -1.0
    ans = scene.cast_rays(o3d.core.Tensor(rays))
    face = ans["primitive_ids"].numpy().astype(np.int64)
    uv = ans["primitive_uvs"].numpy().astype(np.float64)
    inside = face != np.int64(o3d.t.geometry.RaycastingScene.INVALID_ID)
    covered = inside.reshape(size, size).astype(np.uint8)
    ring = np.flatnonzero((cv2.dilate(covered, np.ones((3, 3), np.uint8)) > covered).ravel())
    if len(ring):
        near = scene.compute_closest_points(o3d.core.Tensor(
            np.c_[x[ring], y[ring], np.zeros(len(ring))].astype(np.float32)))
        points = near["points"].numpy()
        close = np.hypot(points[:, 0] - x[ring], points[:, 1] - y[ring]) <= 0.75
        ring = ring[close]
        face[ring] = near["primitive_ids"].numpy()[close]
        uv[ring] = near["primitive_uvs"].numpy()[close]
        inside[ring] = True
    index = np.flatnonzero(inside)
    b = np.clip(np.c_[1.0 - uv[index].sum(1), uv[index]], 0.0, None)
    return Texels(index, face[index], b / b.sum(1, keepdims=True))


def _depth_map(scene: RaycastScene, kf, rays: dict) -> tuple[np.ndarray, Intrinsics]:
    """The mesh's depth (camera z, mm) at :data:`DEPTH_MAP_SCALE` of the keyframe's size,
    the nearest over each 3×3 block (occluders grow by a pixel: a texel behind an edge is
    not taken for visible), and the camera at that size. ``rays``: the cameras' pixel rays
    so far (keyframes share their intrinsics: undistorting them once is enough)."""
    intr = kf.intrinsics
    small = intr.scaled(max(2, round(intr.width * DEPTH_MAP_SCALE)),
                        max(2, round(intr.height * DEPTH_MAP_SCALE)))
    if small not in rays:
        rays[small] = pixel_rays(small).reshape(-1, 3).astype(np.float32)
    d_world = rays[small] @ np.asarray(kf.R, np.float32)  # R.T @ d for each row
    origin = np.broadcast_to(camera_center(kf.R, kf.t).astype(np.float32), d_world.shape)
    depth = scene.cast(origin, d_world)["t_hit"].reshape(small.height, small.width)
    depth = np.where(np.isfinite(depth), depth, 1e9).astype(np.float32)
    return cv2.erode(depth, np.ones((3, 3), np.uint8)), small


def _project(points: np.ndarray, kf) -> tuple[np.ndarray, np.ndarray]:
    """:func:`~facecap_core.camera.project`, its rotation as einsum (several times faster
    than a matmul with three columns)."""
    pc = np.einsum("ij,kj->ik", points, np.asarray(kf.R, float)) + np.asarray(kf.t).reshape(3)
    z = pc[:, 2]
    xy = distort(pc[:, :2] / np.where(np.abs(z) > 1e-12, z, 1e-12)[:, None],
                 kf.intrinsics.k1, kf.intrinsics.k2)
    intr = kf.intrinsics
    return np.c_[intr.fx * xy[:, 0] + intr.cx, intr.fy * xy[:, 1] + intr.cy], z


def _view_samples(kf, depth: np.ndarray, small: Intrinsics, points: np.ndarray,
                  normals: np.ndarray, min_cos: float, depth_tol_mm: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The texels (indices into ``points``) a keyframe sees, their cos and colour."""
    d = camera_center(kf.R, kf.t) - points
    cos = np.einsum("ij,ij->i", normals, d) / np.sqrt(np.einsum("ij,ij->i", d, d))
    ids = np.flatnonzero(cos >= min_cos)
    uv, z = _project(points[ids], kf)
    w, h = kf.intrinsics.width, kf.intrinsics.height
    inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] <= w - 1) & \
             (uv[:, 1] <= h - 1)
    ids, uv, z = ids[inside], uv[inside], z[inside]
    # Depth-map pixel: the same camera scaled (pixel centres at integers).
    sx, sy = small.width / w, small.height / h
    col = np.clip(np.round((uv[:, 0] + 0.5) * sx - 0.5), 0, small.width - 1).astype(np.int64)
    row = np.clip(np.round((uv[:, 1] + 0.5) * sy - 0.5), 0, small.height - 1).astype(np.int64)
    # Over the 3×3 block the erosion looks at, the surface itself recedes by up to 1.5
    # pixels' footprint × tan(view angle): that much deeper is still the surface.
    c = cos[ids]
    footprint = z / small.fx
    tol = depth_tol_mm + 1.5 * footprint * np.sqrt(1.0 - c ** 2) / c
    vis = z <= depth[row, col] + tol
    ids, uv = ids[vis], uv[vis]
    return ids, cos[ids], _bilinear(kf.image, uv)


GAIN_STRIDE = 4
"""Every this-many-th texel is enough for the exposure gains' K × 3 numbers."""


def _gain_samples(sample: tuple, sharpness: float) -> tuple:
    """What :func:`_exposure_gains` needs of one view's samples of every
    :data:`GAIN_STRIDE`-th texel (its index over the stride, its blend score, its log
    colour); ``sample``: :func:`_view_samples` of those texels alone."""
    ids, cos, colour = sample
    return ids, cos * sharpness, np.log(colour + 1.0)


def _exposure_gains(picked: list, n_texels: int, rounds: int = 4,
                    stride: int = GAIN_STRIDE) -> np.ndarray:
    """Per-view, per-channel gains (K, 3) that make each view's colours agree with the
    blend of all views on the texels it shares with others, in the log domain (a gain is a
    shift there); their mean weighted by each view's share of the blend is 1, so the atlas
    keeps the keyframes' overall exposure. ``picked``: each view's :func:`_gain_samples`."""
    K = len(picked)
    if K < 2:
        return np.ones((K, 3))
    n = n_texels // stride + 1
    best = np.full(n, -np.inf)
    seen = np.zeros(n)
    for ids, s, _ in picked:
        best[ids] = np.maximum(best[ids], s)  # ids are unique within a view
        seen[ids] += 1
    weights = [np.exp((s - best[ids]) / BLEND_SOFTNESS) for ids, s, _ in picked]
    total = sum(np.bincount(ids, w, n) for (ids, _, _), w in zip(picked, weights))
    mass = np.array([w.sum() for w in weights])
    # All views' samples in view order: one bincount over them adds each texel's views in
    # the order the view-by-view sums did.
    all_ids = np.concatenate([ids for ids, _, _ in picked])
    all_weights = np.concatenate(weights)
    all_logc = np.concatenate([logc for _, _, logc in picked])
    view_of = np.repeat(np.arange(K), [len(ids) for ids, _, _ in picked])
    shared = [seen[ids] >= 2 for ids, _, _ in picked]
    shift = np.zeros((K, 3))
    for _ in range(rounds):
        ref = np.column_stack([
            np.bincount(all_ids, all_weights * (all_logc[:, ch] + shift[view_of, ch]), n)
            for ch in range(3)])
        ref /= np.maximum(total, 1e-12)[:, None]
        for k, (ids, _, logc) in enumerate(picked):
            if shared[k].sum() >= 50:
                shift[k] = np.median(ref[ids[shared[k]]] - logc[shared[k]], axis=0)
        shift -= (mass[:, None] * shift).sum(0) / max(mass.sum(), 1e-12)
        shift = np.clip(shift, *np.log(GAIN_RANGE))
    return np.exp(shift)


def push_pull(image: np.ndarray, known: np.ndarray) -> np.ndarray:
    """Fill the unknown pixels of ``image`` (H, W, C float) from the known ones: averaged
    down a pyramid, the holes filled from the coarser level on the way up."""
    if known.all() or not known.any():
        return image
    w = known.astype(np.float32)
    img = image.astype(np.float32) * w[..., None]
    levels = [(img, w)]
    while min(img.shape[:2]) > 1:
        img = cv2.resize(img, (max(1, img.shape[1] // 2), max(1, img.shape[0] // 2)),
                         interpolation=cv2.INTER_AREA)
        w = cv2.resize(w, (img.shape[1], img.shape[0]), interpolation=cv2.INTER_AREA)
        if img.ndim == 2:
            img = img[..., None]
        levels.append((img, w))
    filled = levels[-1][0] / np.maximum(levels[-1][1], 1e-12)[..., None]
    for img, w in reversed(levels[:-1]):
        up = cv2.resize(filled, (img.shape[1], img.shape[0]), interpolation=cv2.INTER_LINEAR)
        if up.ndim == 2:
            up = up[..., None]
        # ``img`` is premultiplied by its coverage: the coarser level fills what is missing.
        filled = img + (1.0 - np.clip(w, 0, 1))[..., None] * up
    out = image.astype(np.float32).copy()
    out[~known] = filled[~known]
    return out


@numba.njit(nogil=True, cache=True)
def _blend_view(ids, rescale, weight, colour, gain, acc, total):
    """One view's samples into the soft maximum's sums, in place: texel ``ids[j]``'s sums
    rescaled by ``rescale[j]``, then its colour times the view's ``gain`` added with
    ``weight[j]``. The ids are unique within a view; no fastmath: the float operations of
    the numpy expressions it replaces, in their order, without their gathered copies."""
    for j in range(len(ids)):
        i = ids[j]
        for c in range(3):
            acc[i, c] = acc[i, c] * rescale[j] + weight[j] * np.float64(colour[j, c]) * gain[c]
        total[i] = total[i] * rescale[j] + weight[j]


def bake_texture(vertices: np.ndarray, faces: np.ndarray, keyframes, layout: UVLayout,
                 size: int = ATLAS_SIZE, min_cos: float = 0.25, depth_tol_mm: float = 1.0,
                 fill_colours: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """The texture atlas, RGB uint8 (size, size, 3) with row 0 at v = 1 (as an image file
    is read), and what made it (views used, texels seen, gains). ``fill_colours``: per-vertex
    RGB for texels no view sees (else grey)."""
    v = np.asarray(vertices, float)
    f = np.asarray(faces, np.int64)
    texels = rasterise_uv(layout, size)
    corners = layout.vertex[layout.faces[texels.face]]  # (T, 3) mesh vertices
    points = np.einsum("tc,tck->tk", texels.bary, v[corners])
    normals = np.einsum("tc,tck->tk", texels.bary, vertex_normals(v, f)[corners])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    scene = RaycastScene()
    scene.add(v, f)
    sharp_rel = _relative_sharpness(keyframes)
    T = len(points)
    # Two passes over the views: the gains first, from a quarter of the texels, then the
    # blend, each view's samples made again from its kept depth map: all views' samples at
    # once held a gigabyte at 720p.
    depths, picked, rays = [], [], {}
    # Each texel's samples are its own: those of every GAIN_STRIDE-th texel alone are the
    # same figures, at a quarter of the work.
    gain_points = np.ascontiguousarray(points[::GAIN_STRIDE])
    gain_normals = np.ascontiguousarray(normals[::GAIN_STRIDE])
    for k, kf in enumerate(keyframes):
        depths.append(_depth_map(scene, kf, rays))
        picked.append(_gain_samples(_view_samples(kf, *depths[k], gain_points, gain_normals,
                                                  min_cos, depth_tol_mm), sharp_rel[k]))
    gains = _exposure_gains(picked, T)
    del picked
    # Soft maximum over the views, accumulated view by view (rescaled when the best rises).
    best = np.full(T, -np.inf)
    acc, total = np.zeros((T, 3)), np.zeros(T)
    for k, kf in enumerate(keyframes):
        ids, cos, colour = _view_samples(kf, *depths[k], points, normals, min_cos, depth_tol_mm)
        s = cos * sharp_rel[k]
        new_best = np.maximum(best[ids], s)
        rescale = np.exp(np.where(np.isfinite(best[ids]), (best[ids] - new_best), 0.0)
                         / BLEND_SOFTNESS)
        w = np.exp((s - new_best) / BLEND_SOFTNESS)
        _blend_view(ids, rescale, w, colour, np.ascontiguousarray(gains[k]), acc, total)
        best[ids] = new_best
    seen = total > 0
    colours = np.zeros((T, 3))
    colours[seen] = acc[seen] / total[seen, None]
    if fill_colours is not None:
        fill = np.asarray(fill_colours, float)[corners]
        colours[~seen] = np.einsum("tc,tck->tk", texels.bary[~seen], fill[~seen])
    else:
        colours[~seen] = 128.0
    atlas = np.zeros((size * size, 3), np.float32)
    atlas[texels.index] = colours
    known = np.zeros(size * size, bool)
    known[texels.index] = True
    atlas = push_pull(atlas.reshape(size, size, 3), known.reshape(size, size))
    info = {"size": size, "texels": int(T), "texels_seen": int(seen.sum()),
            "views": len(keyframes),
            "gains": np.round(gains, 3).tolist()}
    return np.clip(np.round(atlas), 0, 255).astype(np.uint8), info


# --- files ------------------------------------------------------------------------------

TEXTURE_PNG = "texture.png"
MESH_MTL = "mesh.mtl"
MESH_GLB = "mesh.glb"
MATERIAL = "skin"


def obj_text(vertices: np.ndarray, faces: np.ndarray, colours: np.ndarray | None,
             layout: UVLayout, mtl_name: str = MESH_MTL) -> str:
    """A Wavefront OBJ with the mesh's vertices in order (``v x y z [r g b]``, colours 0-1
    as trimesh writes them), the layout's ``vt`` and faces ``f v/vt``: the ``v`` lines keep
    the template's vertex order; the texture comes from ``mtl_name``."""
    v = np.asarray(vertices, float)
    if colours is not None:
        v = np.c_[v, np.asarray(colours, float)[:, :3] / 255.0]
    corners = np.stack([np.asarray(faces, np.int64), layout.faces], 2).reshape(-1, 6) + 1
    return "".join([f"# facecap fitted mesh (mm), template topology\nmtllib {mtl_name}\n",
                    _lines("v" + " %.8f" * v.shape[1], v), _lines("vt %.7f %.7f", layout.uv),
                    f"usemtl {MATERIAL}\n", _lines("f %d/%d %d/%d %d/%d", corners)])


def _lines(fmt: str, rows: np.ndarray) -> str:
    """``fmt % row`` and a newline for each row, as np.savetxt writes them: one format of
    all rows at once instead of one per row (several times faster, the same text)."""
    return ((fmt + "\n") * len(rows)) % tuple(rows.ravel().tolist())


def mtl_text(texture_name: str = TEXTURE_PNG) -> str:
    """The material of :func:`obj_text`: diffuse colour from the atlas, no specular."""
    return (f"newmtl {MATERIAL}\nKa 1.0 1.0 1.0\nKd 1.0 1.0 1.0\nKs 0.0 0.0 0.0\nd 1.0\n"
            f"illum 1\nmap_Kd {texture_name}\n")


def glb_bytes(vertices: np.ndarray, faces: np.ndarray, layout: UVLayout, atlas: np.ndarray
              ) -> bytes:
    """Binary glTF of the mesh split at the UV seams (the template's vertices first, in
    order, then the seam copies), its material's ``baseColorTexture`` the atlas (PNG). The
    normals are the unsplit mesh's, so shading stays smooth across the seams (a glTF without
    normals is shaded flat). The mesh's ``extras`` (three.js: ``userData``) say which vertex
    each copy is: ``template_vertices`` (N) and ``seam_vertex`` (the mesh vertex of each
    glTF vertex from N on), so per-vertex data of the mesh (a heat map) can be spread onto
    the glTF's vertices."""
    # Loaded only when a GLB is written: trimesh's exporters and PIL take a second to import.
    import trimesh
    from PIL import Image

    v = np.asarray(vertices, float)[layout.vertex]
    normals = vertex_normals(np.asarray(vertices, float), np.asarray(faces, np.int64))
    material = trimesh.visual.material.PBRMaterial(
        name=MATERIAL, baseColorTexture=Image.fromarray(atlas), metallicFactor=0.0,
        roughnessFactor=0.8, doubleSided=True)
    mesh = trimesh.Trimesh(v, layout.faces, process=False,
                           vertex_normals=normals[layout.vertex],
                           visual=trimesh.visual.TextureVisuals(uv=layout.uv, material=material))
    n = len(vertices)
    mesh.metadata.update(template_vertices=n, seam_vertex=layout.vertex[n:].tolist())
    return mesh.export(file_type="glb", include_normals=True)


def png_bytes(atlas: np.ndarray) -> bytes:
    ok, data = cv2.imencode(".png", cv2.cvtColor(atlas, cv2.COLOR_RGB2BGR))
    if not ok:
        raise RuntimeError("could not encode the texture atlas as PNG")
    return data.tobytes()


def sample_atlas(atlas: np.ndarray, layout: UVLayout, triangle: np.ndarray,
                 bary: np.ndarray) -> np.ndarray:
    """The atlas's colour (float RGB) at points of the mesh given as triangles and their
    barycentric weights (e.g. a ray cast's :class:`~facecap_core.render.Hits`), bilinear."""
    uv = np.einsum("...c,...ck->...k", bary, layout.uv[layout.faces[triangle]])
    size_y, size_x = atlas.shape[:2]
    px = np.c_[uv.reshape(-1, 2)[:, 0] * size_x - 0.5, (1.0 - uv.reshape(-1, 2)[:, 1]) * size_y - 0.5]
    return _bilinear(atlas, px).reshape(uv.shape[:-1] + (3,))
