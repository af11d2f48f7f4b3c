"""The regions scores are taken in, defined on the scan's landmarks: the face sphere and,
beside it, the ear region (a sphere around each ear, outside the face sphere)."""

from __future__ import annotations

import numpy as np

from facecap_core.errors import InputError
from facecap_core.template import head_frame

EAR_CENTRE_OFFSET = np.array([0.072, -0.375, -0.5])
"""Where an ear sphere's centre lies from the top of the jaw contour on its side (L16 for the
subject's left ear, L0 for the right), in face sizes (:func:`face_size`) along the head frame
of the landmarks: outwards, up, forwards (so down and backwards here). Calibrated by
``tools/calibrate_ear_region.py`` on ICT identities 1000–1199 (docs/evaluation.md)."""

EAR_RADIUS_FACTOR = 0.78
"""Ear-sphere radius in face sizes: the farthest ear point of any calibration identity from
its predicted centre (0.621 face sizes) plus a margin of 0.15 (≈ 10 mm) of the side of the
head around the ear; ≈ 55 mm on an adult."""


def check_landmarks(landmarks: np.ndarray, what: str) -> np.ndarray:
    lm = np.asarray(landmarks, float)
    if lm.shape != (68, 3) or not np.all(np.isfinite(lm)):
        raise InputError(f"{what} landmarks must be 68 finite 3-D points in iBUG order; got an "
                         f"array of shape {lm.shape}")
    return lm


def face_size(landmarks68: np.ndarray) -> float:
    """The length both regions scale with (mm): the mean of the outer-eye-corner distance
    |L36 - L45| and the nasion–nose-base length |L27 - L33| (≈ 70 mm on an adult)."""
    lm = check_landmarks(landmarks68, "face-region")
    return float((np.linalg.norm(lm[36] - lm[45]) + np.linalg.norm(lm[27] - lm[33])) / 2.0)


def region_sphere(landmarks68: np.ndarray, radius_factor: float = 1.4) -> tuple[np.ndarray, float]:
    """Centre and radius (mm) of the NoW-style face sphere from 68 iBUG landmarks.

    Centre: the nose tip (landmark 30). Radius: ``radius_factor * (|L36 - L45| + |L27 - L33|)
    / 2``, i.e. scaled from the outer-eye-corner distance and the nasion–nose-base length so
    that it adapts to face size.
    """
    lm = check_landmarks(landmarks68, "face-region")
    return lm[30].copy(), radius_factor * face_size(lm)


def face_region(vertices: np.ndarray, landmarks68: np.ndarray, radius_factor: float = 1.4
                ) -> np.ndarray:
    """Boolean mask of the vertices inside the face sphere of :func:`region_sphere`."""
    centre, radius = region_sphere(landmarks68, radius_factor)
    return np.linalg.norm(np.asarray(vertices, float) - centre, axis=1) <= radius


def ear_spheres(landmarks68: np.ndarray, offset: np.ndarray = EAR_CENTRE_OFFSET,
                radius_factor: float = EAR_RADIUS_FACTOR) -> tuple[np.ndarray, float]:
    """Centres (2, 3: the subject's left ear, then the right) and radius (mm) of the ear spheres.

    Each centre is the top of the jaw contour on its side (L16 left, L0 right: the landmarks
    next to the ear) moved by ``offset`` face sizes along the landmarks' head frame
    (:func:`facecap_core.template.head_frame`: eye centre to eye centre, chin to nasion, out of
    the face), outwards mirrored per side; the radius is ``radius_factor`` face sizes.
    """
    lm = check_landmarks(landmarks68, "ear-region")
    size = face_size(lm)
    with np.errstate(invalid="ignore", divide="ignore"):
        R, _ = head_frame(lm)  # coincident eyes or chin and nasion: nan, an empty region
    centres = [lm[anchor] + size * (outwards * offset[0] * R[0] + offset[1] * R[1]
                                    + offset[2] * R[2])
               for anchor, outwards in ((16, 1.0), (0, -1.0))]
    return np.array(centres), radius_factor * size


def ear_region(vertices: np.ndarray, landmarks68: np.ndarray, radius_factor: float = 1.4,
               ear_radius_factor: float = EAR_RADIUS_FACTOR) -> np.ndarray:
    """Boolean mask of the vertices in the ear region: inside either ear sphere of
    :func:`ear_spheres` and outside the face sphere of ``radius_factor``, so that no vertex is
    scored in both regions."""
    v = np.asarray(vertices, float)
    centres, radius = ear_spheres(landmarks68, radius_factor=ear_radius_factor)
    near_ear = np.linalg.norm(v[:, None] - centres[None], axis=2).min(axis=1) <= radius
    return near_ear & ~face_region(v, landmarks68, radius_factor)
