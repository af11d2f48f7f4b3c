"""An own iris localisation, measured against MediaPipe's by ``bench_iris.py`` (the pipeline
uses MediaPipe): the iris's centre and horizontal radius, found near the eye's six 68-point
landmarks.

The limbus — the border between the dark iris and the bright sclera — is a circle. Its left
and right arcs are seldom hidden by the eyelids, so a circle is fitted to them alone: the
centre and radius that maximise the mean intensity step across the circle (outside minus
inside) on two arcs of ``±ARC_DEG`` around the eye's horizontal axis (Daugman's
integro-differential operator on the lateral arcs). A coarse grid over the eye opening, then
a continuous refinement (bilinear samples) give sub-pixel centre and radius.

A fit is refused (None) when the eye is too small in the image, or when either arc's step is
weak — a closed or half-closed eye, a reflection, a blur — compared with the sclera's
brightness (``min_contrast``).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage
from scipy.optimize import minimize

__all__ = ["IrisFit", "fit_iris", "RIGHT_EYE", "LEFT_EYE"]

RIGHT_EYE = np.arange(36, 42)  # the subject's right eye (image left in a frontal view)
LEFT_EYE = np.arange(42, 48)
ARC_DEG = 40.0
MIN_EYE_WIDTH_PX = 12.0


@dataclass
class IrisFit:
    """One iris: centre (x, y) in pixels, horizontal radius in pixels, and the weaker of its
    two arcs' intensity steps relative to the brightness just outside them."""

    centre: np.ndarray
    radius: float
    contrast: float

    def as_dict(self) -> dict:
        return {"centre": [round(float(c), 3) for c in self.centre],
                "radius_px": round(float(self.radius), 4),
                "contrast": round(float(self.contrast), 4)}


def _grey(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image, np.float32)
    if img.ndim == 3:
        img = img[..., :3] @ np.array([0.299, 0.587, 0.114], np.float32)
    return img


def _sample(grey: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear samples at pixel coordinates (x, y), edge pixels repeated outside."""
    return ndimage.map_coordinates(grey, [y, x], order=1, mode="nearest")


class _LateralArcs:
    """Intensity steps across circles of candidate centres and radii on the lateral arcs, in
    the eye's own frame (``u`` along the corner-to-corner axis, ``v`` across it)."""

    def __init__(self, grey: np.ndarray, origin: np.ndarray, u: np.ndarray, step_px: float):
        self.grey, self.origin, self.u = grey, origin, u
        self.v = np.array([-u[1], u[0]])
        a = np.deg2rad(np.linspace(-ARC_DEG, ARC_DEG, 9))
        # (2 sides, angles, 2): unit directions in the eye frame, right arc then left arc.
        self.dirs = np.stack([np.stack([np.cos(a), np.sin(a)], -1),
                              np.stack([-np.cos(a), np.sin(a)], -1)])
        self.step = step_px

    def steps(self, centres: np.ndarray, radii: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 2) mean step (outside - inside) per arc and (N, 2) mean outside brightness for
        N candidates ``centres`` (N, 2) (eye frame) and ``radii`` (N,)."""
        c = np.asarray(centres, float)[:, None, None, None, :]
        r = np.asarray(radii, float)[:, None, None, None, None]
        # Bands of three samples each side: a wide band outside the true limbus is sclera,
        # outside the pupil's edge it is still iris (a narrow step would take either).
        k = self.step * np.arange(1, 4)[:, None, None, None]
        d = self.dirs[None, None]

        def image_xy(uv):
            return self.origin + uv[..., :1] * self.u + uv[..., 1:] * self.v

        outside = self._at(image_xy(c + (r + k) * d)).mean(1)
        inside = self._at(image_xy(c + (r - k) * d)).mean(1)
        return (outside - inside).mean(-1), outside.mean(-1)

    def _at(self, xy: np.ndarray) -> np.ndarray:
        return _sample(self.grey, xy[..., 0], xy[..., 1])


def fit_iris(image: np.ndarray, eye_points: np.ndarray, min_contrast: float = 0.08,
             start: tuple[np.ndarray, float] | None = None) -> IrisFit | None:
    """The iris of the eye whose six 68-point landmarks (corner, two upper lid points,
    corner, two lower lid points) are ``eye_points`` (6, 2) in ``image`` (RGB or grey);
    None when the eye is too small, closed or the limbus too faint."""
    pts = np.asarray(eye_points, float)
    if pts.shape != (6, 2) or not np.all(np.isfinite(pts)):
        return None
    axis = pts[3] - pts[0]
    width = float(np.linalg.norm(axis))
    if width < MIN_EYE_WIDTH_PX:
        return None
    u = axis / width
    if u[0] < 0:  # u points along +x of the image, whatever the corners' order
        u = -u
    origin = pts.mean(0)
    # Crop around the eye, lightly smoothed so that the bilinear samples vary smoothly.
    margin = 0.6 * width
    x0, y0 = np.floor(pts.min(0) - margin).astype(int)
    x1, y1 = np.ceil(pts.max(0) + margin).astype(int)
    h, w = image.shape[:2]
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
    if x1 - x0 < 8 or y1 - y0 < 8:
        return None
    grey = cv2.GaussianBlur(_grey(image[y0:y1, x0:x1]), (0, 0), max(0.5, width / 80))
    arcs = _LateralArcs(grey, origin - [x0, y0], u, max(0.7, width / 40))

    # Coarse grid: the iris centre inside the opening, its radius 0.12-0.32 eye widths
    # (an adult's iris is ~0.4 of the palpebral fissure's width, ~0.2 of it in radius).
    du = np.linspace(-0.25, 0.25, 21) * width
    dv = np.linspace(-0.15, 0.15, 11) * width
    radii = np.linspace(0.12, 0.32, 21) * width
    if start is not None:  # a search near a given centre (x, y) and radius
        c0 = np.asarray(start[0], float) - origin
        r0 = float(start[1])
        du = c0 @ u + np.linspace(-0.25, 0.25, 11) * r0
        dv = c0 @ np.array([-u[1], u[0]]) + np.linspace(-0.25, 0.25, 11) * r0
        radii = np.linspace(0.8, 1.2, 17) * r0
    U, Vv, Rr = np.meshgrid(du, dv, radii, indexing="ij")
    cand = np.stack([U.ravel(), Vv.ravel()], -1)
    step, _ = arcs.steps(cand, Rr.ravel())
    score = step.min(1)
    best = int(np.argmax(score))
    x_start = np.r_[cand[best], Rr.ravel()[best]]

    def cost(p):
        s, _ = arcs.steps(p[None, :2], np.array([p[2]]))
        return -float(s.min())  # the weaker arc: both must sit on the limbus

    res = minimize(cost, x_start, method="Nelder-Mead",
                   options={"xatol": 0.01, "fatol": 1e-3, "initial_simplex":
                            x_start + np.vstack([np.zeros(3), np.eye(3) * 0.02 * width])})
    centre_uv, radius = res.x[:2], float(res.x[2])
    if not (0.1 * width <= radius <= 0.35 * width):
        return None
    step, outside = arcs.steps(centre_uv[None], np.array([radius]))
    contrast = float(np.min(step[0] / np.maximum(outside[0], 1e-6)))
    if contrast < min_contrast:
        return None
    centre = origin + centre_uv[0] * u + centre_uv[1] * arcs.v
    return IrisFit(centre, radius, contrast)

