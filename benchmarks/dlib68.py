"""dlib's 68-point detector (HOG face box + ERT shape predictor), for comparison only.

facecap does not ship it: its predictor, ``shape_predictor_68_face_landmarks.dat``, is trained
on iBUG 300-W, whose licence excludes commercial use. ``bench_landmark_detectors.py`` compares
it with the product's detector when it is installed by hand::

    .venv/bin/pip install face-recognition-models==0.3.0   # dlib comes with facecap (ears)
"""

from __future__ import annotations

import importlib.util
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np


def available() -> bool:
    return (importlib.util.find_spec("face_recognition_models") is not None
            and importlib.util.find_spec("dlib") is not None)


@lru_cache(maxsize=1)
def _models():
    import dlib

    # Found by path: the package's __init__ needs pkg_resources, gone from recent setuptools.
    spec = importlib.util.find_spec("face_recognition_models")
    path = (Path(list(spec.submodule_search_locations)[0]) / "models"
            / "shape_predictor_68_face_landmarks.dat")
    return dlib.get_frontal_face_detector(), dlib.shape_predictor(str(path))


def detect(image: np.ndarray, detect_width: int = 640, min_score: float = -0.3):
    """(68 points, score, box) of the highest-scoring face, or None: the HOG box on a copy
    ``detect_width`` wide, the 68 points predicted at full resolution (as facecap used it)."""
    import dlib

    detector, predictor = _models()
    img = np.ascontiguousarray(image)
    small, factor = img, 1.0
    if detect_width < img.shape[1]:
        factor = img.shape[1] / float(detect_width)
        size = (int(detect_width), max(1, int(round(img.shape[0] / factor))))
        small = np.ascontiguousarray(cv2.resize(img, size, interpolation=cv2.INTER_AREA))
    boxes, scores, _ = detector.run(small, 0, min_score)
    if not boxes:
        return None
    best = int(np.argmax(scores))
    b = boxes[best]
    box = dlib.rectangle(*(int(round(v * factor)) for v in (b.left(), b.top(), b.right(),
                                                             b.bottom())))
    shape = predictor(img, box)
    points = np.array([[p.x, p.y] for p in shape.parts()], float)
    return points, float(scores[best]), (box.left(), box.top(), box.right(), box.bottom())
