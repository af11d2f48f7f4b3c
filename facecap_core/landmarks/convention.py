"""From the detector's 68 points to 3D landmarks on the face.

The 68 points are face-mesh vertices (:mod:`facecap_core.face`) chosen to lie nearest the
iBUG 300-W landmarks; triangulated, each still sits a little away from the 3D landmark vertex
of a head model (the mesh's vertices are not the annotation's points, and where the annotation
follows an edge seen in the photo, a vertex cannot). These offsets are systematic: a
per-landmark 3D offset, expressed in the head frame and in units of the eye-centre distance (so
it holds at any scale), removes most of them.

The table (:func:`load_offsets`, ``ibug68_convention.json``) is the median offset from the
triangulated to the ground-truth 3D landmarks over synthetic captures of ICT identities that
are not used for testing; ``python benchmarks/bench_landmarks.py --calibrate`` rebuilds it.
"""

from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path

import numpy as np

from facecap_core.template import INNER_LANDMARKS, head_frame

OFFSETS_FILE = Path(__file__).with_name("ibug68_convention.json")

__all__ = ["robust_head_frame", "eye_distance", "convention_offsets", "correct",
           "load_offsets", "OFFSETS_FILE"]


def robust_head_frame(landmarks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`head_frame` of 68 points of which the jaw contour may be NaN."""
    L = np.array(landmarks, float)
    if not np.isfinite(L[8]).all():
        L[8] = L[27] + 1.6 * (L[57] - L[27])  # the chin lies beyond the lower lip
    if not (np.isfinite(L[0]).all() and np.isfinite(L[16]).all()):
        # The origin only moves a camera's yaw by a degree or two.
        L[0] = L[16] = np.nanmean(L[INNER_LANDMARKS], axis=0)
    return head_frame(L)


def eye_distance(landmarks: np.ndarray) -> float:
    """Distance between the two eye centres (means of points 36-41 and 42-47)."""
    L = np.asarray(landmarks, float)
    return float(np.linalg.norm(L[42:48].mean(0) - L[36:42].mean(0)))


def convention_offsets(measured: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """(51, 3) offsets of the inner points from ``measured`` to ``truth`` (both 68 points in
    the same metric frame), in the measured head frame, per eye-centre distance."""
    R, _ = robust_head_frame(measured)
    d = (np.asarray(truth, float) - np.asarray(measured, float))[INNER_LANDMARKS]
    return d @ R.T / eye_distance(measured)


def correct(landmarks: np.ndarray, offsets: np.ndarray, frame_from: np.ndarray | None = None
            ) -> np.ndarray:
    """The 68 landmarks with ``offsets`` (51, 3) applied to the inner points; the head frame
    and eye distance come from ``frame_from`` (default: the landmarks themselves)."""
    L = np.array(landmarks, float)
    ref = L if frame_from is None else np.asarray(frame_from, float)
    R, _ = robust_head_frame(ref)
    L[INNER_LANDMARKS] += eye_distance(ref) * np.asarray(offsets, float) @ R
    return L


@lru_cache(maxsize=1)
def load_offsets() -> tuple[np.ndarray, dict]:
    """The calibrated (51, 3) offsets and their record (captures, command)."""
    doc = json.loads(OFFSETS_FILE.read_text())
    offsets = np.asarray(doc["offsets"], float)
    if offsets.shape != (len(INNER_LANDMARKS), 3):
        raise ValueError(f"{OFFSETS_FILE}: offsets of shape {offsets.shape}")
    return offsets, {k: v for k, v in doc.items() if k != "offsets"}
