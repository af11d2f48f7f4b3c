"""Checks of the triangulated ear points before the scale or the fit may use them.

A side's points are kept only when

1. **enough of them triangulate** (``min_points`` of the contour's points);
2. **the views agree** on one 3-D contour: at least ``min_inlier_share`` of the side's
   observations reproject within the triangulation's inlier threshold (detections on hair,
   a collar or a wrong ear scatter and fail it);
3. **the ear sits where an ear can sit relative to the face**: the template is placed on the
   inner face landmarks by a similarity, and the offset of the measured contour from the
   template's contour (mean over the points, template millimetres, head frame) lies within
   ``EAR_OFFSET_BOUND`` of the offsets real head shapes have;
4. with both sides, **the ear-to-ear width** over the template's lies within
   ``EAR_WIDTH_RATIO_BOUNDS`` (a width outside them drops both sides: a wrong ear does more
   harm than a missing one).

The offsets' mean and spread and the width ratio's bounds were calibrated on 200 ICT Face
Model identities (seeds 1000-1199, each drawn with every mode at 1 sigma), none of which a
benchmark evaluates (``python tools/calibrate_ear_check.py`` prints them again). The
spread is widened (in quadrature) by ``EAR_NOISE_MM``, the error of a triangulated contour's
centroid (see there): all 200 calibration heads pass (largest normalised offset 3.2).
A side that fails is dropped, and the reason is reported in ``ears3d.json``, ``coarse.json``
and the run's report.
"""

from __future__ import annotations

import numpy as np

from facecap_core.geometry import robust_similarity
from facecap_core.template import INNER_LANDMARKS, Template, head_frame

EAR_OFFSET_MEAN_MM = {"left": np.array([-4.31, 2.16, 5.10]),
                      "right": np.array([3.11, 1.29, 5.05])}
"""Mean offset (x: the subject's left, y: up, z: forwards; template mm) of an ear's contour
from the contour of the template placed on the face landmarks, over the calibration heads."""
EAR_OFFSET_SPREAD_MM = {"left": np.array([3.88, 5.93, 4.74]),
                        "right": np.array([3.82, 5.95, 4.56])}
"""Standard deviation of that offset per axis over the calibration heads."""
EAR_NOISE_MM = 4.0
"""Measurement error of a triangulated contour's centroid per axis, added to the spread: the
predictor errs by about 0.04 of the ear box's diagonal (3.3 mm on a 50 mm ear) per point and
view; along a profile view, triangulated from views some 50 degrees apart, that is about
twice as much, and averaging 12 points whose errors are correlated (one box) keeps about half
of it."""
EAR_OFFSET_BOUND = 4.0
"""Largest normalised offset (the offset's distance from the mean, per axis over the widened
spread): the 99.9 % point of a 3-D normal distribution is 4.03."""
MIN_FACE_LANDMARKS = 6
"""Fewest finite inner face landmarks to place the template against the ears."""
EAR_WIDTH_RATIO_BOUNDS = (0.78, 1.13)
"""Ear-to-ear width over the template's: the calibration heads' mean 0.956 ± 4 standard
deviations (0.043); the heads themselves span 0.85-1.08."""


def placed_template(template: Template, landmarks: np.ndarray) -> tuple[float, np.ndarray,
                                                                        np.ndarray]:
    """The template's vertices placed on the inner landmarks by a robust similarity, its
    scale and rotation (template mm to the landmarks' units)."""
    L = np.asarray(landmarks, float)
    ok = np.all(np.isfinite(L[INNER_LANDMARKS]), axis=1)
    src = template.vertices[template.landmarks[INNER_LANDMARKS]][ok]
    s, R, t, _ = robust_similarity(src, L[INNER_LANDMARKS][ok])
    return s, R, s * template.vertices @ R.T + t


def contour_offsets(template: Template, landmarks: np.ndarray, ids: np.ndarray,
                    points: np.ndarray, sides: np.ndarray) -> tuple[dict, float | None]:
    """Per side, the mean offset (template mm, head frame: x the subject's left, y up, z
    forwards) of the measured contour ``points`` from the placed template's contour
    vertices ``ids``; and the ear-to-ear width over the template's (None without both)."""
    s, R, placed = placed_template(template, landmarks)
    frame, _ = head_frame(template.vertices[template.landmarks])
    offsets, centres = {}, {}
    for side in ("left", "right"):
        mine = sides == side
        if mine.any():
            offsets[side] = ((points[mine] - placed[ids[mine]]) @ R / s).mean(0) @ frame.T
            centres[side] = points[mine].mean(0), placed[ids[mine]].mean(0)
    ratio = None
    if len(centres) == 2:
        ratio = float(np.linalg.norm(centres["left"][0] - centres["right"][0])
                      / np.linalg.norm(centres["left"][1] - centres["right"][1]))
    return offsets, ratio


def offset_sigmas(offset: np.ndarray, side: str) -> np.ndarray:
    """How far ``offset`` (..., 3) lies from the mean offset of ``side``'s ear: per axis over
    the spread widened by the measurement error, then the length (the check's statistic)."""
    return np.linalg.norm((np.asarray(offset, float) - EAR_OFFSET_MEAN_MM[side])
                          / np.hypot(EAR_OFFSET_SPREAD_MM[side], EAR_NOISE_MM), axis=-1)


def check_ears(doc: dict, landmarks: np.ndarray, template: Template | None = None,
               min_points: int = 6, min_inlier_share: float = 0.5) -> dict:
    """``doc`` (an ``ears3d.json`` document of :func:`~facecap_core.landmarks.stage.
    triangulate_ears`) with the sides that fail removed and a ``checks`` entry per side that
    was looked for: its figures, ``used`` and, for a dropped side, ``reason``. ``landmarks``
    are the 68 triangulated landmarks in the ear points' units."""
    ids = np.asarray(doc.get("vertex_ids", []), np.int64)
    pts = np.asarray(doc.get("points", []), float).reshape(-1, 3)
    sides = np.asarray(doc.get("sides", []), dtype=object).astype(str)
    checks, reasons = {}, {}
    for side, views in doc.get("views", {}).items():
        if 0 < views < doc.get("min_views", 0):
            checks[side] = {"points": 0}
            reasons[side] = (f"found in {views} keyframe{'s' * (views != 1)} (needs "
                             f"{doc['min_views']})")
    for side in ("left", "right"):
        mine = sides == side
        if not mine.any() and side not in doc.get("observations", {}):
            continue
        checks[side] = c = {"points": int(mine.sum())}
        seen = doc.get("observations", {}).get(side)
        if seen:  # documents without the counts are not judged on them
            c["inlier_share"] = round(doc.get("inliers", {}).get(side, 0) / seen, 3)
        if mine.sum() < min_points:
            reasons[side] = (f"{int(mine.sum())} of its contour points triangulated "
                             f"(needs {min_points})")
        elif c.get("inlier_share", 1.0) < min_inlier_share:
            reasons[side] = (f"the views disagree: {100 * c['inlier_share']:.0f} % of its "
                             "detections reproject onto one contour (needs "
                             f"{100 * min_inlier_share:.0f} %)")
    measured = [side for side in ("left", "right") if side in checks and side not in reasons]
    L = np.asarray(landmarks, float)
    if measured and np.all(np.isfinite(L[INNER_LANDMARKS]), axis=1).sum() < MIN_FACE_LANDMARKS:
        for side in measured:
            reasons[side] = "too few face landmarks triangulated to place the ears against"
        measured = []
    if measured:
        offsets, ratio = contour_offsets(template or Template.default(), L, ids, pts, sides)
        for side in measured:
            offset = offsets[side]
            z = float(offset_sigmas(offset, side))
            checks[side].update(offset_mm=np.round(offset, 2).tolist(), offset_sigmas=round(z, 2))
            if z > EAR_OFFSET_BOUND:
                off = np.linalg.norm(offset - EAR_OFFSET_MEAN_MM[side])
                reasons[side] = (f"it lies {off:.0f} mm from where the face puts that ear "
                                 f"({z:.1f} sigma, bound {EAR_OFFSET_BOUND:g})")
        if len(measured) == 2:
            lo, hi = EAR_WIDTH_RATIO_BOUNDS
            for side in measured:
                checks[side]["width_ratio"] = round(ratio, 4)
            if not lo <= ratio <= hi:
                # Not a width a head has. Even when one ear is clearly out of place, the other
                # may be off too (ears 20 % too far apart are each only 15 mm out, within
                # their own bound): a wrong ear does more harm than a missing one, so neither
                # is used.
                for side in measured:
                    reasons.setdefault(side, f"the ears are {ratio:.2f} times the template's "
                                             f"width apart (bounds {lo:g}-{hi:g})")
    for side, c in checks.items():
        c["used"] = side not in reasons
        if side in reasons:
            c["reason"] = reasons[side]
    keep = np.isin(sides, [side for side, c in checks.items() if c["used"]])
    out = {**doc, "vertex_ids": ids[keep].tolist(), "points": pts[keep].tolist(),
           "sides": sides[keep].tolist(), "checks": checks}
    if "sigma" in doc:  # one per point: a mismatch fails the indexing
        out["sigma"] = np.asarray(doc["sigma"], float)[keep].tolist()
    return out


EAR_RELIABLE_MM = 1.0
"""An ear point triangulated to within this (1 sigma) pulls as hard as a face landmark: the
triangulated landmarks' own error is about 1 mm on the benchmarks' captures."""


def reliability(sigma_mm: np.ndarray) -> np.ndarray:
    """Weight in [0, 1] of ear points whose triangulation leaves ``sigma_mm`` of uncertainty:
    1 up to :data:`EAR_RELIABLE_MM`, beyond it the inverse variance relative to it (a point
    known to 2 mm pulls a quarter as hard as a landmark)."""
    sigma = np.nan_to_num(np.asarray(sigma_mm, float), nan=np.inf)
    return np.minimum(1.0, (EAR_RELIABLE_MM / np.maximum(sigma, 1e-12)) ** 2)
