"""The subjects of synthetic captures: ICT identities or a textured scan, with procedural
skin, hair, eyes and their ground truth."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from scipy import ndimage

from facecap.synthetic.config import SynthConfig
from facecap_core.assets import default_ict_model, james_files
from facecap_core.camera import (
    rotation_matrix,
)
from facecap_core.errors import InputError
from facecap_core.meshio import load_landmarks, load_mesh
from facecap_core.render import (
    RaycastScene,
    interpolate,
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


def smoothstep(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
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
        freckles = smoothstep(n(points, 1.6, 4), self.freckle_level, self.freckle_level + 0.6)
        rgb *= (1 - d * 0.35 * freckles[:, None] * np.array([0.8, 1.0, 1.1]))
        lips = self.lips(points)[:, None]
        rgb = rgb * (1 - lips) + self.lip * (1 + 0.08 * n(points, 0.8, 5))[:, None] * lips
        strands = smoothstep(n(points, 0.6, 6, stretch=(6.0, 1.0, 1.0)), -0.3, 0.6)
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
    hair_v = smoothstep(verts[:, 1] - hairline, -4.0, 6.0) * lateral_ok
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
        # --ict-model, else $FACECAP_ICT_MODEL, else the trimmed model in the package.
        model = config.ict_model or default_ict_model()
        arg = spec[4:]  # ict:mean or ict:SEED, as SynthConfig checked
        return ict_subject(model, None if arg == "mean" else int(arg), config.ict_identity_sigma,
                           config.skin_detail)
    if config.skin_detail != 1.0:
        raise InputError(f"skin_detail {config.skin_detail}: only the procedural skin of ict: "
                         "subjects can be smoothed; leave it at 1 for a textured mesh")
    if spec == "james":
        mesh, lms = james_files()
        return textured_subject(mesh, lms, name="james")
    if config.subject_landmarks is None:
        raise InputError(f"subject mesh {spec}: pass its 68 3D landmarks with "
                         "--subject-landmarks FILE")
    return textured_subject(spec, config.subject_landmarks, config.subject_scale)


# -- the room ---------------------------------------------------------------------------------
