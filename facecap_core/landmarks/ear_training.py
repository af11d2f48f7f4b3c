"""Training data for the ear models, and their training (dlib HOG detector + ERT predictor).

No registry package ships an ear model, so facecap renders its own training set:

1. **Ear contour on the template.** The outer contour of each ear is a fixed, ordered list of
   default-template vertices (:func:`template_ear_contour`): seen from the side, the outline of
   the template's ``ears`` region, walked from the helix root (top front) over the top and
   the back of the helix down to the lobe, sampled at equal arc length. Along the outline the
   most lateral vertex is taken, so the points sit on the rim of the helix.
2. **Correspondence.** Training heads are ICT Face Model identities (another topology). The
   template is fitted once to the ICT mean head (:func:`facecap_core.fitting.fit`, cloud +
   68 landmarks) and each fitted contour vertex is snapped to the nearest ICT surface point,
   kept as (triangle corners, barycentrics): every ICT identity shares the topology, so the
   same barycentrics give its contour. Any other mesh (James) gets its own fit
   (:func:`fitted_ear_contour`).
3. **Renders.** ICT identities (seeds from ``first_identity_seed``, never the evaluation seeds
   0 and 1) with procedural skin in a textured room, seen from yaw 30-100 deg on either side
   with random elevation, roll, distance, focal length, lights, exposure, blur, noise and
   JPEG compression, and often hair painted around the ears. Ground truth: the contour
   points projected into the image, with a ray-cast visibility flag, and a fixed-aspect box
   around them. Right-ear views are mirrored so
   one model serves both sides (:func:`facecap_core.landmarks.ears.detect_ears` mirrors a
   right-ear image before detection).
4. **Training.** ``dlib.train_simple_object_detector`` (HOG + linear SVM) on the boxes, then
   ``dlib.train_shape_predictor`` (ensemble of regression trees) on the contour points, with
   the detector's own boxes as its input where the detector finds the ear.

Run ``python -m facecap_core.landmarks.ear_training --out DIR``; the folder gets
``ear_detector.svm``, ``ear_predictor.dat``, ``ear_contour.json``, ``training.json`` and a
few preview PNGs. Copy the first three into ``facecap_core/landmarks/models/`` to ship them.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from facecap_core.camera import Intrinsics, look_at, pixel_rays, project, rotation_matrix
from facecap_core.config import EarTrainingConfig, FittingConfig
from facecap_core.errors import InputError
from facecap_core.render import RaycastScene
from facecap_core.template import Template, head_frame

SIDES = ("left", "right")
SIDE_SIGN = {"left": 1.0, "right": -1.0}  # head frame +x is the subject's left
DETECTOR_FILE = "ear_detector.svm"
PREDICTOR_FILE = "ear_predictor.dat"
CONTOUR_FILE = "ear_contour.json"
MODEL_FILES = (DETECTOR_FILE, PREDICTOR_FILE, CONTOUR_FILE)


# -- the ear contour on the template ---------------------------------------------------------


def template_ear_contour(template: Template, side: str, count: int = 12,
                         arc_deg: tuple[float, float] = (130.0, -115.0)) -> np.ndarray:
    """Ordered vertex ids of one ear's outer contour (helix root -> top -> back -> lobe).

    In the head frame's side plane (a = backwards, b = up), around the centre of the ear
    region's bounding box, the outline is the farthest ear vertex per 3-degree sector, swept
    clockwise from ``arc_deg[0]`` (0 = straight back, 90 = up) to ``arc_deg[1]``; ``count``
    points are then taken at equal arc length along it.
    """
    if side not in SIDES:
        raise InputError(f"ear side {side!r}: expected 'left' or 'right'")
    R, origin = head_frame(template.landmark_points)
    P = (template.vertices - origin) @ R.T
    ids = np.flatnonzero(template.regions["ears"] & (np.sign(P[:, 0]) == SIDE_SIGN[side]))
    if len(ids) < 3 * count:
        raise InputError(f"template {template.name} has {len(ids)} {side} ear vertices; "
                         f"the ear contour needs a template with ears")
    Q = P[ids]
    ab = np.stack([-Q[:, 2], Q[:, 1]], 1)
    centre = (ab.min(0) + ab.max(0)) / 2
    d = ab - centre
    angle = np.degrees(np.arctan2(d[:, 1], d[:, 0]))
    radius = np.hypot(d[:, 0], d[:, 1])
    lateral = np.abs(Q[:, 0])
    outline = []
    for hi in np.arange(arc_deg[0], arc_deg[1], -3.0):
        sel = np.flatnonzero((angle <= hi) & (angle > hi - 3.0))
        if not len(sel):
            continue
        # Of the vertices on the outline (within 0.5 mm of the farthest), the most lateral
        # one is the rim's outer edge rather than its inner fold.
        near = sel[radius[sel] >= radius[sel].max() - 0.5]
        outline.append(near[np.argmax(lateral[near])])
    outline = np.array(outline)
    # Arc length in the side plane: the outline's lateral zigzag is not part of its length.
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(ab[outline], axis=0), axis=1))])
    picks = [outline[np.argmin(np.abs(arc - s))] for s in np.linspace(0, arc[-1], count)]
    out = ids[np.array(picks)]
    if len(np.unique(out)) != count:
        raise InputError(f"template {template.name}: the {side} ear outline is too coarse "
                         f"for {count} contour points")
    return out


# -- correspondence to other heads -----------------------------------------------------------


@dataclass
class SurfacePoints:
    """Points on a mesh as triangle corner vertex ids (K, 3) and barycentrics (K, 3)."""

    corners: np.ndarray
    bary: np.ndarray

    def on(self, vertices: np.ndarray) -> np.ndarray:
        """The points on a mesh of the same topology with these vertex positions."""
        return np.einsum("kc,kcd->kd", self.bary, np.asarray(vertices, float)[self.corners])

    def to_dict(self) -> dict:
        return {"corners": self.corners.tolist(), "bary": self.bary.round(6).tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> SurfacePoints:
        return cls(np.asarray(d["corners"], np.int64), np.asarray(d["bary"], float))


def snap_to_surface(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray
                    ) -> tuple[SurfacePoints, np.ndarray]:
    """Nearest surface points of a mesh to ``points`` and their distances."""
    import trimesh

    mesh = trimesh.Trimesh(np.asarray(vertices, float), np.asarray(faces, np.int64),
                           process=False)
    closest, dist, tri = trimesh.proximity.closest_point(mesh, np.asarray(points, float))
    corners = mesh.faces[tri]
    bary = trimesh.triangles.points_to_barycentric(mesh.vertices[corners], closest)
    return SurfacePoints(corners.astype(np.int64), np.clip(bary, 0.0, 1.0)), dist


def fit_template_to_head(template: Template, vertices: np.ndarray, faces: np.ndarray,
                         landmarks: np.ndarray) -> np.ndarray:
    """Template vertices fitted (NICP, dense surface samples + 68 landmarks) to a head mesh."""
    from facecap_core.fitting import fit
    from facecap_core.fitting.synthetic_cloud import mvs_like_cloud

    cloud, normals = mvs_like_cloud(vertices, faces, density=2.0, noise_mm=0.0, holes=0.0,
                                    outliers=0.0, normal_jitter_deg=0.0)
    result = fit(template, cloud, landmarks, cloud_normals=normals,
                 config=FittingConfig(use_edges=False, texture=False))
    return result.vertices


def fitted_ear_contour(template: Template, contour_ids: dict[str, np.ndarray],
                       vertices: np.ndarray, faces: np.ndarray, landmarks: np.ndarray
                       ) -> dict[str, tuple[SurfacePoints, np.ndarray]]:
    """Per side: the contour as surface points of the head mesh, and the snap distances (mm)."""
    fitted = fit_template_to_head(template, vertices, faces, landmarks)
    return {side: snap_to_surface(vertices, faces, fitted[ids])
            for side, ids in contour_ids.items()}


def ict_contour_transfer(template: Template, contour_ids: dict[str, np.ndarray],
                         ict_model: str | Path) -> dict:
    """The contour on the ICT topology (via a fit to the ICT mean head), as JSON-ready data."""
    from facecap_core.synthetic import ict_subject

    mean = ict_subject(ict_model, None)
    skin = mean.faces[mean.gt_faces]
    snapped = fitted_ear_contour(template, contour_ids, mean.vertices, skin, mean.landmarks)
    return {side: {**sp.to_dict(), "snap_mm": dist.round(3).tolist()}
            for side, (sp, dist) in snapped.items()}


def write_contour_file(path: str | Path, config: EarTrainingConfig, ict_model: str | Path,
                       template: Template | None = None) -> dict:
    """Compute the template contour ids and their ICT transfer; write ``ear_contour.json``."""
    template = template or Template.default()
    ids = {side: template_ear_contour(template, side, config.contour_points,
                                      config.contour_arc_deg) for side in SIDES}
    doc = {"template": template.name, "template_vertices": len(template.vertices),
           "order": "helix root (top front) -> top -> back -> lobe",
           "vertex_ids": {s: v.tolist() for s, v in ids.items()},
           "ict": ict_contour_transfer(template, ids, ict_model)}
    Path(path).write_text(json.dumps(doc, indent=1))
    return doc


def load_contour_file(path: str | Path) -> dict:
    doc = json.loads(Path(path).read_text())
    return {"vertex_ids": {s: np.asarray(doc["vertex_ids"][s], np.int64) for s in SIDES},
            "ict": {s: SurfacePoints.from_dict(doc["ict"][s]) for s in SIDES},
            "template": doc.get("template")}


# -- rendering ----------------------------------------------------------------------------------


@dataclass
class EarSample:
    """One rendered view of one ear, mirrored to a left-ear view when ``side`` is right."""

    image: np.ndarray | None  # uint8 (H, W, 3) RGB (None until rendered)
    points: np.ndarray  # (K, 2) px, the contour in EAR_VERTEX_IDS order
    visible: np.ndarray  # (K,) bool, ray-cast visibility
    box: tuple[int, int, int, int]  # detector box (left, top, right, bottom)
    tight_box: tuple[float, float, float, float]  # bounding box of the projected contour
    side: str
    yaw_deg: float
    mirrored: bool
    camera: tuple | None = None  # (intrinsics, R, t, centre, view direction)

    @property
    def diagonal(self) -> float:
        l, t, r, b = self.tight_box
        return float(np.hypot(r - l, b - t))


def ear_box(points: np.ndarray, aspect: float, padding: float) -> tuple[int, int, int, int]:
    """Fixed-aspect (width / height) box around contour points, grown by ``padding`` per side."""
    lo, hi = points.min(0), points.max(0)
    centre = (lo + hi) / 2
    w, h = hi - lo
    h = max(h, w / aspect) * (1 + 2 * padding)
    w = h * aspect
    l, t = centre - np.array([w, h]) / 2
    return int(round(l)), int(round(t)), int(round(l + w)), int(round(t + h))


def visible_points(scene: RaycastScene, centre: np.ndarray, points: np.ndarray,
                   tolerance_mm: float = 3.0) -> np.ndarray:
    """True where the ray from the camera centre reaches the point before any other surface.

    The contour lies on the rim of the helix, which the camera often sees edge-on: a ray may
    graze the rim's near side a millimetre or two before the point, which still counts as
    seen; an occluder (the cheek, the helix from behind) is farther in front."""
    d = points - centre
    dist = np.linalg.norm(d, axis=1)
    hit = scene.cast(np.broadcast_to(centre, d.shape), d / dist[:, None])["t_hit"]
    return hit >= dist - tolerance_mm


def _lights(rng: np.random.Generator, view_dir: np.ndarray) -> list[tuple[np.ndarray, float]]:
    """A key light somewhere in front of the camera's side of the head, and a weaker fill."""
    def unit(v):
        return v / np.linalg.norm(v)

    key = unit(view_dir + rng.normal(0.0, 0.8, 3) + [0.0, 0.5, 0.0])
    fill = unit(view_dir + rng.normal(0.0, 1.0, 3))
    return [(key, rng.uniform(0.45, 0.8)), (fill, rng.uniform(0.1, 0.3))]


def _to_srgb8(linear: np.ndarray) -> np.ndarray:
    x = np.clip(linear, 0.0, 1.0)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.round(srgb * 255).astype(np.uint8)


def _smoothstep(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
    t = np.clip((x - lo) / (hi - lo), 0.0, 1.0)
    return t * t * (3 - 2 * t)


class HairAroundEars:
    """Random hair painted (texture only, as on a scanned head) around the ears.

    The ICT renders keep the temples and ears bare; real heads (and the James scan) frame
    the ear with hair, which changes the ear's outline contrast. Per view, each side gets
    hair beyond a random straight hairline in the side plane (above and/or behind the ear,
    sometimes over its top), with a wavy edge and strands.
    """

    def __init__(self, subject, contours: dict[str, np.ndarray], rng: np.random.Generator):
        from facecap_core.synthetic import SolidNoise
        from facecap_core.template import region_masks

        self.subject = subject
        self.base_albedo = subject.albedo
        self.contours = contours
        self.noise = SolidNoise(rng)
        skin = subject.faces[subject.gt_faces]
        self.ear_mask = region_masks(subject.vertices, subject.landmarks, skin)["ears"]
        self.weight = np.zeros(len(subject.vertices))
        self.colour = np.zeros(3)

    def draw(self, rng: np.random.Generator) -> None:
        """A new hairline per side and a new hair colour."""
        from facecap_core.synthetic import HAIR_COLOURS

        P = self.subject.vertices
        wavy = 3.0 * self.noise(P, 6.0, 1)
        weight = np.zeros(len(P))
        for side, contour in self.contours.items():
            centre = contour.mean(0)
            height = np.ptp(contour[:, 1])
            theta = np.radians(rng.uniform(0.0, 100.0))  # hair towards the back (0) .. top (90)
            # Often right at the rim, so that the hair frames the (bare) ear.
            offset = rng.uniform(-0.3, 0.6) * height
            across = (centre[2] - P[:, 2]) * np.cos(theta) + (P[:, 1] - centre[1]) * np.sin(theta)
            w = _smoothstep(across - offset + wavy, -1.5, 1.5)
            w *= np.sign(P[:, 0]) == SIDE_SIGN[side]
            if rng.uniform() < 0.75:
                w[self.ear_mask] = 0.0  # the ear itself stays bare most of the time
            weight = np.maximum(weight, w)
        self.weight = weight
        self.colour = HAIR_COLOURS[rng.integers(len(HAIR_COLOURS))] * rng.uniform(0.7, 1.5)

    def clear(self) -> None:
        self.weight = np.zeros(len(self.subject.vertices))

    def __call__(self, tri: np.ndarray, bary: np.ndarray, points: np.ndarray) -> np.ndarray:
        from facecap_core.render import interpolate

        rgb = self.base_albedo(tri, bary, points)
        w = interpolate(self.weight[:, None], self.subject.faces, tri, bary)[:, 0]
        if not np.any(w > 0):
            return rgb
        strands = _smoothstep(self.noise(points, 0.6, 6, stretch=(1.0, 6.0, 1.0)), -0.3, 0.6)
        hair = self.colour * (0.7 + 0.5 * strands)[:, None]
        w = w[:, None] * (0.85 + 0.15 * strands[:, None])
        return rgb * (1 - w) + hair * w


class EarRenderer:
    """Renders ear views of one subject (with its 3D ear contours) in a room."""

    def __init__(self, subject, contours: dict[str, np.ndarray], room=None):
        from facecap_core.synthetic import Renderer

        self.subject = subject
        self.contours = contours
        self.hair: HairAroundEars | None = None
        placeholder = Intrinsics(8, 8, 8.0, 8.0, 3.5, 3.5)
        self.renderer = Renderer(subject, room, placeholder, [], 0.35, 0.05)
        self.head_scene = RaycastScene()
        self.head_scene.add(subject.vertices, subject.faces)
        w = np.abs(subject.landmarks[[0, 16], 0]).mean()
        # The orbit centre of the synthetic captures: the camera circles the head, not the ear.
        self.orbit_centre = np.array([0.0, subject.landmarks[27, 1] * 0.5, 0.3 * w])

    def view(self, side: str, yaw_deg: float, elevation_deg: float, roll_deg: float,
             distance_mm: float, ear_height_px: float, size: int, rng: np.random.Generator,
             aspect: float = 0.75, padding: float = 0.15, look_jitter: float = 0.35
             ) -> EarSample:
        """The camera and ground truth of one view, without the image (cheap).

        The camera is on ``side`` at ``yaw_deg`` from the face's front around the head,
        ``distance_mm`` from the orbit centre, pointed near the ear, with the focal length
        that makes the ear contour about ``ear_height_px`` tall."""
        contour = self.contours[side]
        s = SIDE_SIGN[side]
        yaw, elev = np.radians(yaw_deg), np.radians(elevation_deg)
        direction = np.array([s * np.sin(yaw) * np.cos(elev), np.sin(elev),
                              np.cos(yaw) * np.cos(elev)])
        eye = self.orbit_centre + distance_mm * direction
        ear_centre = contour.mean(0)
        ear_size = np.ptp(contour[:, 1])
        dist_to_ear = np.linalg.norm(ear_centre - eye)
        focal = ear_height_px * dist_to_ear / max(ear_size, 1e-6)
        # Point the camera so that the ear lands anywhere in the image where its box fits
        # (large ears are not rejected more often than small ones).
        R, _ = look_at(eye, ear_centre, [0.0, 1.0, 0.0])
        box_h = ear_height_px * (1 + 2 * padding)
        room_px = np.maximum(0.0, (size - np.array([box_h * aspect, box_h])) / 2 - 4)
        shift = rng.uniform(-1, 1, 2) * np.minimum(room_px, look_jitter * size) / focal
        target = ear_centre + dist_to_ear * (R[0] * shift[0] + R[1] * shift[1])
        R, _ = look_at(eye, target, [0.0, 1.0, 0.0])
        R = rotation_matrix([0, 0, 1], np.radians(roll_deg)) @ R
        t = -R @ eye
        intr = Intrinsics(size, size, focal, focal, (size - 1) / 2, (size - 1) / 2)
        uv, _ = project(contour, R, t, intr)
        vis = visible_points(self.head_scene, eye, contour)
        sample = EarSample(None, uv, vis, ear_box(uv, aspect, padding),
                           tuple(np.concatenate([uv.min(0), uv.max(0)])), side,
                           float(yaw_deg), False)
        sample.camera = (intr, R, t, eye, direction)
        return sample

    def render(self, sample: EarSample, rng: np.random.Generator, mirror_right: bool = True,
               realism: bool = True, hair_probability: float = 0.0) -> EarSample:
        """Draw the image of a :meth:`view` (mirrored to a left-ear view for a right ear
        when ``mirror_right``): shading, exposure, noise, blur and JPEG compression, and
        with ``hair_probability`` hair painted around the ears (:class:`HairAroundEars`)."""
        intr, R, t, eye, direction = sample.camera
        if hair_probability > 0:
            if self.hair is None:
                self.hair = HairAroundEars(self.subject, self.contours, rng)
                self.subject.albedo = self.hair
            if rng.uniform() < hair_probability:
                self.hair.draw(rng)
            else:
                self.hair.clear()
        lin = self._shade(intr, R, t, eye, direction, rng)
        if realism:
            lin = lin * rng.uniform(0.7, 1.3)
            sigma = np.sqrt(rng.uniform(0.003, 0.012) ** 2
                            + rng.uniform(0.005, 0.02) ** 2 * np.clip(lin, 0, 1))
            lin = lin + sigma * rng.standard_normal(lin.shape)
        img = _to_srgb8(lin)
        if realism:
            blur = rng.uniform(0.0, 1.2)
            if blur > 0.3:
                img = cv2.GaussianBlur(img, (0, 0), blur)
            quality = int(rng.integers(60, 96))
            _, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, quality])
            img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
        sample.image = img
        if mirror_right and sample.side == "right":
            w = intr.width
            sample.image = img[:, ::-1].copy()
            sample.points = np.stack([w - 1 - sample.points[:, 0], sample.points[:, 1]], 1)
            l, top, r, b = sample.box
            sample.box = (w - 1 - r, top, w - 1 - l, b)
            l, top, r, b = sample.tight_box
            sample.tight_box = (w - 1 - r, top, w - 1 - l, b)
            sample.mirrored = True
        return sample

    def _shade(self, intr, R, t, eye, view_dir, rng) -> np.ndarray:
        r = self.renderer
        r.intrinsics = intr
        r.rays = pixel_rays(intr)
        r.lights = _lights(rng, view_dir)
        r.ambient = rng.uniform(0.2, 0.45)
        r.specular = rng.uniform(0.0, 0.08)
        img, _ = r.render(R, t)
        return img


def ict_ear_renderer(ict_model: str | Path, seed: int, transfer: dict[str, SurfacePoints],
                     sigma: float = 1.0, room=None) -> EarRenderer:
    """An :class:`EarRenderer` for the ICT identity ``seed`` (contours from ``transfer``)."""
    from facecap_core.synthetic import ict_subject

    subject = ict_subject(ict_model, seed, sigma)
    contours = {side: sp.on(subject.vertices) for side, sp in transfer.items()}
    return EarRenderer(subject, contours, room)


def draw_views(config: EarTrainingConfig, count: int, rng: np.random.Generator) -> list[dict]:
    """Random view parameters (side, yaw, elevation, roll, distance, ear size)."""
    views = []
    for _ in range(count):
        views.append({
            "side": SIDES[int(rng.integers(2))],
            "yaw_deg": float(rng.uniform(*config.yaw_deg)),
            "elevation_deg": float(rng.uniform(*config.elevation_deg)),
            "roll_deg": float(rng.uniform(-config.roll_deg, config.roll_deg)),
            "distance_mm": float(rng.uniform(*config.distance_mm)),
            "ear_height_px": float(rng.uniform(*config.ear_height_px)),
        })
    return views


def usable(sample: EarSample, size: int, min_visible: float) -> bool:
    """A training view: the box inside the image and most of the contour visible."""
    l, t, r, b = sample.box
    return l >= 0 and t >= 0 and r < size and b < size and sample.visible.mean() >= min_visible


def render_dataset(config: EarTrainingConfig, ict_model: str | Path,
                   transfer: dict[str, SurfacePoints], progress: bool = True
                   ) -> list[EarSample]:
    """The training views: ``identities`` x ``views_per_identity`` (left-ear orientation)."""
    from tqdm import tqdm

    from facecap_core.synthetic import Room

    rooms = [Room.random(np.random.default_rng([config.seed, 7, k])) for k in range(config.rooms)]
    samples: list[EarSample] = []
    seeds = range(config.first_identity_seed, config.first_identity_seed + config.identities)
    for n, seed in enumerate(tqdm(seeds, desc="render ears", unit="head", disable=not progress)):
        rng = np.random.default_rng([config.seed, seed])
        renderer = ict_ear_renderer(ict_model, seed, transfer, config.identity_sigma,
                                    rooms[n % len(rooms)])
        kept = 0
        for _ in range(config.views_per_identity * 10):
            if kept == config.views_per_identity:
                break
            view = draw_views(config, 1, rng)[0]
            sample = renderer.view(**view, size=config.image_size, rng=rng,
                                   aspect=config.box_aspect, padding=config.box_padding)
            if usable(sample, config.image_size, config.min_visible_fraction):
                renderer.render(sample, rng, hair_probability=config.hair_probability)
                sample.image = _grey(sample.image)  # training uses grey; a quarter the memory
                samples.append(sample)
                kept += 1
    return samples


# -- training -------------------------------------------------------------------------------------


TRAINING_ONLY_FIELDS = ("detector_", "predictor_", "threads")


def render_key(config: EarTrainingConfig) -> str:
    """Hash of the settings that change the rendered training set (not the training ones)."""
    fields = {k: v for k, v in config.model_dump(mode="json").items()
              if not k.startswith(TRAINING_ONLY_FIELDS) and k != "ict_model"}
    return hashlib.sha256(json.dumps(fields, sort_keys=True).encode()).hexdigest()[:16]


def save_dataset(path: Path, samples: list[EarSample], key: str) -> Path:
    """The rendered views (grey images, points, visibility, boxes) as one ``.npz``."""
    np.savez_compressed(
        path, key=key, images=np.stack([_grey(s.image) for s in samples]),
        points=np.stack([s.points for s in samples]),
        visible=np.stack([s.visible for s in samples]),
        boxes=np.array([s.box for s in samples]),
        tight_boxes=np.array([s.tight_box for s in samples]),
        sides=np.array([s.side for s in samples]), yaws=np.array([s.yaw_deg for s in samples]))
    return path


def load_dataset(path: Path, key: str) -> list[EarSample] | None:
    """The views saved by :func:`save_dataset`, or None when missing or rendered otherwise."""
    if not path.is_file():
        return None
    with np.load(path) as z:
        if str(z["key"]) != key:
            return None
        return [EarSample(img, pts, vis, tuple(int(v) for v in box), tuple(tb), str(side),
                          float(yaw), True)
                for img, pts, vis, box, tb, side, yaw in zip(
                    z["images"], z["points"], z["visible"], z["boxes"], z["tight_boxes"],
                    z["sides"], z["yaws"])]




def _grey(img: np.ndarray) -> np.ndarray:
    return img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)


def iou(a, b) -> float:
    l, t = max(a[0], b[0]), max(a[1], b[1])
    r, btm = min(a[2], b[2]), min(a[3], b[3])
    inter = max(0, r - l) * max(0, btm - t)
    area = lambda x: max(0, x[2] - x[0]) * max(0, x[3] - x[1])  # noqa: E731
    union = area(a) + area(b) - inter
    return inter / union if union > 0 else 0.0


def train_detector(samples: list[EarSample], config: EarTrainingConfig, progress: bool):
    import dlib

    options = dlib.simple_object_detector_training_options()
    options.add_left_right_image_flips = False  # the model is for left-ear views only
    options.C = config.detector_c
    options.epsilon = config.detector_epsilon
    options.detection_window_size = int(config.detector_window_px ** 2 * config.box_aspect)
    options.num_threads = config.threads
    options.upsample_limit = 0
    options.be_verbose = progress
    images = [_grey(s.image) for s in samples]
    boxes = [[dlib.rectangle(*s.box)] for s in samples]
    return dlib.train_simple_object_detector(images, boxes, options)


def predictor_boxes(detector, samples: list[EarSample]) -> tuple[list, int]:
    """The detector's box where it finds the ear (IoU >= 0.5), else the ground-truth box."""
    import dlib

    out, found = [], 0
    for s in samples:
        dets = detector(_grey(s.image))
        best = max(dets, key=lambda r: iou((r.left(), r.top(), r.right(), r.bottom()), s.box),
                   default=None)
        if best is not None and iou((best.left(), best.top(), best.right(), best.bottom()),
                                    s.box) >= 0.5:
            out.append(best)
            found += 1
        else:
            out.append(dlib.rectangle(*s.box))
    return out, found


def train_predictor(samples: list[EarSample], boxes: list, config: EarTrainingConfig,
                    progress: bool):
    import dlib

    options = dlib.shape_predictor_training_options()
    options.cascade_depth = config.predictor_cascade_depth
    options.tree_depth = config.predictor_tree_depth
    options.num_trees_per_cascade_level = config.predictor_trees_per_level
    options.nu = config.predictor_nu
    options.oversampling_amount = config.predictor_oversampling
    options.oversampling_translation_jitter = config.predictor_translation_jitter
    options.feature_pool_size = config.predictor_feature_pool_size
    options.num_test_splits = config.predictor_test_splits
    options.num_threads = config.threads
    options.random_seed = str(config.seed)
    options.be_verbose = progress
    images = [_grey(s.image) for s in samples]
    objects = [[dlib.full_object_detection(box, [dlib.point(int(round(x)), int(round(y)))
                                                 for x, y in s.points])]
               for s, box in zip(samples, boxes)]
    return dlib.train_shape_predictor(images, objects, options)


def score_detection(sample: EarSample, detection, min_iou: float = 0.5) -> dict:
    """Compare a detection (an ``EarDetection`` or None) with a view's ground truth.

    ``detected``: a box overlapping the ground-truth box with IoU >= ``min_iou``; ``nme``:
    mean distance of the visible contour points to the truth over the diagonal of the
    truth's tight bounding box (nan when not detected)."""
    if detection is None:
        return {"detected": False, "iou": 0.0, "nme": float("nan")}
    overlap = iou(detection.box, sample.box)
    err = np.linalg.norm(np.asarray(detection.points) - sample.points, axis=1)
    vis = sample.visible if sample.visible.any() else np.ones(len(err), bool)
    detected = overlap >= min_iou
    return {"detected": bool(detected), "iou": float(overlap),
            "nme": float(err[vis].mean() / sample.diagonal) if detected else float("nan")}


def sha256(path: str | Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def save_previews(samples: list[EarSample], folder: Path, count: int = 8) -> list[Path]:
    """Overlay PNGs of a few training views (box, contour, hidden points hollow)."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    step = max(1, len(samples) // count)
    for k, s in enumerate(samples[::step][:count]):
        img = cv2.cvtColor(s.image, cv2.COLOR_GRAY2BGR if s.image.ndim == 2 else
                           cv2.COLOR_RGB2BGR)
        draw_contour(img, s.points, s.visible, (0, 0, 255))
        cv2.rectangle(img, s.box[:2], s.box[2:], (0, 255, 0), 1)
        path = folder / f"train_{k:02d}_{s.side}_yaw{s.yaw_deg:.0f}.png"
        cv2.imwrite(str(path), img)
        paths.append(path)
    return paths


def draw_contour(img: np.ndarray, points: np.ndarray, visible: np.ndarray | None,
                 colour: tuple[int, int, int]) -> None:
    pts = np.round(points).astype(np.int32)
    cv2.polylines(img, [pts.reshape(-1, 1, 2)], False, colour, 1, cv2.LINE_AA)
    for i, p in enumerate(pts):
        filled = -1 if visible is None or visible[i] else 1
        cv2.circle(img, tuple(int(v) for v in p), 2, colour, filled, cv2.LINE_AA)


def train(out_dir: str | Path, config: EarTrainingConfig | None = None,
          progress: bool = True) -> Path:
    """Render the training set and train the ear detector and predictor into ``out_dir``.

    Writes ``ear_contour.json``, ``ear_detector.svm``, ``ear_predictor.dat``,
    ``training.json`` (config, counts, timings, sha256 of the model files),
    ``dataset.npz`` (the renders, reused by a later run with the same rendering settings)
    and ``previews/*.png``; returns ``out_dir``.
    """
    config = config or EarTrainingConfig()
    ict_model = config.ict_model or os.environ.get("FACECAP_ICT_MODEL")
    if not ict_model:
        raise InputError("ear training needs the ICT Face Model: set ict_model or "
                         "FACECAP_ICT_MODEL to PATH/ict_face_model.npz")
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create output folder {out}: {exc.strerror}") from None
    wall0, cpu0 = time.perf_counter(), time.process_time()
    timings: dict[str, dict] = {}
    last = [wall0, cpu0]

    def lap(name: str) -> None:
        w, c = time.perf_counter(), time.process_time()
        timings[name] = {"wall_s": round(w - last[0], 2), "cpu_s": round(c - last[1], 2)}
        last[:] = [w, c]

    write_contour_file(out / CONTOUR_FILE, config, ict_model)
    transfer = load_contour_file(out / CONTOUR_FILE)["ict"]
    lap("contour_fit")
    # The renders are kept (``dataset.npz``) so that retraining with other detector or
    # predictor settings does not render again.
    key = render_key(config)
    samples = load_dataset(out / "dataset.npz", key)
    if samples is None:
        samples = render_dataset(config, ict_model, transfer, progress)
        if not samples:
            raise InputError("no usable ear views were rendered: widen the view ranges")
        save_previews(samples, out / "previews")
        save_dataset(out / "dataset.npz", samples, key)
    lap("render")
    detector = train_detector(samples, config, progress)
    detector.save(str(out / DETECTOR_FILE))
    lap("detector")
    boxes, found = predictor_boxes(detector, samples)
    lap("detector_on_training_set")
    predictor = train_predictor(samples, boxes, config, progress)
    predictor.save(str(out / PREDICTOR_FILE))
    lap("predictor")
    report = {
        "config": config.model_dump(mode="json"),
        "samples": len(samples),
        "samples_per_side": {s: sum(x.side == s for x in samples) for s in SIDES},
        "detector_training_recall": found / len(samples),
        "timings": timings,
        "total": {"wall_s": round(time.perf_counter() - wall0, 1),
                  "cpu_s": round(time.process_time() - cpu0, 1)},
        "sha256": {name: sha256(out / name) for name in MODEL_FILES},
        "bytes": {name: (out / name).stat().st_size for name in MODEL_FILES},
    }
    (out / "training.json").write_text(json.dumps(report, indent=1))
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m facecap_core.landmarks.ear_training",
        description="Render ICT heads and train the ear detector + ear contour predictor.")
    parser.add_argument("--out", required=True, help="output folder for the model files")
    parser.add_argument("--config", help="EarTrainingConfig YAML (defaults otherwise)")
    parser.add_argument("--quiet", action="store_true", help="no progress output")
    args = parser.parse_args(argv)
    from facecap_core.config import load_yaml
    from facecap_core.errors import FacecapError

    try:
        config = load_yaml(EarTrainingConfig, args.config) if args.config else EarTrainingConfig()
        out = train(args.out, config, progress=not args.quiet)
    except FacecapError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    report = json.loads((out / "training.json").read_text())
    print(json.dumps({"out": str(out), "samples": report["samples"], "total": report["total"],
                      "sha256": report["sha256"]}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
