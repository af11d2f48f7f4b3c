"""The face region scores are taken in: a sphere defined on the scan's landmarks."""

from __future__ import annotations

import numpy as np

from facecap_core.errors import InputError


def check_landmarks(landmarks: np.ndarray, what: str) -> np.ndarray:
    lm = np.asarray(landmarks, float)
    if lm.shape != (68, 3) or not np.all(np.isfinite(lm)):
        raise InputError(f"{what} landmarks must be 68 finite 3-D points in iBUG order; got an "
                         f"array of shape {lm.shape}")
    return lm


def region_sphere(landmarks68: np.ndarray, radius_factor: float = 1.4) -> tuple[np.ndarray, float]:
    """Centre and radius (mm) of the NoW-style face sphere from 68 iBUG landmarks.

    Centre: the nose tip (landmark 30). Radius: ``radius_factor * (|L36 - L45| + |L27 - L33|)
    / 2``, i.e. scaled from the outer-eye-corner distance and the nasion–nose-base length so
    that it adapts to face size.
    """
    lm = check_landmarks(landmarks68, "face-region")
    eyes = np.linalg.norm(lm[36] - lm[45])
    nose = np.linalg.norm(lm[27] - lm[33])
    return lm[30].copy(), float(radius_factor * (eyes + nose) / 2.0)


def face_region(vertices: np.ndarray, landmarks68: np.ndarray, radius_factor: float = 1.4
                ) -> np.ndarray:
    """Boolean mask of the vertices inside the face sphere of :func:`region_sphere`."""
    centre, radius = region_sphere(landmarks68, radius_factor)
    return np.linalg.norm(np.asarray(vertices, float) - centre, axis=1) <= radius
