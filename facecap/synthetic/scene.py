"""What surrounds the subject and how things move: the room, the hand-held camera path and
the head's sway."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import trimesh
from scipy import ndimage

from facecap.synthetic.config import SynthConfig
from facecap_core.camera import (
    look_at,
    rotation_matrix,
)


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
