"""68-point face landmarks in images (dlib's HOG detector + ERT shape predictor), their 3D
triangulation over keyframes (:mod:`.triangulate`) and the landmark stage (:mod:`.stage`).

The predictor file ships in the ``face-recognition-models`` package (no download at run
time). Its training data (iBUG 300-W) is licensed for non-commercial use only.
"""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np

from facecap_core.errors import FacecapError


@dataclass
class Detection:
    """One face: 68 landmarks (x, y) in pixels, the detector's score and its box.

    ``view`` is which of dlib's five HOG filters fired: 0 frontal, 1 and 2 turned (to the
    image's left / right), 3 and 4 frontal and tilted.
    """

    points: np.ndarray
    score: float
    box: tuple[int, int, int, int]
    view: int = 0
    irises: dict | None = None  # {"right", "left"}: iris.IrisFit, when measured


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


def face_box(image: np.ndarray) -> tuple[int, int, int, int] | None:
    """(left, top, right, bottom) of the highest-scoring face in a uint8 image, or None
    (the box alone, without the 68 points)."""
    detector, _ = _models()
    boxes, scores, _ = detector.run(np.ascontiguousarray(image), 0, 0.0)
    if not boxes:
        return None
    b = boxes[int(np.argmax(scores))]
    return b.left(), b.top(), b.right(), b.bottom()


def detect_68(image: np.ndarray, upsample: int = 0, detect_width: int | None = None,
              min_score: float = 0.0) -> Detection | None:
    """The highest-scoring face in an RGB or grey uint8 image, or None.

    With ``detect_width`` the box is searched in a copy of that width (the HOG scan costs
    time in proportion to the pixels) and the 68 points are predicted in the full image.
    ``min_score`` is dlib's detection threshold (its default is 0; lower finds more turned
    faces and more false boxes).
    """
    import dlib

    detector, predictor = _models()
    img = np.ascontiguousarray(image)
    small, factor = img, 1.0
    if detect_width is not None and detect_width < img.shape[1]:
        factor = img.shape[1] / float(detect_width)
        size = (int(detect_width), max(1, int(round(img.shape[0] / factor))))
        small = np.ascontiguousarray(cv2.resize(img, size, interpolation=cv2.INTER_AREA))
    boxes, scores, views = detector.run(small, upsample, min_score)
    if not boxes:
        return None
    best = int(np.argmax(scores))
    b = boxes[best]
    box = dlib.rectangle(*(int(round(v * factor)) for v in (b.left(), b.top(), b.right(),
                                                             b.bottom())))
    shape = predictor(img, box)
    pts = np.array([[p.x, p.y] for p in shape.parts()], float)
    return Detection(pts, float(scores[best]), (box.left(), box.top(), box.right(),
                                                box.bottom()), int(views[best]))
