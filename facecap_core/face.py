"""Faces in images: the face box, MediaPipe's 478-point face mesh, and the 68 landmarks of the
iBUG 300-W convention read off that mesh.

MediaPipe (the ``mediapipe`` package, Apache-2.0) ships its models inside the wheel:
BlazeFace's short- and full-range face detectors (the box and its score) and the face mesh with
attention (468 surface points plus the two irises' five points each). ``make install`` installs
it without its declared dependencies, which would replace opencv-python-headless's ``cv2``
(docs/dependencies.md).

The 68 points are fixed mesh vertices (:func:`mesh_to_68`): for each iBUG index, the vertex
whose image lies nearest that landmark on calibration renders. They are surface points, the
same ones in every view, so they triangulate consistently; where the iBUG annotation means
something else (the jaw contour is a silhouette in each photo, a brow is drawn along its lower
edge) the landmark stage's calibrated convention offsets
(:mod:`facecap_core.landmarks.convention`) move them in 3D.
"""

from __future__ import annotations

import importlib.util
import json
import logging
import threading
import warnings
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from facecap_core.errors import FacecapError
from facecap_core.native_logs import native_stderr_to_log

__all__ = ["Detection", "MESH_POINTS", "MESH_TO_68_FILE", "available", "detect", "face_box",
           "mesh_to_68", "DETECTOR"]

log = logging.getLogger(__name__)

DETECTOR = ("MediaPipe 0.10 (Apache-2.0): BlazeFace face box (short or full range), face mesh with "
            "irises (478 points); the 68 iBUG points are fixed mesh vertices")
MESH_POINTS = 478
MIN_SCORE = 0.1  # the weakest detection the detector reports at all

# iBUG 300-W index -> MediaPipe face-mesh vertex ("right" is the subject's right, the image's
# left in a frontal view, in both conventions): the vertex nearest each projected ground-truth
# landmark on calibration renders (``python benchmarks/bench_landmarks.py --calibrate``).
MESH_TO_68_FILE = Path(__file__).with_name("data") / "face_mesh_to_ibug68.json"

_LOCK = threading.Lock()  # MediaPipe's graphs are not re-entrant: one call at a time

# protobuf 4 warns on every graph output that MediaPipe 0.10 reads the old way; filtered once
# here (catch_warnings around each call would swap the process's filters from several
# threads at once).
warnings.filterwarnings("ignore", message="SymbolDatabase.GetPrototype", category=UserWarning)


@dataclass
class Detection:
    """One face: the 68 landmarks (x, y) in pixels, the face detector's score (0-1), its box
    (left, top, right, bottom), the whole mesh (478, 2) and, when measured, the irises
    ({"right", "left"}: :class:`facecap_core.landmarks.iris.IrisFit`)."""

    points: np.ndarray
    score: float
    box: tuple[float, float, float, float]
    mesh: np.ndarray
    irises: dict | None = None


@lru_cache(maxsize=1)
def mesh_to_68() -> np.ndarray:
    """The (68,) mesh vertex of each iBUG point."""
    vertices = np.asarray(json.loads(MESH_TO_68_FILE.read_text())["vertices"], int)
    if vertices.shape != (68,) or vertices.min() < 0 or vertices.max() >= 468:
        raise ValueError(f"{MESH_TO_68_FILE}: 68 face-mesh vertices (0-467) expected")
    return vertices


def available() -> bool:
    """Whether the ``mediapipe`` package is installed."""
    return importlib.util.find_spec("mediapipe") is not None


INSTALL = ("run `make install`, or `pip install --no-deps mediapipe==0.10.21` and the "
           "packages pyproject.toml lists for it (docs/dependencies.md)")


def _require() -> None:
    if not available():
        raise FacecapError(f"the mediapipe package (the face detector) is not installed: "
                           f"{INSTALL}")


def _solution(name: str):
    """``mediapipe.python.solutions.<name>``, or a one-line error when it cannot be imported."""
    _require()
    try:
        return importlib.import_module(f"mediapipe.python.solutions.{name}")
    except ImportError as exc:
        raise FacecapError(f"the mediapipe package does not import ({exc}): {INSTALL}") from exc


_SPOKEN: set[int] = set()  # graphs that have run a model on a face


def _run(graph, image: np.ndarray):
    """``graph.process(image)``. The C++ side logs to stderr when a model first runs (the
    TFLite delegate, absl notices), which is at the first image with a face for the mesh
    model: until then its stderr goes to the log at DEBUG, none of it is a warning to the
    user."""
    with _LOCK:
        if id(graph) in _SPOKEN:
            return graph.process(image)
        with native_stderr_to_log(log, warnings=(), prefix="mediapipe: "):
            result = graph.process(image)
        if getattr(result, "detections", None) or getattr(result, "multi_face_landmarks", None):
            _SPOKEN.add(id(graph))
        return result


def _started(graph):
    _run(graph, np.zeros((64, 64, 3), np.uint8))
    return graph


@lru_cache(maxsize=2)
def _face_detector(full_range: bool):
    face_detection = _solution("face_detection")
    return _started(face_detection.FaceDetection(model_selection=int(full_range),
                                                 min_detection_confidence=MIN_SCORE))


@lru_cache(maxsize=1)
def _face_mesh():
    face_mesh = _solution("face_mesh")
    return _started(face_mesh.FaceMesh(static_image_mode=True, refine_landmarks=True,
                                       max_num_faces=1, min_detection_confidence=0.3))


def _rgb(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    return np.ascontiguousarray(img[..., :3], dtype=np.uint8)


def face_box(image: np.ndarray, min_score: float = 0.5
             ) -> tuple[tuple[float, float, float, float], float] | None:
    """The box (left, top, right, bottom) and score of the highest-scoring face in an RGB or
    grey uint8 image, or None when no face scores ``min_score`` or more."""
    img = _rgb(image)
    h, w = img.shape[:2]
    best = None
    # The short-range model finds faces that fill the frame (a phone at arm's length or
    # closer), which the full-range one misses; the full-range one finds faces further away.
    for full_range in (False, True):
        result = _run(_face_detector(full_range), img)
        if result.detections:
            best = max(result.detections, key=lambda d: d.score[0])
            if best.score[0] >= min_score:
                break
    if best is None or best.score[0] < min_score:
        return None
    b = best.location_data.relative_bounding_box
    # MediaPipe's normalised coordinates put pixel centres at (i + 0.5) / size; ours at i.
    box = (b.xmin * w - 0.5, b.ymin * h - 0.5, (b.xmin + b.width) * w - 0.5,
           (b.ymin + b.height) * h - 0.5)
    return tuple(float(v) for v in box), float(best.score[0])


def detect(image: np.ndarray, min_score: float = 0.5) -> Detection | None:
    """The highest-scoring face of an RGB or grey uint8 image with its 68 landmarks, or None.

    The mesh is computed on a crop twice the face box's size around it, so that a small face in
    a large frame reaches the mesh model (192 px) as large as it can."""
    img = _rgb(image)
    found = face_box(img, min_score)
    if found is None:
        return None
    box, score = found
    left, top, right, bottom = box
    size = max(right - left, bottom - top)
    cx, cy = 0.5 * (left + right), 0.5 * (top + bottom)
    h, w = img.shape[:2]
    x0, y0 = int(max(0, np.floor(cx - size))), int(max(0, np.floor(cy - size)))
    x1, y1 = int(min(w, np.ceil(cx + size))), int(min(h, np.ceil(cy + size)))
    if x1 - x0 < 32 or y1 - y0 < 32:
        return None
    result = _run(_face_mesh(), np.ascontiguousarray(img[y0:y1, x0:x1]))
    if not result.multi_face_landmarks:
        return None
    # MediaPipe's normalised coordinates put pixel centres at (i + 0.5) / size; ours at i.
    mesh = np.array([[q.x * (x1 - x0) + x0 - 0.5, q.y * (y1 - y0) + y0 - 0.5]
                     for q in result.multi_face_landmarks[0].landmark])
    if len(mesh) < MESH_POINTS:
        return None
    return Detection(mesh[mesh_to_68()], score, box, mesh)
