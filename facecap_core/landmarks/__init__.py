"""68-point face landmarks in images (dlib's HOG detector + ERT shape predictor).

The predictor file ships in the ``face-recognition-models`` package (no download at run
time). Its training data (iBUG 300-W) is licensed for non-commercial use only.
"""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from facecap_core.errors import FacecapError


@dataclass
class Detection:
    """One face: 68 landmarks (x, y) in pixels, the detector's score and its box."""

    points: np.ndarray
    score: float
    box: tuple[int, int, int, int]


PREDICTOR_68 = "shape_predictor_68_face_landmarks.dat"


def model_path(name: str) -> Path:
    """A model file inside the installed face-recognition-models package."""
    # Located without importing the package: its __init__ needs pkg_resources, which
    # recent setuptools no longer provides.
    spec = importlib.util.find_spec("face_recognition_models")
    if spec is None or not spec.submodule_search_locations:
        raise FacecapError("face-recognition-models is not installed: run `make install`")
    path = Path(list(spec.submodule_search_locations)[0]) / "models" / name
    if not path.is_file():
        raise FacecapError(f"landmark model {path} is missing: reinstall face-recognition-models")
    return path


@lru_cache(maxsize=1)
def _models():
    import dlib

    return dlib.get_frontal_face_detector(), dlib.shape_predictor(str(model_path(PREDICTOR_68)))


def detect_68(image: np.ndarray, upsample: int = 0) -> Detection | None:
    """The highest-scoring face in an RGB or grey uint8 image, or None."""
    detector, predictor = _models()
    img = np.ascontiguousarray(image)
    boxes, scores, _ = detector.run(img, upsample, 0.0)
    if not boxes:
        return None
    best = int(np.argmax(scores))
    box = boxes[best]
    shape = predictor(img, box)
    pts = np.array([[p.x, p.y] for p in shape.parts()], float)
    return Detection(pts, float(scores[best]), (box.left(), box.top(), box.right(), box.bottom()))
