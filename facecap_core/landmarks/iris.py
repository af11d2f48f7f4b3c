"""The irises in an image: each pupil's centre and the iris's horizontal diameter in pixels.

They come from the face detection's mesh (:mod:`facecap_core.face`: MediaPipe's face mesh with
iris refinement, 478 points): 468 and 473 are the centres of the subject's right and left
iris, 469/471 and 474/476 their horizontal edges. The pupil is then refined, along the eye's
axis, to the centroid of the dark pixels around MediaPipe's centre (:func:`pupil_centre`).

Against the renderer's truth (``benchmarks/bench_iris.py``, views within 15° of frontal at
640x360, irises ~12 px wide): pupil error 0.67 px median (MediaPipe's own centre: 1.0 px),
diameter error 5.4 % RMS per eye. An own limbus fit near the eye points did worse (see
docs/landmarks.md, "Metric scale").

An eye is refused when it is not open enough (the mesh's lid points: their mean distance over
the corner-to-corner width below ``min_eye_opening``), when the iris centre lies outside the
eye's outline, or when the diameter is implausible for the eye's width.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from facecap_core.camera import CameraSet, camera_center
from facecap_core.face import Detection
from facecap_core.landmarks.config import LandmarkConfig
from facecap_core.landmarks.triangulate import box_size, triangulate

__all__ = ["IrisFit", "detect_irises", "eye_opening", "pupil_centre", "RIGHT_EYE",
           "LEFT_EYE", "DETECTOR"]

RIGHT_EYE = np.arange(36, 42)  # the subject's right eye (image left in a frontal view)
LEFT_EYE = np.arange(42, 48)
# MediaPipe's iris points: centre, then the subject's right/top/left/bottom edge... per side.
_MESH_IRIS = {"right": (468, 469, 471), "left": (473, 474, 476)}
# MediaPipe's lid points per eye: outer corner, two upper-lid points, inner corner, two
# lower-lid points (the usual eye-aspect-ratio sextuple; for the left eye iBUG's order runs
# the other way, from the inner corner).
_MESH_LIDS = {"right": (33, 160, 158, 133, 153, 144), "left": (263, 387, 385, 362, 380, 373)}
DETECTOR = ("MediaPipe face mesh with iris refinement (478 points); pupils refined along the "
            "eye's axis to the dark centroid")
# An adult's visible iris is 0.35-0.5 of the eye's corner-to-corner width.
_DIAMETER_OVER_WIDTH = (0.25, 0.65)


@dataclass
class IrisFit:
    """One iris: its centre (x, y) and horizontal diameter in pixels, and the eye's opening."""

    centre: np.ndarray
    diameter: float
    opening: float

    def as_dict(self) -> dict:
        return {"centre": [round(float(c), 3) for c in self.centre],
                "diameter_px": round(float(self.diameter), 4),
                "opening": round(float(self.opening), 4)}


def eye_opening(eye_points: np.ndarray) -> float:
    """Mean distance between the upper and lower lid points of an eye's six 68-point
    landmarks over its corner-to-corner width (~0.3 open, below ~0.15 closed)."""
    p = np.asarray(eye_points, float)
    width = np.linalg.norm(p[3] - p[0])
    return float((np.linalg.norm(p[1] - p[5]) + np.linalg.norm(p[2] - p[4])) / (2 * width))


def pupil_centre(image: np.ndarray, start: np.ndarray, iris_radius: float,
                 axis: np.ndarray | None = None, iterations: int = 3) -> np.ndarray:
    """The pupil's centre near ``start``: the centroid of the pixels darker than midway
    between the darkest and the brightest within half the iris radius (weighted by how much
    darker), on a quarter-pixel grid of bilinear samples, re-centred ``iterations`` times.

    With ``axis`` (the eye's corner-to-corner direction) it moves along that axis only:
    across it, the upper lid's shadow on a dark iris pulls the centroid up, and the scale
    cues need the pupils' separation, which lies along the axis. Corneal reflections are
    removed first (a grey opening with a disk of about half the iris radius erases bright
    spots smaller than it, which would otherwise push the centroid away from them); a window
    without contrast (all pupil, or an iris too dark to show one) stays where it is."""
    c = np.asarray(start, float)
    u = None if axis is None else np.asarray(axis, float) / np.linalg.norm(axis)
    h, w = image.shape[:2]
    half = int(np.ceil(1.5 * iris_radius)) + 2
    x0, y0 = max(0, int(c[0]) - half), max(0, int(c[1]) - half)
    x1, y1 = min(w, int(c[0]) + half + 1), min(h, int(c[1]) + half + 1)
    if x1 - x0 < 3 or y1 - y0 < 3:
        return c
    img = np.asarray(image[y0:y1, x0:x1], np.float32)
    grey = img[..., :3] @ np.array([0.299, 0.587, 0.114], np.float32) if img.ndim == 3 else img
    k = 2 * max(1, int(round(iris_radius / 4))) + 1
    grey = cv2.morphologyEx(grey, cv2.MORPH_OPEN,
                            cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
    r = 0.5 * iris_radius
    g = np.arange(-r, r + 1e-9, 0.25)
    X, Y = np.meshgrid(g, g)
    inside = X ** 2 + Y ** 2 <= r * r
    dx, dy = X[inside], Y[inside]
    for _ in range(iterations):
        vals = ndimage.map_coordinates(grey, [c[1] - y0 + dy, c[0] - x0 + dx], order=1,
                                       mode="nearest")
        dark, bright = np.percentile(vals, [2, 98])
        if bright - dark < 8.0:  # no pupil edge in the window (8 grey levels of 255)
            break
        weights = np.clip(0.5 * (dark + bright) - vals, 0, None)
        step = np.array([weights @ dx, weights @ dy]) / weights.sum()
        c = c + (step if u is None else (step @ u) * u)
    return c


def _inside(point: np.ndarray, polygon: np.ndarray) -> bool:
    return cv2.pointPolygonTest(polygon.astype(np.float32), tuple(map(float, point)), False) >= 0


def detect_irises(image: np.ndarray, detection: Detection, min_eye_opening: float = 0.2,
                  refine_pupil: bool = True) -> dict[str, IrisFit]:
    """The irises ({"right", "left"}: :class:`IrisFit`) of a detected face in an RGB uint8
    ``image``; an eye that is refused is missing. Without ``refine_pupil`` the centre is
    MediaPipe's own."""
    mesh = detection.mesh
    found = {}
    for side, ids in (("right", RIGHT_EYE), ("left", LEFT_EYE)):
        eye = np.asarray(detection.points, float)[ids]
        lids = mesh[list(_MESH_LIDS[side])]
        centre, a, b = mesh[list(_MESH_IRIS[side])]
        diameter = float(np.linalg.norm(a - b))
        width = float(np.linalg.norm(lids[3] - lids[0]))
        opening = eye_opening(lids)
        if (opening < min_eye_opening or not _inside(centre, eye)
                or not _DIAMETER_OVER_WIDTH[0] <= diameter / width <= _DIAMETER_OVER_WIDTH[1]):
            continue
        if refine_pupil:
            centre = pupil_centre(image, centre, 0.5 * diameter, lids[3] - lids[0])
        if not _inside(centre, eye):
            continue
        found[side] = IrisFit(centre, diameter, opening)
    return found


def triangulate_irises(dets: list, records: list[dict], gated: list[int],
                       cams: CameraSet, head_R: np.ndarray, config: LandmarkConfig) -> dict:
    """Pupil centres triangulated over the gated keyframes within ``iris_max_yaw_deg`` of
    frontal, and the horizontal iris diameter in world units: each view's pixel diameter
    times the pupil's depth over the focal length, undone of the foreshortening of an iris
    that looks along the head's +z (cos of the view's yaw at that eye); the median over views
    and eyes."""
    doc = {"detector": DETECTOR, "units": cams.units,
           "views": [], "pupils": {"right": None, "left": None}, "pupil_distance": None,
           "iris_diameter": None, "iris_diameter_spread_rel": None, "iris_diameter_views": [],
           "reason": None}
    if not config.irises:
        doc["reason"] = "iris measurement is off (LandmarkConfig.irises)"
        return doc
    views = [k for k in gated if abs(records[k]["yaw_deg"]) <= config.iris_max_yaw_deg
             and dets[k].irises]
    doc["views"] = [cams.frame_indices[k] for k in views]
    if len(views) < 2:
        doc["reason"] = (f"irises measured in {len(views)} frontal keyframe(s) (|yaw| <= "
                         f"{config.iris_max_yaw_deg:g}°, eyes open); two or more are needed")
        return doc
    sides = ("right", "left")
    uv = np.full((len(views), 2, 2), np.nan)
    for v, k in enumerate(views):
        for j, side in enumerate(sides):
            if side in dets[k].irises:
                uv[v, j] = dets[k].irises[side].centre
    size = np.array([box_size(dets[k].box) for k in views])
    tri = triangulate(uv, cams.R[views], cams.t[views], cams.intrinsics,
                      config.outlier_threshold * size, config.huber * size, 2,
                      config.min_parallax_deg)
    focal = 0.5 * (cams.intrinsics.fx + cams.intrinsics.fy)
    diameters = []
    for j, side in enumerate(sides):
        P = tri.points[j]
        if not np.all(np.isfinite(P)):
            continue
        doc["pupils"][side] = [round(float(x), 6) for x in P]
        for v, k in enumerate(views):
            if not tri.inliers[v, j]:
                continue
            depth = float(cams.R[k][2] @ P + cams.t[k][2])
            to_camera = head_R @ (camera_center(cams.R[k], cams.t[k]) - P)
            cos_yaw = abs(to_camera[2]) / np.hypot(to_camera[0], to_camera[2])
            d = dets[k].irises[side].diameter * depth / focal / cos_yaw
            diameters.append(d)
            doc["iris_diameter_views"].append([cams.frame_indices[k], side, round(d, 6)])
    if all(p is not None for p in doc["pupils"].values()):
        doc["pupil_distance"] = float(np.linalg.norm(tri.points[0] - tri.points[1]))
    if len(diameters) >= 2:
        d = np.array(diameters)
        med = float(np.median(d))
        doc["iris_diameter"] = med
        doc["iris_diameter_spread_rel"] = round(float(1.4826 * np.median(np.abs(d - med)) / med),
                                                5)
    else:
        doc["reason"] = "fewer than two iris measurements agree with the triangulated pupils"
    return doc
