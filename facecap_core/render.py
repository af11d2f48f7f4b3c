"""Ray casting of triangle meshes through a (distorted) camera, with open3d's BVH.

One :class:`RaycastScene` holds several meshes; :meth:`RaycastScene.cast_camera` returns, per
pixel, the depth, the mesh hit, the triangle and its barycentric coordinates. From these the
synthetic renderer shades pixels, the evaluation paints heat maps, and later stages get
visibility and ground-truth depth. Everything is in the world frame the meshes are given in.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from facecap_core.camera import Intrinsics, camera_center, pixel_rays, project
from facecap_core.lazy import LazyModule

o3d = LazyModule("open3d")

NO_HIT = np.uint32(2**32 - 1)
"""open3d's ``RaycastingScene.INVALID_ID``: the triangle id of a ray that hits nothing."""


@dataclass
class Hits:
    """Per-pixel ray-cast result, arrays shaped like the image (H, W[, k])."""

    depth: np.ndarray  # float32, camera z (inf where nothing is hit)
    mesh: np.ndarray  # int32 index of the mesh hit, -1 for none
    triangle: np.ndarray  # int64 triangle index within that mesh, -1 for none
    bary: np.ndarray  # float32 (H, W, 3) barycentric weights of the triangle's corners
    points: np.ndarray  # float64 (H, W, 3) world position of the hit

    @property
    def valid(self) -> np.ndarray:
        return self.mesh >= 0


class RaycastScene:
    """A set of triangle meshes to cast rays against."""

    def __init__(self):
        self._scene = o3d.t.geometry.RaycastingScene()
        self._ids: list[int] = []

    def add(self, vertices: np.ndarray, faces: np.ndarray) -> int:
        """Add a mesh; returns its index in :attr:`Hits.mesh`."""
        gid = self._scene.add_triangles(
            o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32)),
            o3d.core.Tensor(np.ascontiguousarray(faces, dtype=np.uint32)),
        )
        self._ids.append(int(gid))
        return len(self._ids) - 1

    def cast(self, origins: np.ndarray, directions: np.ndarray) -> dict:
        """Cast rays (N, 3) + (N, 3); ``t_hit`` is in units of the direction's length."""
        rays = np.concatenate([origins, directions], axis=-1).astype(np.float32)
        ans = self._scene.cast_rays(o3d.core.Tensor(np.ascontiguousarray(rays)))
        return {k: v.numpy() for k, v in ans.items()}

    def cast_camera(self, intr: Intrinsics, R: np.ndarray, t: np.ndarray,
                    rays_cam: np.ndarray | None = None,
                    box: tuple[int, int, int, int] | None = None) -> Hits:
        """Cast one ray through every pixel of a (distorted) camera with pose (R, t); with
        ``box`` = (u0, u1, v0, v1), only through the pixels u0 <= u < u1, v0 <= v < v1
        (the rest hit nothing)."""
        if rays_cam is None:
            rays_cam = pixel_rays(intr)
        h, w = rays_cam.shape[:2]
        u0, u1, v0, v1 = box if box is not None else (0, w, 0, h)
        inner = rays_cam[v0:v1, u0:u1]
        bh, bw = inner.shape[:2]
        d_cam = inner.reshape(-1, 3)
        d_world = d_cam @ np.asarray(R)  # R.T @ d for each row
        centre = -np.asarray(R).T @ np.asarray(t).reshape(3)
        ans = self.cast(np.broadcast_to(centre, d_world.shape), d_world)
        depth = ans["t_hit"].astype(np.float32)
        gid = ans["geometry_ids"]
        hit = gid != NO_HIT
        lookup = {g: i for i, g in enumerate(self._ids)}
        mesh = np.full(gid.shape, -1, np.int32)
        for g, i in lookup.items():
            mesh[gid == g] = i
        tri = np.where(hit, ans["primitive_ids"].astype(np.int64), -1)
        uv = ans["primitive_uvs"]
        bary = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1).astype(np.float32)
        # Positions from depth along the z=1 rays keep float64 precision for the hit point.
        points = centre + d_world * np.where(hit, depth, np.nan)[:, None].astype(np.float64)
        inner_hits = (np.where(hit, depth, np.inf).reshape(bh, bw), mesh.reshape(bh, bw),
                      tri.reshape(bh, bw), bary.reshape(bh, bw, 3), points.reshape(bh, bw, 3))
        if (bh, bw) == (h, w):
            return Hits(*inner_hits)
        full = Hits(depth=np.full((h, w), np.inf, np.float32), mesh=np.full((h, w), -1, np.int32),
                    triangle=np.full((h, w), -1, np.int64),
                    bary=np.tile(np.array([1, 0, 0], np.float32), (h, w, 1)),
                    points=np.full((h, w, 3), np.nan))
        for whole, part in zip((full.depth, full.mesh, full.triangle, full.bary, full.points),
                               inner_hits, strict=True):
            whole[v0:v1, u0:u1] = part
        return full


def projected_box(intr: Intrinsics, R: np.ndarray, t: np.ndarray, vertices: np.ndarray
                  ) -> tuple[int, int, int, int] | None:
    """The pixels (u0, u1, v0, v1) a mesh with these vertices can cover in a pinhole camera:
    a triangle in front of the camera projects onto the triangle of its corners' projections,
    so every pixel whose ray hits the mesh lies in their bounding box. None where a vertex is
    not in front of the camera or the camera has distortion (no such bound then)."""
    if intr.k1 or intr.k2:
        return None
    uv, z = project(vertices, R, t, intr)
    if len(z) == 0 or not np.all(z > 0):
        return None
    u, v = uv[:, 0], uv[:, 1]
    # A pixel centre at integer (u, v); one pixel of slack for the rounding of the cast.
    u0, v0 = int(np.floor(u.min())) - 1, int(np.floor(v.min())) - 1
    u1, v1 = int(np.ceil(u.max())) + 2, int(np.ceil(v.max())) + 2
    u0, u1 = min(max(u0, 0), intr.width), min(max(u1, 0), intr.width)
    v0, v1 = min(max(v0, 0), intr.height), min(max(v1, 0), intr.height)
    return u0, u1, v0, v1


def interpolate(values: np.ndarray, faces: np.ndarray, triangle: np.ndarray,
                bary: np.ndarray) -> np.ndarray:
    """Interpolate per-vertex values (V, ...) at hits (triangle ids + barycentrics)."""
    corners = values[faces[triangle]]  # (..., 3, k)
    return np.einsum("...c,...ck->...k", bary, corners.reshape(corners.shape[:-1] + (-1,)))


def visible_vertices(scene: RaycastScene, vertices: np.ndarray, normals: np.ndarray, R, t,
                     intr: Intrinsics, min_cos: float, tol_mm: float, margin_px: float = 0.0
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The vertices a camera (world-to-camera ``R``, ``t``) sees: facing it at
    ``cos >= min_cos``, projecting at least ``margin_px`` inside the image, and not occluded
    (a ray from the camera centre reaches within ``tol_mm`` of them in ``scene``). Their
    indices, cos, pixels and camera depths."""
    c = camera_center(R, t)
    d = c - vertices
    dist = np.linalg.norm(d, axis=1)
    d /= dist[:, None]
    cos = np.einsum("ij,ij->i", normals, d)
    ids = np.flatnonzero(cos >= min_cos)
    uv, z = project(vertices[ids], R, t, intr)
    inside = (z > 0) & (uv >= margin_px).all(axis=1) & \
        (uv[:, 0] <= intr.width - 1 - margin_px) & (uv[:, 1] <= intr.height - 1 - margin_px)
    ids, uv, z = ids[inside], uv[inside], z[inside]
    if len(ids):
        hit = scene.cast(np.broadcast_to(c, (len(ids), 3)), -d[ids])["t_hit"]
        seen = hit >= dist[ids] - tol_mm
        ids, uv, z = ids[seen], uv[seen], z[seen]
    return ids, cos[ids], uv, z


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals."""
    fn = np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]],
                  vertices[faces[:, 2]] - vertices[faces[:, 0]])
    # Each vertex's faces summed by one bincount over the corners (all first corners, then
    # all second, then all third): the order of the three np.add.at calls it replaces. The
    # normals keep the vertices' memory layout (a fit's are column-major), as the callers'
    # sums over them have.
    corners = np.asarray(faces).T.ravel()
    vn = np.zeros_like(vertices, dtype=float)
    for c in range(3):
        vn[:, c] = np.bincount(corners, np.tile(fn[:, c], 3), len(vertices))
    return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-12)


def shade_lambert(albedo: np.ndarray, normals: np.ndarray, view_dirs: np.ndarray,
                  lights: list[tuple[np.ndarray, float]], ambient: float,
                  specular: float = 0.0, shininess: float = 30.0) -> np.ndarray:
    """Lambert + Blinn–Phong shading; ``view_dirs`` point from the surface to the camera.

    ``lights`` are (unit direction towards the light, intensity) pairs in the world frame.
    """
    n = normals
    # Normals may face away from the camera on open meshes; light the visible side.
    n = np.where((np.sum(n * view_dirs, -1, keepdims=True) < 0), -n, n)
    diffuse = np.full(n.shape[:-1] + (1,), ambient)
    spec = np.zeros_like(diffuse)
    for direction, intensity in lights:
        ndl = np.clip(np.sum(n * direction, -1, keepdims=True), 0.0, None)
        diffuse = diffuse + intensity * ndl
        if specular > 0:
            h = direction + view_dirs
            h /= np.maximum(np.linalg.norm(h, axis=-1, keepdims=True), 1e-12)
            highlight = np.clip(np.sum(n * h, -1, keepdims=True), 0, None) ** shininess
            spec = spec + intensity * specular * highlight * (ndl > 0)
    return albedo * diffuse + spec
