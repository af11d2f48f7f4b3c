"""Synthetic handheld captures of a textured head, with exact ground truth.

A capture is an ear-to-ear sweep: the camera moves on an arc from one profile to the other
at 35–50 cm, looking at the head, with slow drifts (distance, elevation, roll) and fast hand
tremor. The camera is a phone-like pinhole with an unknown focal length (~65° horizontal
field of view), a jittered principal point and radial distortion. Each frame is ray cast
(open3d) through the distorted pixel grid — no resampling — shaded (Lambert + a little
specular) under fixed world lights, blurred by the camera's motion during the exposure,
scaled by a drifting auto-exposure gain, given Poisson–Gaussian sensor noise, and encoded as
H.264. A static textured room surrounds the subject so there is a background to track.

What phones do and a plain render does not, each a :class:`SynthConfig` field that is off by
default: portrait frames stored landscape with a display rotation
(``display_rotation_deg``), a rolling shutter whose every sensor line is ray cast and
blurred at its own camera pose (``rolling_shutter_s``), HEVC (``codec``), a head that sways
rigidly before the still room (``sway_mm``, ``sway_deg``), untextured walls
(``plain_walls``) and smoother skin (``skin_detail``). 4K and 120 fps are ``width``,
``height`` and ``fps``.

World frame: the subject's head frame (mm) from its landmarks (see
:func:`facecap_core.template.head_frame`): +x the subject's left, +y up, +z out of the face,
origin between the tops of the jaw contour.

Output folder::

    video.mp4            the capture (H.264 or HEVC, yuv420p, display rotation if any)
    gt/mesh.ply          the visible head surface in mm (world frame): the "scan"
    gt/landmarks.json    68 3D landmarks (iBUG order, mm)
    gt/cameras.json      intrinsics + distortion (of the upright image), and per frame:
                         time, world-to-camera R, t (OpenCV convention, at mid-exposure of
                         the sensor's middle line), exposure gain; with sway the world is
                         the head frame and head_R, head_t give the head's pose in the room
    gt/subject.json      what the subject is (ICT coefficients, texture, ...)
    gt/config.yaml       the exact SynthConfig used
    gt/render.json       every drawn quantity (focal, distortion, lights, ...)
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path

import cv2
import numpy as np
import trimesh
from scipy import ndimage

from facecap_core.camera import (
    Intrinsics,
    distort,
    look_at,
    pixel_rays,
    project,
    rotation_matrix,
)
from facecap_core.config import SynthConfig, dump_yaml
from facecap_core.errors import InputError
from facecap_core.meshio import load_landmarks, load_mesh, save_landmarks
from facecap_core.render import (
    NO_HIT,
    Hits,
    RaycastScene,
    interpolate,
    shade_lambert,
    vertex_normals,
)
from facecap_core.template import (
    ICT_EYE_MATERIALS,
    head_frame,
    ict_faces_of,
    ict_identity_vertices,
    ict_skin_faces,
    load_ict_model,
)

AlbedoFn = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]


# -- procedural texture --------------------------------------------------------------------


class SolidNoise:
    """Band-limited 3D value noise from a periodic random grid (unit std, zero mean)."""

    def __init__(self, rng: np.random.Generator, size: int = 48, smooth: float = 1.2):
        grid = ndimage.gaussian_filter(rng.standard_normal((size, size, size)), smooth,
                                       mode="wrap")
        self.grid = ((grid - grid.mean()) / grid.std()).astype(np.float32)
        self.rotations = [rotation_matrix(rng.normal(size=3), rng.uniform(0, np.pi))
                          for _ in range(8)]
        self.offsets = rng.uniform(0, size, size=(8, 3))

    def __call__(self, points: np.ndarray, cell_mm: float, octave: int = 0,
                 stretch: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> np.ndarray:
        """Noise at points (N, 3) with features of about ``cell_mm``; each octave index
        samples the grid in its own rotated frame so octaves are independent."""
        p = points @ self.rotations[octave % 8].T
        p = p / (cell_mm * np.asarray(stretch)) + self.offsets[octave % 8]
        return ndimage.map_coordinates(self.grid, p.T, order=1, mode="grid-wrap")


def _smoothstep(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
    t = np.clip((x - lo) / (hi - lo), 0.0, 1.0)
    return t * t * (3 - 2 * t)


@dataclass
class FrontMask:
    """A soft 2D mask in the head frame's (x, y) plane, applied to front-facing points."""

    image: np.ndarray  # float32, rows = y (top = max y)
    x0: float
    y1: float
    mm_per_px: float
    z_min: float

    def __call__(self, p_head: np.ndarray) -> np.ndarray:
        col = (p_head[:, 0] - self.x0) / self.mm_per_px
        row = (self.y1 - p_head[:, 1]) / self.mm_per_px
        val = ndimage.map_coordinates(self.image, [row, col], order=1, mode="constant")
        return val * (p_head[:, 2] > self.z_min)


def _front_mask(polylines: list[np.ndarray], closed: bool, thickness_mm: float,
                blur_mm: float, z_min: float, mm_per_px: float = 0.25) -> FrontMask:
    pts = np.concatenate(polylines)
    x0, x1 = pts[:, 0].min() - 20, pts[:, 0].max() + 20
    y0, y1 = pts[:, 1].min() - 20, pts[:, 1].max() + 20
    w, h = int((x1 - x0) / mm_per_px), int((y1 - y0) / mm_per_px)
    img = np.zeros((h, w), np.float32)
    for line in polylines:
        px = np.stack([(line[:, 0] - x0) / mm_per_px, (y1 - line[:, 1]) / mm_per_px], 1)
        px = np.round(px * 16).astype(np.int32)  # 4 fractional bits
        if closed:
            cv2.fillPoly(img, [px], 1.0, lineType=cv2.LINE_AA, shift=4)
        else:
            cv2.polylines(img, [px], False, 1.0, max(1, int(thickness_mm / mm_per_px)),
                          lineType=cv2.LINE_AA, shift=4)
    img = cv2.GaussianBlur(img, (0, 0), blur_mm / mm_per_px)
    return FrontMask(img / max(img.max(), 1e-6), x0, y1, mm_per_px, z_min)


SKIN_TONES = np.array([  # linear RGB albedo
    [0.62, 0.42, 0.32], [0.55, 0.36, 0.26], [0.45, 0.28, 0.19], [0.33, 0.20, 0.13],
    [0.68, 0.50, 0.40], [0.50, 0.33, 0.22], [0.24, 0.14, 0.09],
])
IRIS_COLOURS = np.array([[0.20, 0.11, 0.05], [0.10, 0.18, 0.30], [0.14, 0.20, 0.10],
                         [0.30, 0.20, 0.08]])
IRIS_DIAMETER_MM = (11.7, 0.5)
"""Mean and 1σ of an adult's horizontal visible iris diameter; each ICT subject draws its own."""
PUPIL_RADIUS_MM = 1.9
HAIR_COLOURS = np.array([[0.05, 0.035, 0.025], [0.12, 0.07, 0.035], [0.25, 0.16, 0.08],
                         [0.02, 0.02, 0.02]])


class SkinAlbedo:
    """Procedural skin for a head in its head frame: tone, blotches, mottling, pores,
    freckles, lips, brows and short hair — texture at 0.5–25 mm for stereo matching."""

    def __init__(self, landmarks: np.ndarray, rng: np.random.Generator,
                 hair_weight: np.ndarray | None = None, detail: float = 1.0):
        self.noise = SolidNoise(rng)
        self.detail = detail  # weight of the fine (<= 1.6 mm) texture, see SynthConfig
        self.tone = SKIN_TONES[rng.integers(len(SKIN_TONES))] * rng.uniform(0.9, 1.1, 3)
        self.hair = HAIR_COLOURS[rng.integers(len(HAIR_COLOURS))]
        self.lip = self.tone * np.array([1.05, 0.62, 0.62])
        self.freckle_level = rng.uniform(1.6, 2.4)
        L = landmarks
        nose_z = L[30, 2]
        self.lips = _front_mask([L[48:60]], True, 0, 0.8, nose_z - 45)
        # The 68-point brow landmarks trace the brow's upper edge: the hair lies below them.
        down = np.array([0.0, -3.5, 0.0])
        self.brows = _front_mask([L[17:22] + down, L[22:27] + down], False, 7.0, 1.2,
                                 nose_z - 60)
        self.lashes = _front_mask([L[36:40], L[42:46]], False, 1.4, 0.5, nose_z - 45)
        self.hair_weight = hair_weight

    def __call__(self, points: np.ndarray, hair: np.ndarray | None = None) -> np.ndarray:
        n = self.noise
        d = self.detail
        lum = (1 + 0.07 * n(points, 4.0, 1) + d * 0.05 * n(points, 1.2, 2)
               + d * 0.03 * n(points, 0.5, 3))
        red = 0.06 * n(points, 25.0, 0)
        rgb = self.tone[None, :] * lum[:, None]
        rgb[:, 0] *= 1 + red
        rgb[:, 1] *= 1 - 0.5 * red
        freckles = _smoothstep(n(points, 1.6, 4), self.freckle_level, self.freckle_level + 0.6)
        rgb *= (1 - d * 0.35 * freckles[:, None] * np.array([0.8, 1.0, 1.1]))
        lips = self.lips(points)[:, None]
        rgb = rgb * (1 - lips) + self.lip * (1 + 0.08 * n(points, 0.8, 5))[:, None] * lips
        strands = _smoothstep(n(points, 0.6, 6, stretch=(6.0, 1.0, 1.0)), -0.3, 0.6)
        brows = (self.brows(points) * (0.45 + 0.55 * strands))[:, None]
        rgb = rgb * (1 - 0.9 * brows) + self.hair * 0.9 * brows
        lashes = 0.85 * self.lashes(points)[:, None]
        rgb = rgb * (1 - lashes) + 0.02 * lashes
        if hair is not None:
            h = hair[:, None] * (0.75 + 0.25 * strands[:, None])
            rgb = rgb * (1 - h) + self.hair * (1 + 0.5 * n(points, 0.7, 7))[:, None] * h
        return np.clip(rgb, 0.0, 1.0)


# -- subjects ---------------------------------------------------------------------------------


@dataclass
class Subject:
    """A head to render: geometry in the head frame (mm), albedo and ground truth."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    landmarks: np.ndarray
    albedo: AlbedoFn  # (triangle ids, barycentrics, points) -> linear RGB
    gt_faces: np.ndarray  # bool per face: part of the ground-truth surface (skin)
    optional_faces: np.ndarray  # bool per face: in the GT only where seen (eyeballs)
    info: dict = field(default_factory=dict)
    occlusion: np.ndarray | None = None  # per-vertex open fraction (ambient occlusion)

    def __post_init__(self):
        if self.occlusion is None:
            self.occlusion = ambient_occlusion(self.vertices, self.faces)


def ambient_occlusion(vertices: np.ndarray, faces: np.ndarray, rays: int = 48,
                      reach_mm: float = 60.0, seed: int = 0) -> np.ndarray:
    """Per-vertex fraction of the hemisphere that is open within ``reach_mm`` (1 = open)."""
    normals = vertex_normals(vertices, faces)
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(rays, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    scene = RaycastScene()
    scene.add(vertices, faces)
    open_fraction = np.zeros(len(vertices))
    for k in range(rays):
        dirs = np.where((normals @ d[k] < 0)[:, None], -d[k], d[k]) * np.ones_like(normals)
        hit = scene.cast(vertices + 0.05 * normals, dirs)["t_hit"]
        open_fraction += hit > reach_mm
    return open_fraction / rays


def _to_head_frame(vertices: np.ndarray, landmarks: np.ndarray):
    R, origin = head_frame(landmarks)
    return (vertices - origin) @ R.T, (landmarks - origin) @ R.T


def ict_subject(model_path: str | Path, seed: int | None, sigma: float = 1.0,
                skin_detail: float = 1.0) -> Subject:
    """A random ICT Face Model identity (``seed=None``: the mean face) with procedural skin
    (``skin_detail``: weight of its fine texture, see :attr:`SynthConfig.skin_detail`)."""
    model = load_ict_model(model_path)
    rng = np.random.default_rng(None if seed is None else [seed, 1])
    coeffs = None if seed is None else rng.standard_normal(100) * sigma
    verts = ict_identity_vertices(model, coeffs)
    lm = verts[model["landmarks68"]]
    verts, lm = _to_head_frame(verts, lm)
    skin = ict_skin_faces(model)
    eyes = ict_faces_of(model, ICT_EYE_MATERIALS)
    sockets = ict_faces_of(model, ("M_BackHead",))
    sockets = sockets[~np.all(sockets < 11248, axis=1)]
    faces = np.concatenate([skin, eyes, sockets])
    kind = np.concatenate([np.zeros(len(skin), int), np.ones(len(eyes), int),
                           np.full(len(sockets), 2)])
    # Hair: scalp above a hairline that falls from the forehead to the nape.
    w = np.abs(lm[[0, 16], 0]).mean()
    hairline = np.interp(verts[:, 2], [-1.4 * w, -0.6 * w, 0.3 * w, 2 * w],
                         [-0.45 * w, 0.62 * w, lm[27, 1] + 0.95 * w, lm[27, 1] + 0.95 * w])
    lateral_ok = ~((np.abs(verts[:, 0]) > 0.85 * w) & (verts[:, 1] < 0.75 * w)
                   & (verts[:, 2] > -0.7 * w))  # keep the temples and ears bare
    hair_v = _smoothstep(verts[:, 1] - hairline, -4.0, 6.0) * lateral_ok
    skin_albedo = SkinAlbedo(lm, rng, detail=skin_detail)
    iris_rgb = IRIS_COLOURS[rng.integers(len(IRIS_COLOURS))]
    # Own stream: the other draws (and so existing renders' skin and hair) stay as they were.
    iris_radius = 0.5 * (IRIS_DIAMETER_MM[0] if seed is None else
                         np.random.default_rng([seed, 3]).normal(*IRIS_DIAMETER_MM))
    # The eyes look straight ahead (+z of the head frame, parallel: a far gaze, as an
    # optician's distance PD). The ICT eyeball's iris and sclera materials both wrap the whole
    # ball, so the iris is painted: a disk of ``iris_radius`` around the gaze axis through the
    # eyeball's centre, its pupil where the axis leaves the eye.
    axis = np.array([0.0, 0.0, 1.0])
    eye_centres, pupils = {}, {}
    for side in ("Left", "Right"):
        ball = verts[np.unique(ict_faces_of(model, (f"M_Sclera{side}", f"M_Iris{side}")))]
        centre = ball.mean(0)
        d = ball - centre
        on_axis = np.linalg.norm(d - (d @ axis)[:, None] * axis, axis=1) < 1.5
        eye_centres[side] = centre
        pupils[side.lower()] = centre + axis * float((d[on_axis] @ axis).max())
    n_skin = len(skin)

    def albedo(tri: np.ndarray, bary: np.ndarray, points: np.ndarray) -> np.ndarray:
        out = np.empty((len(tri), 3))
        k = kind[tri]
        s = k == 0
        if s.any():
            hair = np.einsum("nc,nc->n", bary[s], hair_v[faces[tri[s]]])
            out[s] = skin_albedo(points[s], hair)
        e = k == 1
        if e.any():
            p = points[e]
            rgb = np.tile([0.80, 0.76, 0.72], (len(p), 1)) * (
                1 + 0.05 * skin_albedo.noise(p, 0.5, 3))[:, None]
            for centre in eye_centres.values():
                d = p - centre
                r = np.linalg.norm(d - (d @ axis)[:, None] * axis, axis=1)
                ahead = (d @ axis > 0) & (np.linalg.norm(d, axis=1) < 16)
                ring = 1 + 0.25 * skin_albedo.noise(p, 0.4, 5)
                col = np.where((r < PUPIL_RADIUS_MM)[:, None], 0.02, iris_rgb * ring[:, None])
                sel = ahead & (r < iris_radius)
                rgb[sel] = col[sel]
            out[e] = rgb
        o = k == 2
        out[o] = [0.12, 0.04, 0.04]
        return out

    gt = np.zeros(len(faces), bool)
    gt[:n_skin] = True
    optional = kind == 1
    info = {"kind": "ict", "seed": seed, "sigma": sigma,
            "identity_modes": int(len(model["identity_basis"])),
            "coefficients": None if coeffs is None else coeffs.round(6).tolist(),
            "skin_tone": skin_albedo.tone.round(4).tolist(),
            "iris_diameter_mm": round(2 * iris_radius, 4),
            "pupils_mm": {k: v.round(4).tolist() for k, v in pupils.items()}}
    return Subject(f"ict-{'mean' if seed is None else seed}", verts, faces, lm, albedo, gt,
                   optional, info)


def textured_subject(mesh_path: str | Path, landmarks_path: str | Path, scale: float = 1.0,
                     name: str | None = None) -> Subject:
    """A textured mesh (OBJ + image, or per-vertex colours) with 68 3D landmarks."""
    mesh = load_mesh(mesh_path, what="subject mesh", keep_vertex_order=False)
    lm = load_landmarks(landmarks_path) * scale
    if lm.shape[1] != 3:
        raise InputError(f"subject landmarks {landmarks_path} must be 3D points")
    verts, lm = _to_head_frame(np.asarray(mesh.vertices, float) * scale, lm)
    faces = np.asarray(mesh.faces, np.int64)
    visual = mesh.visual
    image = getattr(getattr(visual, "material", None), "image", None)
    uv = getattr(visual, "uv", None)
    if image is not None and uv is not None:
        tex = np.asarray(image.convert("RGB"), np.float32) / 255.0
        tex = tex ** 2.2  # sRGB texture to linear albedo
        th, tw = tex.shape[:2]

        def albedo(tri, bary, points):
            st = interpolate(np.asarray(uv, float), faces, tri, bary)
            mx = (st[:, 0] % 1.0) * (tw - 1)
            my = (1.0 - st[:, 1] % 1.0) * (th - 1)
            return np.stack([ndimage.map_coordinates(tex[..., c], [my, mx], order=1,
                                                     mode="nearest") for c in range(3)], 1)
    else:
        colours = getattr(visual, "vertex_colors", None)
        if colours is None or len(colours) != len(verts):
            raise InputError(f"subject mesh {mesh_path} has no texture image or vertex colours")
        lin = (np.asarray(colours, float)[:, :3] / 255.0) ** 2.2

        def albedo(tri, bary, points):
            return interpolate(lin, faces, tri, bary)

    gt = np.ones(len(faces), bool)
    return Subject(name or Path(mesh_path).stem, verts, faces, lm, albedo, gt,
                   np.zeros(len(faces), bool), {"kind": "mesh", "path": str(mesh_path)})


def make_subject(config: SynthConfig) -> Subject:
    """The subject a config names (see :attr:`SynthConfig.subject`)."""
    spec = config.subject
    if spec.startswith("ict:"):
        from facecap_core.assets import default_ict_model

        # --ict-model, else $FACECAP_ICT_MODEL, else the trimmed model in the package.
        model = config.ict_model or default_ict_model()
        arg = spec[4:]
        if arg != "mean" and not arg.lstrip("-").isdigit():
            raise InputError(f"subject {spec!r}: expected ict:SEED (an integer) or ict:mean")
        return ict_subject(model, None if arg == "mean" else int(arg), config.ict_identity_sigma,
                           config.skin_detail)
    if config.skin_detail != 1.0:
        raise InputError(f"skin_detail {config.skin_detail}: only the procedural skin of ict: "
                         "subjects can be smoothed; leave it at 1 for a textured mesh")
    if spec == "james":
        from facecap_core.assets import james_files

        mesh, lms = james_files()
        return textured_subject(mesh, lms, name="james")
    if config.subject_landmarks is None:
        raise InputError(f"subject mesh {spec}: pass its 68 3D landmarks with "
                         "--subject-landmarks FILE")
    return textured_subject(spec, config.subject_landmarks, config.subject_scale)


# -- the room ---------------------------------------------------------------------------------


def _wall_texture(rng: np.random.Generator, size: int = 1024, plain: bool = False) -> np.ndarray:
    """A wall: paint with large and fine noise, and posters, shelves and frames on it;
    ``plain``: its paint colour alone (a 2×2 texture), drawn from the same random stream."""
    base = rng.uniform(0.25, 0.75, 3)
    low = cv2.resize(rng.standard_normal((8, 8)).astype(np.float32), (size, size),
                     interpolation=cv2.INTER_CUBIC)
    fine = cv2.GaussianBlur(rng.standard_normal((size, size)).astype(np.float32), (0, 0), 1.5)
    img = base[None, None, :] * (1 + 0.08 * low + 0.25 * fine)[..., None]
    for _ in range(rng.integers(6, 12)):
        w, h = rng.integers(size // 12, size // 3, 2)
        x, y = rng.integers(0, size - w), rng.integers(0, size - h)
        kind = rng.integers(4)
        patch = np.empty((h, w, 3), np.float32)
        if kind == 0:  # stripes
            period = rng.integers(6, 40)
            s = (np.arange(w) // period % 2).astype(np.float32)
            patch[:] = (rng.uniform(0, 1, 3) * s[:, None] + rng.uniform(0, 1, 3) * (1 - s)[:, None])
        elif kind == 1:  # checkerboard
            c = rng.integers(8, 48)
            yy, xx = np.mgrid[:h, :w]
            s = ((yy // c + xx // c) % 2).astype(np.float32)[..., None]
            patch[:] = rng.uniform(0, 1, 3) * s + rng.uniform(0, 1, 3) * (1 - s)
        elif kind == 2:  # blotchy picture
            blot = cv2.resize(rng.uniform(0, 1, (6, 6, 3)).astype(np.float32), (w, h),
                              interpolation=cv2.INTER_CUBIC)
            patch[:] = np.clip(blot, 0, 1)
        else:  # text-like marks
            patch[:] = rng.uniform(0.7, 1.0, 3)
            for _ in range(int(w * h / 400)):
                cx, cy = rng.integers(0, w), rng.integers(0, h)
                cv2.rectangle(patch, (int(cx), int(cy)), (int(cx + rng.integers(3, 15)), int(cy + 3)),
                              rng.uniform(0, 0.3, 3).tolist(), -1)
        img[y:y + h, x:x + w] = patch
        cv2.rectangle(img, (int(x), int(y)), (int(x + w), int(y + h)), rng.uniform(0, 1, 3).tolist(), 3)
    if plain:
        # Everything above was still drawn so that the rest of the room (furniture, later
        # walls) comes out of the random stream exactly as in the textured room.
        return np.full((2, 2, 3), np.clip(base, 0.02, 1.0), np.float32)
    return np.clip(img, 0.02, 1.0).astype(np.float32)


@dataclass
class Room:
    """A closed box of textured walls around the head, plus a few boxes for parallax."""

    vertices: np.ndarray
    faces: np.ndarray
    face_texture: np.ndarray  # texture index per face
    face_axes: np.ndarray  # (F, 2) world axes (0..2) mapped to texture (u, v)
    face_origin: np.ndarray  # (F, 2) world coordinates at texture (0, 0)
    face_extent: np.ndarray  # (F, 2) mm covered by the whole texture
    textures: list[np.ndarray]

    @classmethod
    def random(cls, rng: np.random.Generator, plain: bool = False) -> Room:
        lo = np.array([-rng.uniform(1500, 2200), -rng.uniform(1100, 1400), -rng.uniform(1500, 2500)])
        hi = np.array([rng.uniform(1500, 2200), rng.uniform(1300, 1700), rng.uniform(1500, 2500)])
        boxes = [(lo, hi, True)]
        for _ in range(rng.integers(3, 6)):  # furniture standing on the floor
            size = rng.uniform([300, 400, 300], [900, 1500, 700])
            centre = np.array([rng.uniform(lo[0] + size[0] / 2, hi[0] - size[0] / 2), 0,
                               rng.uniform(lo[2] + size[2] / 2, hi[2] - size[2] / 2)])
            if np.hypot(centre[0], centre[2]) < 900:
                continue  # keep clear of the camera's path
            centre[1] = lo[1] + size[1] / 2
            boxes.append((centre - size / 2, centre + size / 2, False))
        verts, faces, tex, axes, origin, extent, textures = [], [], [], [], [], [], []
        for b_lo, b_hi, inward in boxes:
            box = trimesh.creation.box(bounds=np.stack([b_lo, b_hi]))
            f = box.faces if not inward else box.faces[:, ::-1]
            normal_axis = np.argmax(np.abs(box.face_normals), axis=1)
            for axis in range(3):
                sel = normal_axis == axis
                t = len(textures)
                textures.append(_wall_texture(rng, plain=plain))
                a = [i for i in range(3) if i != axis]
                faces.append(f[sel] + sum(len(v) for v in verts))
                tex.append(np.full(sel.sum(), t))
                axes.append(np.tile(a, (sel.sum(), 1)))
                origin.append(np.tile(b_lo[a], (sel.sum(), 1)))
                extent.append(np.tile(np.maximum(b_hi[a] - b_lo[a], 1.0), (sel.sum(), 1)))
            verts.append(box.vertices)
            # Each box's faces were appended three times (one per axis) but share vertices.
        return cls(np.concatenate(verts), np.concatenate(faces), np.concatenate(tex),
                   np.concatenate(axes), np.concatenate(origin), np.concatenate(extent), textures)

    def albedo(self, tri: np.ndarray, bary: np.ndarray, points: np.ndarray) -> np.ndarray:
        out = np.empty((len(tri), 3))
        ax = self.face_axes[tri]
        uv = (np.take_along_axis(points, ax, 1) - self.face_origin[tri]) / self.face_extent[tri]
        for t in np.unique(self.face_texture[tri]):
            sel = self.face_texture[tri] == t
            img = self.textures[t]
            s = img.shape[0] - 1
            coords = [np.clip(uv[sel, 1], 0, 1) * s, np.clip(uv[sel, 0], 0, 1) * s]
            out[sel] = np.stack([ndimage.map_coordinates(img[..., c], coords, order=1)
                                 for c in range(3)], 1)
        return out


# -- the camera path ------------------------------------------------------------------------


class SmoothNoise:
    """Sum of random sinusoids: a smooth zero-mean signal with about unit amplitude."""

    def __init__(self, rng: np.random.Generator, dims: int, f_lo: float, f_hi: float,
                 terms: int = 6):
        self.freq = rng.uniform(f_lo, f_hi, (terms, dims))
        self.phase = rng.uniform(0, 2 * np.pi, (terms, dims))
        self.amp = rng.uniform(0.5, 1.0, (terms, dims)) / np.sqrt(terms / 2)

    def __call__(self, t: float) -> np.ndarray:
        return np.sum(self.amp * np.sin(2 * np.pi * self.freq * t + self.phase), axis=0)


@dataclass
class CameraPath:
    """World-to-camera pose as a smooth function of time (seconds)."""

    config: SynthConfig
    target: np.ndarray
    rng: np.random.Generator

    def __post_init__(self):
        r = self.rng
        self.slow = SmoothNoise(r, 4, 0.05, 0.3)  # distance, elevation, roll, look-at drift
        self.tremor_pos = SmoothNoise(r, 3, 1.0, 6.0)
        self.tremor_rot = SmoothNoise(r, 3, 1.0, 6.0)

    def pose(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        c = self.config
        s = np.clip(t / c.duration_s, 0.0, 1.0)
        ease = s * s * (3 - 2 * s) * 0.6 + s * 0.4  # slower at the ends, as a hand does
        yaw = np.radians(c.yaw_start_deg + (c.yaw_end_deg - c.yaw_start_deg) * ease)
        slow = self.slow(t)
        lo, hi = c.distance_mm
        dist = (lo + hi) / 2 + (hi - lo) / 2 * np.clip(slow[0], -1, 1)
        elev = np.radians(c.elevation_deg + c.elevation_wobble_deg * slow[1])
        direction = np.array([np.sin(yaw) * np.cos(elev), np.sin(elev), np.cos(yaw) * np.cos(elev)])
        eye = self.target + dist * direction + c.hand_jitter_mm * self.tremor_pos(t)
        look = self.target + np.array([0.0, 8.0, 0.0]) * slow[3]
        roll = np.radians(c.roll_deg * slow[2])
        R, _ = look_at(eye, look, [0.0, 1.0, 0.0])
        jitter = np.radians(c.hand_jitter_deg) * self.tremor_rot(t)
        R = rotation_matrix([0, 0, 1], roll) @ _small_rotation(jitter) @ R
        return R, -R @ eye


def _small_rotation(w: np.ndarray) -> np.ndarray:
    angle = np.linalg.norm(w)
    return np.eye(3) if angle < 1e-12 else rotation_matrix(w / angle, angle)


# -- subject sway and rolling shutter -------------------------------------------------------


NECK_PIVOT_MM = np.array([0.0, -90.0, -30.0])
"""Where a swaying head turns, in the head frame: the top of the neck (the frame's origin
lies between the tops of the jaw contour, about ear level)."""


class HeadSway:
    """The head's rigid pose in the room over time: ``p_room = R p + c`` for a point ``p`` of
    the head frame, a smooth (0.1–0.5 Hz) translation and a turn about :data:`NECK_PIVOT_MM`,
    scaled so that their largest values at ``times`` are exactly ``sway_mm`` and
    ``sway_deg``. The reference pose (identity) is the head frame itself."""

    def __init__(self, rng: np.random.Generator, sway_mm: float, sway_deg: float,
                 times: np.ndarray):
        self.move = SmoothNoise(rng, 3, 0.1, 0.5)
        self.turn = SmoothNoise(rng, 3, 0.1, 0.5)
        peak_move = max(np.linalg.norm(self.move(t)) for t in times)
        peak_turn = max(np.linalg.norm(self.turn(t)) for t in times)
        self.move_scale = sway_mm / max(peak_move, 1e-12)
        self.turn_scale = np.radians(sway_deg) / max(peak_turn, 1e-12)

    def pose(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(R, c) of the head at time ``t``."""
        R = _small_rotation(self.turn_scale * self.turn(t))
        return R, NECK_PIVOT_MM - R @ NECK_PIVOT_MM + self.move_scale * self.move(t)


def _turn(image: np.ndarray, rotation_deg: int) -> np.ndarray:
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
    return Readout(_turn(rows, config.display_rotation_deg), offsets)


def _world_to_lines(points: np.ndarray, R: np.ndarray, t: np.ndarray, line: np.ndarray,
                    chunk: int = 1 << 19) -> np.ndarray:
    """Camera coordinates of points (N, 3), each seen by the pose (R[l], t[l]) of its line."""
    out = np.empty_like(points, dtype=float)
    for s in range(0, len(points), chunk):
        ln = line[s:s + chunk]  # chunked: a (N, 3, 3) gather of 4K frames would be 600 MB
        out[s:s + chunk] = np.einsum("nij,nj->ni", R[ln], points[s:s + chunk]) + t[ln]
    return out


def _project_lines(points: np.ndarray, R: np.ndarray, t: np.ndarray, line: np.ndarray,
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


def _motion_blur(img: np.ndarray, points: np.ndarray, projections: list[Callable],
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


def _to_srgb8(linear: np.ndarray) -> np.ndarray:
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


def _draw_lights(rng: np.random.Generator) -> list[tuple[np.ndarray, float]]:
    def direction(az, el):
        a, e = np.radians(az), np.radians(el)
        return np.array([np.sin(a) * np.cos(e), np.sin(e), np.cos(a) * np.cos(e)])

    key_az = rng.uniform(-50, 50)
    return [(direction(key_az, rng.uniform(20, 45)), rng.uniform(0.55, 0.75)),
            (direction(-key_az - np.sign(key_az) * rng.uniform(30, 60), rng.uniform(0, 20)),
             rng.uniform(0.15, 0.3))]


@dataclass
class Capture:
    """What :func:`synthesize` wrote."""

    folder: Path
    video: Path
    gt_mesh: Path
    gt_landmarks: Path
    gt_cameras: Path
    frames: int
    seconds: float


CODECS = {"h264": "libx264", "hevc": "libx265"}


def _encode(frames_path: Path, width: int, height: int, fps: float, crf: int,
            codec: str = "h264", rotation_deg: int = 0):
    import av

    container = av.open(str(frames_path), mode="w", format="mp4")
    rate = Fraction(fps).limit_denominator(1001)
    stream = container.add_stream(CODECS[codec], rate=rate)
    stream.width, stream.height = width, height
    stream.pix_fmt = "yuv420p"
    stream.time_base = 1 / rate
    stream.options = {"crf": str(crf), "preset": "medium"}
    if codec == "hevc":
        stream.codec_tag = "hvc1"  # as phones write it (Apple players need this tag)
        stream.options["x265-params"] = "log-level=error"
    if rotation_deg:
        stream.set_display_rotation(rotation_deg)
    return container, stream


@dataclass
class FrameRender:
    """One frame before sensor noise: linear RGB (upright, exposure gain applied), the
    ray-cast hits of its sharp image, and its ground truth."""

    image: np.ndarray
    hits: Hits
    time: float  # the ground-truth instant (s): mid-exposure of the sensor's middle line
    R: np.ndarray  # world-to-camera at ``time``, world = the head frame (the GT mesh's)
    t: np.ndarray
    gain: float
    head: tuple[np.ndarray, np.ndarray] | None  # head-to-room (R, c) at ``time`` when swaying


@dataclass
class Shot:
    """A capture's scene, camera path and sensor, ready to render any frame or instant."""

    config: SynthConfig
    subject: Subject
    intrinsics: Intrinsics  # of the upright image
    lights: list
    renderer: Renderer
    path: CameraPath  # camera in the room
    target: np.ndarray
    gain_noise: SmoothNoise
    readout: Readout | None
    sway: HeadSway | None
    frames: int
    exposure: float
    uv0: np.ndarray

    def frame_time(self, i: int) -> float:
        """Frame ``i``'s ground-truth instant: mid-exposure of the sensor's middle line."""
        return i / self.config.fps + self.exposure / 2 + self.config.rolling_shutter_s / 2

    def camera(self, time: float):
        """The room-to-camera pose at ``time``: (R, t), or per sensor line (L, 3, 3), (L, 3)
        with a rolling shutter."""
        if self.readout is None:
            return self.path.pose(time)
        poses = [self.path.pose(time + o) for o in self.readout.offsets]
        return np.stack([p[0] for p in poses]), np.stack([p[1] for p in poses])

    def _projection(self, time: float) -> Callable:
        R, t = self.camera(time)
        intr = self.intrinsics
        if self.readout is None:
            return lambda p, valid: project(p, R, t, intr)[0]
        line = self.readout.lines.ravel()
        return lambda p, valid: _project_lines(p, R, t, line[valid], intr)

    def render(self, time: float):
        """Linear RGB image of the (blurred) exposure centred on ``time`` (its sensor lines
        at their own times with a rolling shutter; the head at its pose at ``time``), the
        sharp image's hits, and the head's pose."""
        c = self.config
        R, t = self.camera(time)
        head = None if self.sway is None else self.sway.pose(time)
        lines = None if self.readout is None else self.readout.lines
        img, hits = self.renderer.render(R, t, lines, head)
        if c.blur_samples > 1 and self.exposure > 0:
            offsets = np.linspace(-self.exposure / 2, self.exposure / 2, c.blur_samples)
            img = _motion_blur(img, hits.points, [self._projection(time + d) for d in offsets],
                               self.uv0)
        return img, hits, head

    def frame(self, i: int) -> FrameRender:
        time = self.frame_time(i)
        img, hits, head = self.render(time)
        gain = float(np.exp(self.config.exposure_drift * self.gain_noise(i / self.config.fps)[0]))
        R, t = self.path.pose(time)
        if head is not None:
            # Head-relative ground truth: x_cam = R (R_h p + c_h) + t for a head-frame p.
            R, t = R @ head[0], R @ head[1] + t
        return FrameRender(img * gain, hits, time, R, t, gain, head)


def prepare(config: SynthConfig) -> Shot:
    """Subject, camera, lights, room and motions of a capture (every random draw)."""
    rng = np.random.default_rng(config.seed)
    subject = make_subject(config)
    intr = draw_intrinsics(config, rng)
    if config.display_rotation_deg in (90, 270):
        # Portrait: the sensor's drawn camera, as seen in the upright image.
        intr = Intrinsics(intr.height, intr.width, intr.fy, intr.fx, intr.cy, intr.cx,
                          intr.k1, intr.k2)
    lights = _draw_lights(rng)
    room = (Room.random(np.random.default_rng([config.seed, 2]), plain=config.plain_walls)
            if config.room else None)
    renderer = Renderer(subject, room, intr, lights, config.ambient, config.specular)
    w = np.abs(subject.landmarks[[0, 16], 0]).mean()
    target = np.array([0.0, subject.landmarks[27, 1] * 0.5, 0.3 * w])
    path = CameraPath(config, target, np.random.default_rng([config.seed, 3]))
    gain_noise = SmoothNoise(np.random.default_rng([config.seed, 4]), 1, 0.05, 0.4)
    n_frames = max(2, int(round(config.duration_s * config.fps)))
    exposure = config.exposure_fraction / config.fps
    uv0 = np.stack(np.meshgrid(np.arange(intr.width, dtype=float),
                               np.arange(intr.height, dtype=float)), -1).reshape(-1, 2)
    shot = Shot(config, subject, intr, lights, renderer, path, target, gain_noise,
                rolling_readout(config), None, n_frames, exposure, uv0)
    if config.sway_mm > 0 or config.sway_deg > 0:
        times = np.array([shot.frame_time(i) for i in range(n_frames)])
        shot.sway = HeadSway(np.random.default_rng([config.seed, 6]), config.sway_mm,
                             config.sway_deg, times)
    return shot


def synthesize(config: SynthConfig, out_dir: str | Path, progress: bool = True) -> Capture:
    """Render a capture of ``config`` into ``out_dir`` (see the module docstring)."""
    import av
    from tqdm import tqdm

    start = time.perf_counter()
    out = Path(out_dir)
    gt_dir = out / "gt"
    try:
        gt_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create output folder {out}: {exc.strerror}") from None
    if config.width % 2 or config.height % 2:
        raise InputError(f"video size {config.width}x{config.height}: H.264 needs even sizes")
    shot = prepare(config)
    subject, intr = shot.subject, shot.intrinsics
    noise_rng = np.random.default_rng([config.seed, 5])
    seen = np.zeros(len(subject.faces), bool)
    frames_meta = []
    video_path = out / "video.mp4"
    tmp_video = out / ".video.mp4.part"
    container, stream = _encode(tmp_video, config.width, config.height, config.fps, config.crf,
                                config.codec, config.display_rotation_deg)
    try:
        for i in tqdm(range(shot.frames), desc="render", unit="frame", disable=not progress):
            f = shot.frame(i)
            on_subject = f.hits.mesh == 0
            seen[np.unique(f.hits.triangle[on_subject])] = True
            img = f.image
            sigma = np.sqrt(config.read_noise ** 2 + config.shot_noise ** 2 * np.clip(img, 0, 1))
            img = img + sigma * noise_rng.standard_normal(img.shape)
            # Stored as the sensor holds it; the display rotation turns it upright again.
            stored = _turn(_to_srgb8(img), -config.display_rotation_deg)
            frame = av.VideoFrame.from_ndarray(stored, format="rgb24")
            frame.pts = i
            for packet in stream.encode(frame):
                container.mux(packet)
            meta = {"index": i, "time": round(f.time, 6), "R": f.R.round(12).tolist(),
                    "t": f.t.round(9).tolist(), "exposure_gain": round(f.gain, 6)}
            if f.head is not None:
                meta["head_R"] = f.head[0].round(12).tolist()
                meta["head_t"] = f.head[1].round(9).tolist()
            frames_meta.append(meta)
        for packet in stream.encode():
            container.mux(packet)
    finally:
        container.close()
    os.replace(tmp_video, video_path)

    gt_faces = subject.gt_faces | (subject.optional_faces & seen)
    gt = trimesh.Trimesh(subject.vertices, subject.faces[gt_faces], process=False)
    gt.remove_unreferenced_vertices()
    gt.export(gt_dir / "mesh.ply")
    save_landmarks(gt_dir / "landmarks.json", subject.landmarks, subject=subject.name)
    cameras = {"units": "mm", "convention": "world-to-camera x_cam = R x_world + t (OpenCV); "
               "pixel centres at integer coordinates", "model": "RADIAL (k1, k2)",
               "width": intr.width, "height": intr.height, "fps": config.fps,
               "intrinsics": intr.to_dict(), "frames": frames_meta}
    cameras.update(_conditions_doc(config))
    (gt_dir / "cameras.json").write_text(json.dumps(cameras, indent=1))
    (gt_dir / "subject.json").write_text(json.dumps({"name": subject.name, **subject.info},
                                                    indent=1))
    dump_yaml(config, gt_dir / "config.yaml")
    render_info = {"intrinsics": intr.to_dict(), "horizontal_fov_deg": intr.horizontal_fov_deg,
                   "lights": [{"direction": d.round(6).tolist(), "intensity": round(s, 6)}
                              for d, s in shot.lights],
                   "ambient": config.ambient, "specular": config.specular,
                   "exposure_s": shot.exposure, "frames": shot.frames,
                   "look_at_target": shot.target.tolist(),
                   "render_seconds": round(time.perf_counter() - start, 3)}
    (gt_dir / "render.json").write_text(json.dumps(render_info, indent=1))
    return Capture(out, video_path, gt_dir / "mesh.ply", gt_dir / "landmarks.json",
                   gt_dir / "cameras.json", shot.frames, time.perf_counter() - start)


def _conditions_doc(config: SynthConfig) -> dict:
    """What ``gt/cameras.json`` says about the phone-like conditions that are on (nothing
    for a default capture, whose file stays as it was)."""
    doc = {}
    if config.display_rotation_deg:
        doc["display_rotation_deg"] = config.display_rotation_deg
        doc["stored_size"] = [config.width, config.height]
        doc["orientation"] = ("width, height and intrinsics are of the upright image (the "
                              "stored frames turned counter-clockwise by display_rotation_deg)")
    if config.rolling_shutter_s > 0:
        doc["rolling_shutter"] = {
            "readout_s": config.rolling_shutter_s, "lines": config.height,
            "meaning": "stored row r (a column of the upright image in portrait) is exposed "
                       "at frames[].time + readout_s * ((r + 0.5) / lines - 0.5); the frame's "
                       "R, t are the pose at frames[].time, mid-exposure of the middle line"}
    if config.sway_mm > 0 or config.sway_deg > 0:
        doc["sway"] = {
            "sway_mm": config.sway_mm, "sway_deg": config.sway_deg,
            "meaning": "the head sways in a still room; world = the head frame (the GT mesh's "
                       "at rest), so R, t are camera relative to the head; head_R, head_t map "
                       "head-frame points into the room at frames[].time: p_room = head_R p + "
                       "head_t (the room-relative camera is R head_R^T, t - R head_R^T head_t)"}
    return doc


def load_gt_cameras(path: str | Path) -> tuple[Intrinsics, list[dict]]:
    """Intrinsics and per-frame poses (R, t as arrays) from a ``gt/cameras.json``."""
    doc = json.loads(Path(path).read_text())
    frames = [{**f, "R": np.asarray(f["R"]), "t": np.asarray(f["t"])} for f in doc["frames"]]
    return Intrinsics.from_dict(doc["intrinsics"]), frames
