"""Rendered training samples of ears: varied heads, skin, hair, light and views."""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from facecap.ear_training.config import EarTrainingConfig
from facecap.ear_training.contour import (
    SIDE_SIGN,
    SIDES,
    SurfacePoints,
)
from facecap.synthetic import HAIR_COLOURS, Renderer, Room, SolidNoise, ict_subject
from facecap.synthetic.sensor import to_srgb8
from facecap.synthetic.subjects import smoothstep
from facecap_core.camera import Intrinsics, look_at, pixel_rays, project, rotation_matrix
from facecap_core.render import RaycastScene, interpolate
from facecap_core.template import region_masks


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




class HairAroundEars:
    """Random hair painted (texture only, as on a scanned head) around the ears.

    The ICT renders keep the temples and ears bare; real heads (and the James scan) frame
    the ear with hair, which changes the ear's outline contrast. Per view, each side gets
    hair beyond a random straight hairline in the side plane (above and/or behind the ear,
    sometimes over its top), with a wavy edge and strands.
    """

    def __init__(self, subject, contours: dict[str, np.ndarray], rng: np.random.Generator):
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
            w = smoothstep(across - offset + wavy, -1.5, 1.5)
            w *= np.sign(P[:, 0]) == SIDE_SIGN[side]
            if rng.uniform() < 0.75:
                w[self.ear_mask] = 0.0  # the ear itself stays bare most of the time
            weight = np.maximum(weight, w)
        self.weight = weight
        self.colour = HAIR_COLOURS[rng.integers(len(HAIR_COLOURS))] * rng.uniform(0.7, 1.5)

    def clear(self) -> None:
        self.weight = np.zeros(len(self.subject.vertices))

    def __call__(self, tri: np.ndarray, bary: np.ndarray, points: np.ndarray) -> np.ndarray:
        rgb = self.base_albedo(tri, bary, points)
        w = interpolate(self.weight[:, None], self.subject.faces, tri, bary)[:, 0]
        if not np.any(w > 0):
            return rgb
        strands = smoothstep(self.noise(points, 0.6, 6, stretch=(1.0, 6.0, 1.0)), -0.3, 0.6)
        hair = self.colour * (0.7 + 0.5 * strands)[:, None]
        w = w[:, None] * (0.85 + 0.15 * strands[:, None])
        return rgb * (1 - w) + hair * w


class EarRenderer:
    """Renders ear views of one subject (with its 3D ear contours) in a room."""

    def __init__(self, subject, contours: dict[str, np.ndarray], room=None):
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
        img = to_srgb8(lin)
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
                sample.image = grey(sample.image)  # training uses grey; a quarter the memory
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
        path, key=key, images=np.stack([grey(s.image) for s in samples]),
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


def grey(img: np.ndarray) -> np.ndarray:
    return img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
