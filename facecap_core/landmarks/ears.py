"""Ear detection and ear-contour landmarks (our own dlib HOG detector + ERT shape predictor).

No registry package ships an ear model; facecap trains one on renders of ICT Face Model
identities (:mod:`facecap.ear_training`, ``facecap train-ears``) and ships the
small model files in ``facecap_core/landmarks/models/`` (``$FACECAP_EAR_MODELS`` points to
another folder holding the same three files, e.g. a fresh training run).

The points are the outer contour of the ear, from the helix root (top front) over the top
and the back of the helix down to the lobe, and each means a vertex of the default template
(:data:`EAR_VERTEX_IDS`): the fitting pins those vertices to the triangulated points.
``side`` names the subject's ear that faces the camera ('left': the camera is on the
subject's left, the face looks towards the image's left). The model is trained on left-ear
views; a right-ear image is mirrored before detection and the points mirrored back.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from facecap_core.errors import FacecapError, InputError
from facecap_core.settings import settings

# Imported where used: dlib only where the ear models run (a run without them never loads it).

MODELS_DIR = Path(__file__).resolve().parent / "models"
DETECTOR_FILE = "ear_detector.svm"
PREDICTOR_FILE = "ear_predictor.dat"
CONTOUR_FILE = "ear_contour.json"
SIDES = ("left", "right")
SCORE_THRESHOLD = -0.4
"""Weakest HOG detector score accepted (the SVM margin: 0 is the trained boundary). Chosen on
renders of validation identities (ICT seeds 900-909, neither trained on nor benchmarked):
from 0 to -0.4 the detection rate rises from 97.5 % to 99.4 % while frontal and
background views with a box stay at 5 %; below -0.5 these false boxes climb quickly."""


def models_dir() -> Path:
    """The folder the ear model files are read from (``$FACECAP_EAR_MODELS`` or the package)."""
    return settings().ear_models or MODELS_DIR


def model_digest() -> str:
    """Digest of the model files in use ("none" without them): part of the landmark stage's
    artifact key, so a retrained or newly installed model is never hidden by a cached result."""
    folder = models_dir()
    if not model_available():
        return "none"
    stats = tuple((name, (folder / name).stat().st_mtime_ns, (folder / name).stat().st_size)
                  for name in (DETECTOR_FILE, PREDICTOR_FILE, CONTOUR_FILE))
    return _digest(str(folder), stats)


@lru_cache(maxsize=8)
def _digest(folder: str, stats: tuple) -> str:
    h = hashlib.sha256()
    for name, _, _ in stats:
        h.update((Path(folder) / name).read_bytes())
    return h.hexdigest()[:16]


def _load_vertex_ids() -> dict[str, np.ndarray]:
    # The contour definition ships with the package even where a user's model folder is used.
    path = MODELS_DIR / CONTOUR_FILE
    if not path.is_file():
        return {side: np.zeros(0, np.int64) for side in SIDES}
    doc = json.loads(path.read_text())
    return {side: np.asarray(doc["vertex_ids"][side], np.int64) for side in SIDES}


EAR_VERTEX_IDS: dict[str, np.ndarray] = _load_vertex_ids()
"""'left' / 'right' (the subject's) -> default-template vertex ids of the ear's outer contour,
ordered helix root -> top -> back -> lobe (``Template.default()``, menpo3d BFM topology)."""


def model_available() -> bool:
    """True when the detector, the predictor and the contour definition are present."""
    folder = models_dir()
    return all((folder / name).is_file() for name in (DETECTOR_FILE, PREDICTOR_FILE,
                                                        CONTOUR_FILE))


@dataclass
class EarDetection:
    """One ear: contour points (K, 2) in pixels (order of :data:`EAR_VERTEX_IDS`), the
    detector's score and its box (left, top, right, bottom) in the input image."""

    side: str
    points: np.ndarray
    score: float
    box: tuple[int, int, int, int]


@lru_cache(maxsize=4)
def _models(folder: str):
    import dlib

    path = Path(folder)
    if not model_available():
        raise FacecapError(f"ear model files missing in {path}: run `facecap train-ears` "
                           "(or python -m facecap.ear_training --out DIR) "
                           "and point FACECAP_EAR_MODELS at DIR")
    detector = dlib.fhog_object_detector(str(path / DETECTOR_FILE))
    predictor = dlib.shape_predictor(str(path / PREDICTOR_FILE))
    parts = len(json.loads((path / CONTOUR_FILE).read_text())["vertex_ids"]["left"])
    return detector, predictor, parts


def _grey_image(image: np.ndarray) -> np.ndarray:
    if not isinstance(image, np.ndarray):
        raise InputError(f"ear detection needs an image array, got {type(image).__name__}")
    if image.dtype != np.uint8:
        raise InputError(f"ear detection needs a uint8 image, got dtype {image.dtype}")
    if image.ndim == 3 and image.shape[2] in (3, 4):
        image = (image[..., :3].astype(np.float32) @ np.array([0.299, 0.587, 0.114],
                                                              np.float32))
        image = np.clip(np.round(image), 0, 255).astype(np.uint8)
    elif image.ndim != 2:
        raise InputError(f"ear detection needs an (H, W) grey or (H, W, 3) RGB image, got "
                         f"shape {image.shape}")
    if min(image.shape) < 32:
        raise InputError(f"image of {image.shape[1]}x{image.shape[0]} px is too small for ear "
                         "detection (needs 32 px or more on each side)")
    return image


def detect_ears(image: np.ndarray, side: str) -> EarDetection | None:
    """The best-scoring ear of the given ``side`` in an RGB or grey uint8 image, or None.

    The detector finds ears whose box is about 80 px tall or more (the image is upsampled
    once when it is small and nothing is found at its own size).
    """
    if side not in SIDES:
        raise InputError(f"ear side {side!r}: expected 'left' or 'right' (the subject's ear "
                         "that faces the camera)")
    grey = _grey_image(image)
    detector, predictor, parts = _models(str(models_dir()))
    import dlib

    h, w = grey.shape
    img = np.ascontiguousarray(grey[:, ::-1] if side == "right" else grey)
    boxes, scores, _ = detector.run(img, 0, SCORE_THRESHOLD)
    if not boxes and max(h, w) <= 800:
        boxes, scores, _ = detector.run(img, 1, SCORE_THRESHOLD)
    if not boxes:
        return None
    best = int(np.argmax(scores))
    box = boxes[best]
    shape = predictor(img, dlib.rectangle(box.left(), box.top(), box.right(), box.bottom()))
    pts = np.array([[p.x, p.y] for p in shape.parts()], float)
    if len(pts) != parts:
        raise FacecapError(f"ear predictor in {models_dir()} gives {len(pts)} points but its "
                           f"{CONTOUR_FILE} defines {parts}: retrain the ear model")
    l, t, r, b = box.left(), box.top(), box.right(), box.bottom()
    if side == "right":
        pts[:, 0] = w - 1 - pts[:, 0]
        l, r = w - 1 - r, w - 1 - l
    return EarDetection(side, pts, float(scores[best]), (l, t, r, b))
