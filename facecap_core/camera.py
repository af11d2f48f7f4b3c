"""Pinhole camera with two-term radial distortion, and world-to-camera poses.

Conventions (the same everywhere in facecap, and OpenCV's):

* A pose is world-to-camera: ``x_cam = R @ x_world + t``; the camera looks down +z with
  +x right and +y down in the image. The camera centre is ``-R.T @ t``.
* Pixel coordinates put the centre of the top-left pixel at (0, 0). COLMAP puts it at
  (0.5, 0.5): add 0.5 to the principal point when exporting to COLMAP.
* Distortion acts on normalised coordinates ``(x, y) = (X/Z, Y/Z)``:
  ``(x, y) * (1 + k1 r^2 + k2 r^4)`` with ``r^2 = x^2 + y^2`` — OpenCV's model with
  ``dist = (k1, k2, 0, 0, 0)`` and COLMAP's RADIAL model.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

CAMERAS_JSON = "cameras.json"
"""The keyframe cameras of the pose stage (its own units) and of the coarse stage (mm)."""


@dataclass(frozen=True)
class Intrinsics:
    """Image size, focal lengths and principal point in pixels, radial distortion k1, k2."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist(self) -> np.ndarray:
        """OpenCV distortion vector (k1, k2, p1, p2, k3)."""
        return np.array([self.k1, self.k2, 0.0, 0.0, 0.0])

    @property
    def image_centre(self) -> np.ndarray:
        """The image's centre (x, y), px: pixel centres sit at integer coordinates."""
        return np.array([(self.width - 1) / 2, (self.height - 1) / 2])

    @property
    def horizontal_fov_deg(self) -> float:
        return float(np.degrees(2.0 * np.arctan(self.width / (2.0 * self.fx))))

    def scaled(self, width: int, height: int) -> Intrinsics:
        """The same camera at another image resolution (distortion is resolution-free)."""
        sx, sy = width / self.width, height / self.height
        # Pixel centres sit at integer coordinates, so the image edge is at -0.5.
        return Intrinsics(
            width, height, self.fx * sx, self.fy * sy,
            (self.cx + 0.5) * sx - 0.5, (self.cy + 0.5) * sy - 0.5, self.k1, self.k2,
        )

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> Intrinsics:
        return cls(**{k: d[k] for k in cls.__dataclass_fields__ if k in d})


def distort(xy: np.ndarray, k1: float, k2: float) -> np.ndarray:
    """Apply radial distortion to normalised coordinates (..., 2)."""
    r2 = np.sum(xy * xy, axis=-1, keepdims=True)
    return xy * (1.0 + k1 * r2 + k2 * r2 * r2)


def undistort(xy_d: np.ndarray, k1: float, k2: float, iterations: int = 30) -> np.ndarray:
    """Invert :func:`distort` by Newton's method on the radius (exact to ~1e-12 here)."""
    rd = np.linalg.norm(xy_d, axis=-1, keepdims=True)
    r = rd.copy()
    for _ in range(iterations):
        r2 = r * r
        f = r * (1.0 + k1 * r2 + k2 * r2 * r2) - rd
        df = 1.0 + 3.0 * k1 * r2 + 5.0 * k2 * r2 * r2
        r = r - f / df
    scale = np.where(rd > 1e-15, r / np.maximum(rd, 1e-300), 1.0)
    return xy_d * scale


def world_to_camera(points: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    return points @ np.asarray(R).T + np.asarray(t).reshape(1, 3)


def camera_center(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    return -np.asarray(R).T @ np.asarray(t).reshape(3)


def project(points: np.ndarray, R: np.ndarray, t: np.ndarray, intr: Intrinsics):
    """Project world points (N, 3) to distorted pixels (N, 2); also returns camera depth (N,)."""
    pc = world_to_camera(np.asarray(points, float), R, t)
    z = pc[:, 2]
    xy = pc[:, :2] / np.where(np.abs(z) > 1e-12, z, 1e-12)[:, None]
    xy = distort(xy, intr.k1, intr.k2)
    uv = np.stack([intr.fx * xy[:, 0] + intr.cx, intr.fy * xy[:, 1] + intr.cy], axis=1)
    return uv, z


def pixel_grid(intr: Intrinsics) -> np.ndarray:
    """Pixel-centre coordinates (H, W, 2) as (u, v)."""
    u, v = np.meshgrid(np.arange(intr.width, dtype=float), np.arange(intr.height, dtype=float))
    return np.stack([u, v], axis=-1)


def pixel_rays(intr: Intrinsics) -> np.ndarray:
    """Camera-frame ray directions (H, W, 3) with z = 1 through every (distorted) pixel centre.

    With z = 1, the distance along a ray is the pixel's depth.
    """
    uv = pixel_grid(intr)
    xy_d = np.stack([(uv[..., 0] - intr.cx) / intr.fx, (uv[..., 1] - intr.cy) / intr.fy], -1)
    xy = undistort(xy_d, intr.k1, intr.k2)
    return np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1)


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera (R, t) of a camera at ``eye`` looking at ``target``, ``up`` pointing up."""
    eye, target, up = (np.asarray(a, float).reshape(3) for a in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)  # image +x (right) for an image +y that points down
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ eye


def rotation_matrix(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """Rotation about a unit axis (Rodrigues)."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle_rad) * K + (1 - np.cos(angle_rad)) * (K @ K)


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Angle of the relative rotation between two rotation matrices, in degrees."""
    c = (np.trace(np.asarray(R_a) @ np.asarray(R_b).T) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


@dataclass
class CameraSet:
    """The cameras of a ``cameras.json`` as arrays (its file format:
    :mod:`facecap_core.pose.cameras_json`): one shared camera and every keyframe's
    world-to-camera pose."""

    intrinsics: Intrinsics
    frame_indices: list[int]
    R: np.ndarray  # (K, 3, 3)
    t: np.ndarray  # (K, 3)
    units: str = "arbitrary"
    """Units of t and of the world: ``mm`` after the coarse stage."""
    metric_scale: float | None = None
    """mm per pose-stage unit, once the coarse stage has scaled the cameras."""

    def pose(self, frame_index: int) -> tuple[np.ndarray, np.ndarray]:
        k = self.frame_indices.index(int(frame_index))
        return self.R[k], self.t[k]
