"""The phone camera: intrinsics, rolling-shutter readout, ray casting through distorted
pixels, motion blur, and the lights."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
import trimesh

from facecap.synthetic.config import SynthConfig
from facecap.synthetic.scene import Room
from facecap.synthetic.subjects import Subject
from facecap_core.camera import (
    Intrinsics,
    distort,
    pixel_rays,
)
from facecap_core.render import (
    NO_HIT,
    Hits,
    RaycastScene,
    interpolate,
    shade_lambert,
    vertex_normals,
)


def turn_image(image: np.ndarray, rotation_deg: int) -> np.ndarray:
    """Turn an image counter-clockwise by ``rotation_deg`` (the display rotation's
    convention in :mod:`facecap_core.video`: stored frame turned by it = upright frame)."""
    return np.ascontiguousarray(np.rot90(image, k=(rotation_deg // 90) % 4))


@dataclass
class Readout:
    """A rolling shutter: when each pixel of the upright image is exposed."""

    lines: np.ndarray  # (H, W) int: the sensor line (stored row) each upright pixel lies on
    offsets: np.ndarray  # (L,) s from the frame's ground-truth time to each line's mid-exposure


def rolling_readout(config: SynthConfig) -> Readout | None:
    """The sensor reads its ``height`` stored rows top to bottom in ``rolling_shutter_s``;
    the frame's ground-truth time is the middle of that readout (``None``: global shutter)."""
    if config.rolling_shutter_s <= 0:
        return None
    rows = np.repeat(np.arange(config.height)[:, None], config.width, axis=1)
    offsets = config.rolling_shutter_s * ((np.arange(config.height) + 0.5) / config.height - 0.5)
    return Readout(turn_image(rows, config.display_rotation_deg), offsets)


def _world_to_lines(points: np.ndarray, R: np.ndarray, t: np.ndarray, line: np.ndarray,
                    chunk: int = 1 << 19) -> np.ndarray:
    """Camera coordinates of points (N, 3), each seen by the pose (R[l], t[l]) of its line."""
    out = np.empty_like(points, dtype=float)
    for s in range(0, len(points), chunk):
        ln = line[s:s + chunk]  # chunked: a (N, 3, 3) gather of 4K frames would be 600 MB
        out[s:s + chunk] = np.einsum("nij,nj->ni", R[ln], points[s:s + chunk]) + t[ln]
    return out


def project_lines(points: np.ndarray, R: np.ndarray, t: np.ndarray, line: np.ndarray,
                   intr: Intrinsics) -> np.ndarray:
    """As :func:`facecap_core.camera.project` (pixels only), one pose per line."""
    pc = _world_to_lines(points, R, t, line)
    z = pc[:, 2]
    xy = distort(pc[:, :2] / np.where(np.abs(z) > 1e-12, z, 1e-12)[:, None], intr.k1, intr.k2)
    return np.stack([intr.fx * xy[:, 0] + intr.cx, intr.fy * xy[:, 1] + intr.cy], axis=1)


def _cast_lines(scene: RaycastScene, rays_cam: np.ndarray, R: np.ndarray, t: np.ndarray,
                lines: np.ndarray) -> tuple[Hits, np.ndarray]:
    """:meth:`RaycastScene.cast_camera` with one pose per sensor line; also returns each
    pixel's camera centre (H*W, 3)."""
    h, w = lines.shape
    line = lines.ravel()
    centres = -np.einsum("lji,lj->li", R, t)  # -R^T t per line
    d_cam = rays_cam.reshape(-1, 3)
    d_world = np.empty_like(d_cam)
    for s in range(0, len(d_cam), 1 << 19):
        ln = line[s:s + (1 << 19)]
        d_world[s:s + (1 << 19)] = np.einsum("nji,nj->ni", R[ln], d_cam[s:s + (1 << 19)])
    centre = centres[line]
    ans = scene.cast(centre, d_world)
    depth = ans["t_hit"].astype(np.float32)
    gid = ans["geometry_ids"]
    hit = gid != NO_HIT
    mesh = np.full(gid.shape, -1, np.int32)
    for i, g in enumerate(scene._ids):  # the scene's meshes in the order they were added
        mesh[gid == g] = i
    tri = np.where(hit, ans["primitive_ids"].astype(np.int64), -1)
    uv = ans["primitive_uvs"]
    bary = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1).astype(np.float32)
    points = centre + d_world * np.where(hit, depth, np.nan)[:, None].astype(np.float64)
    return Hits(depth=np.where(hit, depth, np.inf).reshape(h, w), mesh=mesh.reshape(h, w),
                triangle=tri.reshape(h, w), bary=bary.reshape(h, w, 3),
                points=points.reshape(h, w, 3)), centre


# -- rendering ---------------------------------------------------------------------------------


@dataclass
class Renderer:
    """Everything needed to render frames of one capture."""

    subject: Subject
    room: Room | None
    intrinsics: Intrinsics
    lights: list[tuple[np.ndarray, float]]
    ambient: float
    specular: float

    def __post_init__(self):
        self.scene = RaycastScene()
        self.scene.add(self.subject.vertices, self.subject.faces)
        if self.room is not None:
            self.scene.add(self.room.vertices, self.room.faces)
        self.normals = vertex_normals(self.subject.vertices, self.subject.faces)
        if self.room is not None:
            self.room_normals = trimesh.Trimesh(self.room.vertices, self.room.faces,
                                                process=False).face_normals
        self.rays = pixel_rays(self.intrinsics)

    def _scene_with_head(self, R_head: np.ndarray, c_head: np.ndarray) -> RaycastScene:
        scene = RaycastScene()  # a BVH of the moved head: milliseconds, once per frame
        scene.add(self.subject.vertices @ R_head.T + c_head, self.subject.faces)
        if self.room is not None:
            scene.add(self.room.vertices, self.room.faces)
        return scene

    def render(self, R: np.ndarray, t: np.ndarray, lines: np.ndarray | None = None,
               head: tuple[np.ndarray, np.ndarray] | None = None):
        """Linear-RGB image (H, W, 3) and the ray-cast hits (room frame) of one pose, or with
        ``lines`` (H, W) of one pose per sensor line (R (L, 3, 3), t (L, 3): a rolling
        shutter). ``head``: the head's pose (R, c) in the room (sway); else it is at rest."""
        scene = self.scene if head is None else self._scene_with_head(*head)
        if lines is None:
            hits = scene.cast_camera(self.intrinsics, R, t, self.rays)
            centre = -R.T @ t
        else:
            hits, centre = _cast_lines(scene, self.rays, R, t, lines)
        h, w = hits.depth.shape
        img = np.zeros((h * w, 3))
        mesh = hits.mesh.ravel()
        tri = hits.triangle.ravel()
        bary = hits.bary.reshape(-1, 3)
        pts = hits.points.reshape(-1, 3)
        for mesh_id in (0, 1):
            sel = mesh == mesh_id
            if not sel.any():
                continue
            if mesh_id == 0:
                # Texture and normals live in the head frame: take the hits back into it.
                p_head = pts[sel] if head is None else (pts[sel] - head[1]) @ head[0]
                alb = self.subject.albedo(tri[sel], bary[sel], p_head)
                n = interpolate(self.normals, self.subject.faces, tri[sel], bary[sel])
                n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
                if head is not None:
                    n = n @ head[0].T
                spec = self.specular
                # Occlusion darkens eye sockets, nostrils and creases as in a real photo.
                alb = alb * interpolate(self.subject.occlusion[:, None], self.subject.faces,
                                        tri[sel], bary[sel]) ** 0.7
            else:
                alb = self.room.albedo(tri[sel], bary[sel], pts[sel])
                n = self.room_normals[tri[sel]]
                spec = 0.0
            view = (centre if lines is None else centre[sel]) - pts[sel]
            view /= np.linalg.norm(view, axis=1, keepdims=True)
            img[sel] = shade_lambert(alb, n, view, self.lights, self.ambient, spec)
        return img.reshape(h, w, 3), hits


def motion_blur(img: np.ndarray, points: np.ndarray, projections: list[Callable],
                 uv0: np.ndarray) -> np.ndarray:
    """Average the sharp image along each pixel's motion over the exposure; ``projections``
    map the pixels' world points (N, 3) to pixels (N, 2) at each sub-frame instant."""
    h, w = img.shape[:2]
    valid = np.isfinite(points[..., 0]).ravel()
    acc = np.zeros_like(img, dtype=np.float32)
    src = img.astype(np.float32)
    for proj in projections:
        uv = uv0.copy()
        uv[valid] = proj(points.reshape(-1, 3)[valid], valid)
        flow = (uv - uv0).reshape(h, w, 2)
        grid = uv0.reshape(h, w, 2) - flow
        acc += cv2.remap(src, grid[..., 0].astype(np.float32), grid[..., 1].astype(np.float32),
                         cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    return acc / len(projections)


def sensor_image(linear: np.ndarray, config: SynthConfig,
                 rng: np.random.Generator) -> np.ndarray:
    """What the phone stores for a rendered linear RGB image: lens blur, the colour filter
    array, Poisson–Gaussian noise per photosite, demosaicing, sRGB and sharpening (uint8)."""
    img = np.asarray(linear)  # its own dtype: the default path renders as it always has
    if config.defocus_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), config.defocus_px)
    if config.bayer:
        h, w = img.shape[:2]
        # RGGB: red at (even, even), green at (even, odd) and (odd, even), blue at (odd, odd).
        channel = np.ones((h, w), np.int64)
        channel[0::2, 0::2] = 0
        channel[1::2, 1::2] = 2
        raw = np.take_along_axis(img, channel[..., None], axis=2)[..., 0]
        sigma = np.sqrt(config.read_noise ** 2 + config.shot_noise ** 2 * np.clip(raw, 0, 1))
        raw = raw + sigma * rng.standard_normal(raw.shape)
        raw16 = np.round(np.clip(raw, 0, 1) * 65535).astype(np.uint16)
        # OpenCV names the pattern by the second row's first two pixels: RGGB is "BayerBG".
        img = cv2.demosaicing(raw16, cv2.COLOR_BayerBG2RGB_EA).astype(np.float64) / 65535
    else:
        sigma = np.sqrt(config.read_noise ** 2 + config.shot_noise ** 2 * np.clip(img, 0, 1))
        img = img + sigma * rng.standard_normal(img.shape)
    srgb = to_srgb8(img)
    if config.sharpen > 0:
        soft = cv2.GaussianBlur(srgb, (0, 0), 1.0).astype(np.float64)
        srgb = np.clip(np.round(srgb + config.sharpen * (srgb - soft)), 0, 255).astype(np.uint8)
    return srgb


def to_srgb8(linear: np.ndarray) -> np.ndarray:
    x = np.clip(linear, 0.0, 1.0)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.round(srgb * 255).astype(np.uint8)


def draw_intrinsics(config: SynthConfig, rng: np.random.Generator) -> Intrinsics:
    w, h = config.width, config.height
    f = (w / 2) / np.tan(np.radians(config.hfov_deg) / 2) * (1 + config.focal_jitter * rng.normal())
    cx = (w - 1) / 2 + config.principal_point_jitter * w * rng.normal()
    cy = (h - 1) / 2 + config.principal_point_jitter * h * rng.normal()
    k1 = rng.uniform(*config.k1_range)
    return Intrinsics(w, h, float(f), float(f), float(cx), float(cy), float(k1), float(-0.25 * k1))


def draw_lights(rng: np.random.Generator) -> list[tuple[np.ndarray, float]]:
    def direction(az, el):
        a, e = np.radians(az), np.radians(el)
        return np.array([np.sin(a) * np.cos(e), np.sin(e), np.cos(a) * np.cos(e)])

    key_az = rng.uniform(-50, 50)
    return [(direction(key_az, rng.uniform(20, 45)), rng.uniform(0.55, 0.75)),
            (direction(-key_az - np.sign(key_az) * rng.uniform(30, 60), rng.uniform(0, 20)),
             rng.uniform(0.15, 0.3))]
