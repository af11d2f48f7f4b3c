"""Synthetic handheld captures of a textured head, with exact ground truth.

A capture is an ear-to-ear sweep: the camera moves on an arc from one profile to the other
at 35–50 cm, looking at the head, with slow drifts (distance, elevation, roll) and fast hand
tremor. The camera is a phone-like pinhole with an unknown focal length (~65° horizontal
field of view), a jittered principal point and radial distortion. Each frame is ray cast
(open3d) through the distorted pixel grid — no resampling — shaded (Lambert + a little
specular) under fixed world lights, blurred by the camera's motion during the exposure,
scaled by a drifting auto-exposure gain, given Poisson–Gaussian sensor noise, and encoded as
H.264. A static textured room surrounds the subject so there is a background to track.

World frame: the subject's head frame (mm) from its landmarks (see
:func:`facecap_core.template.head_frame`): +x the subject's left, +y up, +z out of the face,
origin between the tops of the jaw contour.

Output folder::

    video.mp4            the capture (H.264, yuv420p)
    gt/mesh.ply          the visible head surface in mm (world frame): the "scan"
    gt/landmarks.json    68 3D landmarks (iBUG order, mm)
    gt/cameras.json      intrinsics + distortion, and per frame: time, world-to-camera R, t
                         (OpenCV convention, at mid-exposure), exposure gain
    gt/subject.json      what the subject is (ICT coefficients, texture, ...)
    gt/config.yaml       the exact SynthConfig used
    gt/render.json       every drawn quantity (focal, distortion, lights, ...)
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import trimesh
from scipy import ndimage

from facecap_core.camera import Intrinsics, look_at, pixel_rays, project, rotation_matrix
from facecap_core.config import SynthConfig, dump_yaml
from facecap_core.errors import InputError
from facecap_core.meshio import load_landmarks, load_mesh, save_landmarks
from facecap_core.render import RaycastScene, interpolate, shade_lambert, vertex_normals
from facecap_core.template import (
    ICT_EYE_MATERIALS, head_frame, ict_faces_of, ict_identity_vertices, ict_skin_faces,
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
HAIR_COLOURS = np.array([[0.05, 0.035, 0.025], [0.12, 0.07, 0.035], [0.25, 0.16, 0.08],
                         [0.02, 0.02, 0.02]])


class SkinAlbedo:
    """Procedural skin for a head in its head frame: tone, blotches, mottling, pores,
    freckles, lips, brows and short hair — texture at 0.5–25 mm for stereo matching."""

    def __init__(self, landmarks: np.ndarray, rng: np.random.Generator,
                 hair_weight: np.ndarray | None = None):
        self.noise = SolidNoise(rng)
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
        lum = (1 + 0.07 * n(points, 4.0, 1) + 0.05 * n(points, 1.2, 2) + 0.03 * n(points, 0.5, 3))
        red = 0.06 * n(points, 25.0, 0)
        rgb = self.tone[None, :] * lum[:, None]
        rgb[:, 0] *= 1 + red
        rgb[:, 1] *= 1 - 0.5 * red
        freckles = _smoothstep(n(points, 1.6, 4), self.freckle_level, self.freckle_level + 0.6)
        rgb *= (1 - 0.35 * freckles[:, None] * np.array([0.8, 1.0, 1.1]))
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


def ict_subject(model_path: str | Path, seed: int | None, sigma: float = 1.0) -> Subject:
    """A random ICT Face Model identity (``seed=None``: the mean face) with procedural skin."""
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
    names = list(model["material_names"])
    iris_ids = [names.index("M_IrisLeft"), names.index("M_IrisRight")]
    face_mat = model["face_material"]
    eye_material = face_mat[np.isin(face_mat, [names.index(m) for m in ICT_EYE_MATERIALS])]
    is_iris = np.concatenate([np.zeros(len(skin), bool), np.isin(eye_material, iris_ids),
                              np.zeros(len(sockets), bool)])
    # Hair: scalp above a hairline that falls from the forehead to the nape.
    w = np.abs(lm[[0, 16], 0]).mean()
    hairline = np.interp(verts[:, 2], [-1.4 * w, -0.6 * w, 0.3 * w, 2 * w],
                         [-0.45 * w, 0.62 * w, lm[27, 1] + 0.95 * w, lm[27, 1] + 0.95 * w])
    lateral_ok = ~((np.abs(verts[:, 0]) > 0.85 * w) & (verts[:, 1] < 0.75 * w)
                   & (verts[:, 2] > -0.7 * w))  # keep the temples and ears bare
    hair_v = _smoothstep(verts[:, 1] - hairline, -4.0, 6.0) * lateral_ok
    skin_albedo = SkinAlbedo(lm, rng)
    iris_rgb = IRIS_COLOURS[rng.integers(len(IRIS_COLOURS))]
    eye_centres = {}
    for side in ("Left", "Right"):
        tri = ict_faces_of(model, (f"M_Sclera{side}", f"M_Iris{side}"))
        iris = ict_faces_of(model, (f"M_Iris{side}",))
        centre = verts[np.unique(tri)].mean(0)
        front = verts[np.unique(iris)].mean(0)
        eye_centres[side] = (centre, (front - centre) / np.linalg.norm(front - centre), front)
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
            iris = is_iris[tri[e]]
            for centre, axis, front in eye_centres.values():
                d = p - front
                r = np.linalg.norm(d - (d @ axis)[:, None] * axis, axis=1)
                near = np.linalg.norm(p - centre, axis=1) < 16
                ring = 1 + 0.25 * skin_albedo.noise(p, 0.4, 5)
                col = np.where((r < 1.9)[:, None], 0.02, iris_rgb * ring[:, None])
                sel = near & (iris | (r < 5.8))
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
            "skin_tone": skin_albedo.tone.round(4).tolist()}
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
        return ict_subject(model, None if arg == "mean" else int(arg), config.ict_identity_sigma)
    if spec == "james":
        from facecap_core.assets import james_files

        mesh, lms = james_files()
        return textured_subject(mesh, lms, name="james")
    if config.subject_landmarks is None:
        raise InputError(f"subject mesh {spec}: pass its 68 3D landmarks with "
                         "--subject-landmarks FILE")
    return textured_subject(spec, config.subject_landmarks, config.subject_scale)


# -- the room ---------------------------------------------------------------------------------


def _wall_texture(rng: np.random.Generator, size: int = 1024) -> np.ndarray:
    """A wall: paint with large and fine noise, and posters, shelves and frames on it."""
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
    def random(cls, rng: np.random.Generator) -> "Room":
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
                textures.append(_wall_texture(rng))
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

    def render(self, R: np.ndarray, t: np.ndarray):
        """Linear-RGB image (H, W, 3) and the ray-cast hits of one pose."""
        hits = self.scene.cast_camera(self.intrinsics, R, t, self.rays)
        h, w = hits.depth.shape
        img = np.zeros((h * w, 3))
        mesh = hits.mesh.ravel()
        tri = hits.triangle.ravel()
        bary = hits.bary.reshape(-1, 3)
        pts = hits.points.reshape(-1, 3)
        centre = -R.T @ t
        for mesh_id in (0, 1):
            sel = mesh == mesh_id
            if not sel.any():
                continue
            if mesh_id == 0:
                alb = self.subject.albedo(tri[sel], bary[sel], pts[sel])
                n = interpolate(self.normals, self.subject.faces, tri[sel], bary[sel])
                n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
                spec = self.specular
                # Occlusion darkens eye sockets, nostrils and creases as in a real photo.
                alb = alb * interpolate(self.subject.occlusion[:, None], self.subject.faces,
                                        tri[sel], bary[sel]) ** 0.7
            else:
                alb = self.room.albedo(tri[sel], bary[sel], pts[sel])
                n = self.room_normals[tri[sel]]
                spec = 0.0
            view = centre - pts[sel]
            view /= np.linalg.norm(view, axis=1, keepdims=True)
            img[sel] = shade_lambert(alb, n, view, self.lights, self.ambient, spec)
        return img.reshape(h, w, 3), hits


def _motion_blur(img: np.ndarray, points: np.ndarray, poses: list, intr: Intrinsics,
                 uv0: np.ndarray) -> np.ndarray:
    """Average the sharp image along each pixel's motion over the exposure."""
    h, w = img.shape[:2]
    valid = np.isfinite(points[..., 0]).ravel()
    acc = np.zeros_like(img, dtype=np.float32)
    src = img.astype(np.float32)
    for R, t in poses:
        uv = uv0.copy()
        uv_k, _ = project(points.reshape(-1, 3)[valid], R, t, intr)
        uv[valid] = uv_k
        flow = (uv - uv0).reshape(h, w, 2)
        grid = uv0.reshape(h, w, 2) - flow
        acc += cv2.remap(src, grid[..., 0].astype(np.float32), grid[..., 1].astype(np.float32),
                         cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    return acc / len(poses)


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


def _encode(frames_path: Path, width: int, height: int, fps: float, crf: int):
    import av

    container = av.open(str(frames_path), mode="w", format="mp4")
    rate = Fraction(fps).limit_denominator(1001)
    stream = container.add_stream("libx264", rate=rate)
    stream.width, stream.height = width, height
    stream.pix_fmt = "yuv420p"
    stream.time_base = 1 / rate
    stream.options = {"crf": str(crf), "preset": "medium"}
    return container, stream


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
    rng = np.random.default_rng(config.seed)
    subject = make_subject(config)
    intr = draw_intrinsics(config, rng)
    lights = _draw_lights(rng)
    room = Room.random(np.random.default_rng([config.seed, 2])) if config.room else None
    renderer = Renderer(subject, room, intr, lights, config.ambient, config.specular)
    w = np.abs(subject.landmarks[[0, 16], 0]).mean()
    target = np.array([0.0, subject.landmarks[27, 1] * 0.5, 0.3 * w])
    path = CameraPath(config, target, np.random.default_rng([config.seed, 3]))
    gain_noise = SmoothNoise(np.random.default_rng([config.seed, 4]), 1, 0.05, 0.4)
    noise_rng = np.random.default_rng([config.seed, 5])

    n_frames = max(2, int(round(config.duration_s * config.fps)))
    exposure = config.exposure_fraction / config.fps
    uv0 = np.stack(np.meshgrid(np.arange(intr.width, dtype=float),
                               np.arange(intr.height, dtype=float)), -1).reshape(-1, 2)
    seen = np.zeros(len(subject.faces), bool)
    frames_meta = []
    video_path = out / "video.mp4"
    tmp_video = out / ".video.mp4.part"
    container, stream = _encode(tmp_video, intr.width, intr.height, config.fps, config.crf)
    try:
        for i in tqdm(range(n_frames), desc="render", unit="frame", disable=not progress):
            t_mid = i / config.fps + exposure / 2
            R, t = path.pose(t_mid)
            img, hits = renderer.render(R, t)
            on_subject = hits.mesh == 0
            seen[np.unique(hits.triangle[on_subject])] = True
            if config.blur_samples > 1 and exposure > 0:
                offsets = np.linspace(-exposure / 2, exposure / 2, config.blur_samples)
                img = _motion_blur(img, hits.points, [path.pose(t_mid + d) for d in offsets],
                                   intr, uv0)
            gain = float(np.exp(config.exposure_drift * gain_noise(i / config.fps)[0]))
            img = img * gain
            sigma = np.sqrt(config.read_noise ** 2 + config.shot_noise ** 2 * np.clip(img, 0, 1))
            img = img + sigma * noise_rng.standard_normal(img.shape)
            frame = av.VideoFrame.from_ndarray(_to_srgb8(img), format="rgb24")
            frame.pts = i
            for packet in stream.encode(frame):
                container.mux(packet)
            frames_meta.append({"index": i, "time": round(t_mid, 6), "R": R.round(12).tolist(),
                                "t": t.round(9).tolist(), "exposure_gain": round(gain, 6)})
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
    (gt_dir / "cameras.json").write_text(json.dumps(cameras, indent=1))
    (gt_dir / "subject.json").write_text(json.dumps({"name": subject.name, **subject.info},
                                                    indent=1))
    dump_yaml(config, gt_dir / "config.yaml")
    render_info = {"intrinsics": intr.to_dict(), "horizontal_fov_deg": intr.horizontal_fov_deg,
                   "lights": [{"direction": d.round(6).tolist(), "intensity": round(s, 6)}
                              for d, s in lights],
                   "ambient": config.ambient, "specular": config.specular,
                   "exposure_s": exposure, "frames": n_frames, "look_at_target": target.tolist(),
                   "render_seconds": round(time.perf_counter() - start, 3)}
    (gt_dir / "render.json").write_text(json.dumps(render_info, indent=1))
    return Capture(out, video_path, gt_dir / "mesh.ply", gt_dir / "landmarks.json",
                   gt_dir / "cameras.json", n_frames, time.perf_counter() - start)


def load_gt_cameras(path: str | Path) -> tuple[Intrinsics, list[dict]]:
    """Intrinsics and per-frame poses (R, t as arrays) from a ``gt/cameras.json``."""
    doc = json.loads(Path(path).read_text())
    frames = [{**f, "R": np.asarray(f["R"]), "t": np.asarray(f["t"])} for f in doc["frames"]]
    return Intrinsics.from_dict(doc["intrinsics"]), frames
