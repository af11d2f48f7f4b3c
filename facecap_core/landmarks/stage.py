"""The landmark stage: 68 landmarks per keyframe, a confidence gate, and 3D landmarks.

:func:`main` runs, for the keyframes of a ``cameras.json`` (``facecap_core/pose/io.py``):

1. **Detection**: MediaPipe's face box and face mesh, and the 68 points read off the mesh, on
   every keyframe (:func:`facecap_core.face.detect`).
2. **First triangulation** of all 68 points from every detection (robust,
   :mod:`.triangulate`). It gives the head frame (:func:`facecap_core.template.head_frame`),
   hence each keyframe's **yaw** around the head — for every keyframe, detected or not — and
   each detection's **agreement**: the median reprojection error of its inner points against
   the landmarks triangulated from all views, relative to the face box size.
3. **Gate** (the paper: high-confidence, near-frontal frames): |yaw| and agreement within the
   :class:`~facecap_core.landmarks.config.LandmarkConfig` limits (the detector's score is checked
   at detection).
4. **3D landmarks**: the 51 inner points (iBUG 17–67; the jaw contour 0–16 depends on the
   view and is left out, as in the paper) triangulated from the gated keyframes, then moved
   from the detector's image convention to 3D landmarks on the face
   (:mod:`.convention`, when ``convention_correction``).
5. **Ears**, when :mod:`facecap_core.landmarks.ears` and its model are installed: each
   profile-side keyframe (``ear_min_yaw_deg`` ≤ |yaw| ≤ ``ear_max_yaw_deg``) looks for the
   ear that faces its camera (+yaw: the subject's left), and each ear's contour points are
   triangulated over the keyframes that found it. A side whose points fail the checks of
   :mod:`.ear_check` (too few points, views that disagree, an ear where no ear can be
   relative to the face, an ear-to-ear width no head has) is dropped with its reason.
6. **Irises** (:mod:`.iris`, from the same face mesh): each detected keyframe's pupil
   centres and horizontal iris diameters (``landmarks2d.json``, per keyframe); over the gated
   keyframes within ``iris_max_yaw_deg`` of frontal, the pupils triangulated and the iris
   diameter in world units (``landmarks3d.json``: ``irises``), for the coarse stage's scale
   cues.

Outputs (``out_dir``): ``landmarks2d.json``, ``landmarks3d.json`` (camera units; the jaw
contour and any inner point too uncertain to keep — ``max_point_spread`` — are null),
``ears3d.json`` (possibly empty). Coordinates are full-resolution pixels of the
cameras' intrinsics (video frames of another size are mapped to it).
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import numpy as np

from facecap_core.camera import (
    CAMERAS_JSON,
    CameraSet,
    Intrinsics,
    camera_center,
)
from facecap_core.errors import InputError
from facecap_core.face import DETECTOR, MESH_TO_68_FILE, Detection, detect
from facecap_core.landmarks import ears, iris
from facecap_core.landmarks.config import LandmarkConfig
from facecap_core.landmarks.convention import (
    OFFSETS_FILE,
    correct,
    eye_distance,
    load_offsets,
    robust_head_frame,
)
from facecap_core.landmarks.ear_check import check_ears
from facecap_core.landmarks.landmarks3d_json import Landmarks3d, load_landmarks3d
from facecap_core.landmarks.triangulate import Triangulation, box_size, triangulate
from facecap_core.pose.cameras_json import read_cameras_json
from facecap_core.pose.checks import CameraSolveError, face_problem
from facecap_core.stage import Folders, Stage, capture_in
from facecap_core.template import INNER_LANDMARKS
from facecap_core.video import iter_frames

TRY_AGAIN = ("record a slower, steadier sweep of a well-lit, still face from one ear round to "
             "the other (photos: named in sweep order, frame_001.jpg, …, or the video itself)")
"""What to try when the landmarks show that the camera solve failed."""

LANDMARKS_2D = "landmarks2d.json"
LANDMARKS_3D = "landmarks3d.json"
EARS_3D = "ears3d.json"

log = logging.getLogger(__name__)

__all__ = ["main", "load_landmarks3d", "load_ears3d",
           "camera_yaw_pitch_deg", "robust_head_frame"]

EAR_TEMPLATE = "menpo3d-bfm"  # the template whose vertex ids ears3d.json refers to


# --------------------------------------------------------------------------- geometry


def camera_yaw_pitch_deg(head_R: np.ndarray, head_origin: np.ndarray, R: np.ndarray,
                         t: np.ndarray) -> tuple[float, float]:
    """Yaw (+: towards the subject's left) and pitch (+: from above) of a camera around the
    head, in degrees; 0, 0 is straight in front of the face."""
    c = head_R @ (camera_center(R, t) - head_origin)
    return (float(np.degrees(np.arctan2(c[0], c[2]))),
            float(np.degrees(np.arctan2(c[1], np.hypot(c[0], c[2])))))


def _box_diagonal(box) -> float:
    left, top, right, bottom = box
    return float(np.hypot(right - left, bottom - top))


def _to_intrinsics(points: np.ndarray, image_shape, intr: Intrinsics) -> np.ndarray:
    """Pixels of a decoded frame to pixels of the intrinsics' resolution."""
    h, w = image_shape[:2]
    if (w, h) == (intr.width, intr.height):
        return np.asarray(points, float)
    s = np.array([intr.width / w, intr.height / h])
    return (np.asarray(points, float) + 0.5) * s - 0.5


# --------------------------------------------------------------------------- detection


def _at_intrinsics(det: Detection, irises: dict | None, image_shape, intr: Intrinsics
                   ) -> Detection:
    """A detection in a decoded frame's pixels, with its irises (None: not measured), in the
    intrinsics' pixels."""
    def at(points):
        return _to_intrinsics(np.reshape(points, (-1, 2)), image_shape, intr)

    zoom = intr.width / image_shape[1]
    if irises is not None:
        irises = {side: iris.IrisFit(at(f.centre)[0], f.diameter * zoom, f.opening)
                  for side, f in irises.items()}
    return Detection(at(det.points), det.score, tuple(float(b) for b in at(det.box).ravel()),
                     at(det.mesh), irises)


def detect_keyframes(video: str | Path, cams: CameraSet, config: LandmarkConfig
                     ) -> list[Detection | None]:
    """One :class:`Detection` (points at the intrinsics' resolution) or None per keyframe."""

    found: dict[int, Detection | None] = {}
    for frame in iter_frames(video, indices=cams.frame_indices):
        det = detect(frame.image, config.min_detector_score)
        if det is not None:
            irises = (iris.detect_irises(frame.image, det, config.min_eye_opening)
                      if config.irises else None)
            det = _at_intrinsics(det, irises, frame.image.shape, cams.intrinsics)
        found[frame.index] = det
    missing = [i for i in cams.frame_indices if i not in found]
    if missing:
        raise InputError(f"{video} has no frames {missing[:5]}{'...' if len(missing) > 5 else ''}"
                         " that the cameras list: the video and cameras.json do not belong "
                         "together")
    return [found[i] for i in cams.frame_indices]


def _ear_module():
    """The ear module when its trained models are installed, else None."""
    return ears if ears.model_available() else None


# --------------------------------------------------------------------------- main


def _observations(dets: list[Detection | None], ids: np.ndarray, points: np.ndarray):
    """(V, P, 2) observations of the landmarks ``points`` over the views ``ids``."""
    uv = np.full((len(ids), len(points), 2), np.nan)
    for k, v in enumerate(ids):
        uv[k] = dets[v].points[points]
    return uv


def _triangulate_faces(dets, views, points, cams: CameraSet, config: LandmarkConfig,
                       min_views: int = 2) -> Triangulation:
    views = np.asarray(views, int)
    size = np.array([box_size(dets[v].box) for v in views])
    return triangulate(_observations(dets, views, points), cams.R[views], cams.t[views],
                       cams.intrinsics, config.outlier_threshold * size, config.huber * size,
                       min_views, config.min_parallax_deg)


def _gate(records: list[dict], config: LandmarkConfig) -> tuple[list[int], bool]:
    """Keyframe positions that pass the gate, and whether it had to be widened."""
    detected = [k for k, r in enumerate(records) if r["detected"]]
    passed = [k for k in detected
              if abs(records[k]["yaw_deg"]) <= config.gate_max_yaw_deg
              and records[k]["reprojection_rel"] <= config.gate_max_reprojection]
    if len(passed) >= min(config.min_views, len(detected)):
        return passed, False
    # Too few: the best-agreeing detections, nearest to frontal first among equals.
    order = sorted(detected, key=lambda k: (records[k]["reprojection_rel"],
                                            abs(records[k]["yaw_deg"])))
    return sorted(order[:max(config.min_views, 2)]), True


def _detect_ears(video, cams: CameraSet, records: list[dict], ears, config: LandmarkConfig):
    """Ear detections of the profile-side keyframes: {side: [(keyframe position, det)]}."""

    side_of = {}
    for k, r in enumerate(records):
        if config.ear_min_yaw_deg <= abs(r["yaw_deg"]) <= config.ear_max_yaw_deg:
            side_of[cams.frame_indices[k]] = (k, "left" if r["yaw_deg"] > 0 else "right")
    found: dict[str, list] = {"left": [], "right": []}
    for frame in iter_frames(video, indices=list(side_of)):
        k, side = side_of[frame.index]
        det = ears.detect_ears(frame.image, side)
        if det is None:
            continue
        pts = _to_intrinsics(det.points, frame.image.shape, cams.intrinsics)
        box = _to_intrinsics(np.reshape(det.box, (2, 2)), frame.image.shape,
                             cams.intrinsics).ravel()
        found[side].append((k, pts, float(det.score), tuple(float(b) for b in box)))
        records[k]["ears"].append({"side": side, "score": float(det.score),
                                   "box": [round(float(b), 2) for b in box],
                                   "points": np.round(pts, 3).tolist()})
    return found


def triangulate_ears(found: dict[str, list], cams: CameraSet, vertex_ids: dict[str, np.ndarray],
                     config: LandmarkConfig) -> dict:
    """Triangulate each ear's contour points; returns the ears3d.json document (before
    :func:`~facecap_core.landmarks.ear_check.check_ears`): per point its ``sigma``, the
    standard deviation of its least certain direction (camera units) for the reprojection
    error its side's views leave, and per side the ``observations`` and ``inliers`` counted."""
    ids, points, sides, sigmas, views = [], [], [], [], {}
    observations, inliers = {}, {}
    for side, obs in found.items():
        views[side] = len(obs)
        if len(obs) < config.ear_min_views:
            continue
        k = np.array([o[0] for o in obs])
        uv = np.stack([o[1] for o in obs])
        diag = np.array([_box_diagonal(o[3]) for o in obs])
        tri = triangulate(uv, cams.R[k], cams.t[k], cams.intrinsics,
                          config.ear_outlier_threshold * diag, config.ear_huber * diag, 2,
                          config.min_parallax_deg)
        ok = np.all(np.isfinite(tri.points), axis=1)
        observations[side] = int(np.all(np.isfinite(uv), axis=-1).sum())
        inliers[side] = int(tri.inliers.sum())
        # The image noise the side's inlier views leave, pooled over its points (3 unknowns
        # per point): one estimate per point would rest on a degree of freedom or two.
        n = tri.inliers.sum(0)[ok]
        sq = np.where(tri.inliers, np.nan_to_num(tri.errors) ** 2, 0.0).sum(0)[ok]
        noise_px = np.sqrt(sq.sum() / max(int(np.sum(2 * n - 3)), 1))
        ids += np.asarray(vertex_ids[side])[ok].astype(int).tolist()
        points += tri.points[ok].tolist()
        sides += [side] * int(ok.sum())
        sigmas += (tri.spread(1.0)[ok] * noise_px).tolist()
    return {"template": EAR_TEMPLATE, "units": cams.units, "vertex_ids": ids,
            "points": points, "sides": sides, "sigma": sigmas, "views": views,
            "min_views": config.ear_min_views, "observations": observations,
            "inliers": inliers}


def yaw_coverage(records: list[dict]) -> dict:
    """The yaw range around the head that the registered keyframes span (+: the subject's
    left), and each keyframe's yaw."""
    yaws = np.array([r["yaw_deg"] for r in records], float)
    return {"yaw_min_deg": round(float(yaws.min()), 1), "yaw_max_deg": round(float(yaws.max()), 1),
            "yaw_span_deg": round(float(yaws.max() - yaws.min()), 1),
            "yaw_by_frame": [[r["frame_index"], r["yaw_deg"]] for r in records]}


def _keyframe_records(dets, detected, first, head_R, head_o, cams) -> list[dict]:
    """Each keyframe's record: its view of the head (yaw, pitch), and where a face was
    detected its score, box, points and how far they are from the first triangulation."""
    inner = INNER_LANDMARKS
    records = []
    for k, det in enumerate(dets):
        yaw, pitch = camera_yaw_pitch_deg(head_R, head_o, cams.R[k], cams.t[k])
        rec = {"frame_index": cams.frame_indices[k], "detected": det is not None,
               "yaw_deg": round(yaw, 2), "pitch_deg": round(pitch, 2), "ears": []}
        if det is not None:
            v = detected.index(k)
            err = first.errors[v, inner]
            med = float(np.nanmedian(err)) if np.isfinite(err).any() else float("inf")
            rec.update(score=round(det.score, 4),
                       box=[round(b, 2) for b in det.box],
                       points=np.round(det.points, 3).tolist(),
                       reprojection_px=round(med, 3),
                       reprojection_rel=round(med / box_size(det.box), 5))
        records.append(rec)
    return records


def _coverage(records: list[dict], config: LandmarkConfig) -> dict:
    """How far round the head the views go; too little is bad input."""
    coverage = yaw_coverage(records)
    if coverage["yaw_span_deg"] < config.min_yaw_span_deg:
        raise InputError(
            f"the {len(records)} registered views cover yaw {coverage['yaw_min_deg']:+.0f}° to "
            f"{coverage['yaw_max_deg']:+.0f}° around the head ({coverage['yaw_span_deg']:.0f}°"
            f"); a face needs at least {config.min_yaw_span_deg:.0f}° and a full capture about "
            "180°: record again, moving the camera from one ear round the face to the other")
    return coverage


def _landmarks3d_doc(cams, landmarks, correction, triangulated, gated, uncertain, spread,
                     final, head_R, head_o, iris_doc, detected: int, keyframes: int,
                     coverage) -> dict:
    """``landmarks3d.json``'s content (without its timings)."""
    errs = final.errors[final.inliers]
    doc3d = {"convention": "ibug68", "units": cams.units,
             "landmarks": [None if not np.all(np.isfinite(p)) else [round(float(x), 6)
                                                                     for x in p]
                           for p in landmarks],
             "convention_correction": correction,
             "triangulated": [None if not np.all(np.isfinite(p)) else [round(float(x), 6)
                                                                        for x in p]
                              for p in triangulated],
             "views": [cams.frame_indices[k] for k in gated],
             "dropped_uncertain": uncertain.tolist(),
             "spread_rel": [None] * 17 + [round(float(x), 5) if np.isfinite(x) else None
                                          for x in spread],
             "inlier_views": [int(v) for v in np.r_[np.zeros(17, int), final.views]],
             "reprojection_px": {"median": float(np.median(errs)) if errs.size else None,
                                 "rms": float(np.sqrt(np.mean(errs ** 2))) if errs.size
                                 else None},
             "head_frame": {"R": head_R.tolist(), "origin": head_o.tolist()},
             "irises": iris_doc,
             "detected": detected, "keyframes": keyframes, "coverage": coverage}
    return doc3d


def _ears3d(video, cams, records, landmarks, ears, config: LandmarkConfig) -> dict:
    """``ears3d.json``'s content: the ear points triangulated and checked against the face
    (none without the ear model ``ears``)."""
    if ears is None:
        return {"template": EAR_TEMPLATE, "units": cams.units, "vertex_ids": [],
                "points": [], "sides": [], "views": {}}
    found = _detect_ears(video, cams, records, ears, config)
    ears_doc = check_ears(triangulate_ears(found, cams, ears.EAR_VERTEX_IDS, config), landmarks)
    for side, c in ears_doc["checks"].items():
        log.info("%s ear: %s", side, f"{c['points']} points used" if c["used"]
                 else f"dropped, {c['reason']}")
    return ears_doc


def _must_be_a_face(landmarks: np.ndarray) -> None:
    """Refuse landmarks that do not form a face: the camera solve failed."""
    problem = face_problem(landmarks)
    if problem:
        raise CameraSolveError(problem, TRY_AGAIN)


def main(video: str | Path, cameras_json: str | Path, out_dir: str | Path,
         config: LandmarkConfig | None = None) -> Path:
    """Detect 68 landmarks on every keyframe of ``cameras_json``, score and gate them,
    triangulate the inner points (robustly) and the ear points when the ear model is
    installed. Writes ``landmarks2d.json``, ``landmarks3d.json`` and ``ears3d.json`` into
    ``out_dir``; returns the path of ``landmarks3d.json``."""
    config = config or LandmarkConfig()
    t_wall, t_cpu = time.perf_counter(), time.process_time()
    cams = read_cameras_json(cameras_json)
    dets = detect_keyframes(video, cams, config)
    n = len(dets)
    detected = [k for k, d in enumerate(dets) if d is not None]
    if not detected:
        raise InputError(f"no face was detected in any of {n} keyframes: the video must show "
                         "a face, frontally lit and unoccluded, from the front as well as the "
                         "sides")
    if len(detected) < 2:
        raise InputError(f"a face was detected in only 1 of {n} keyframes; 3D landmarks need "
                         "two or more: film the face from the front and both sides")
    t_detect = time.process_time() - t_cpu

    # First triangulation (all 68, all detections): head frame, yaw and agreement.
    first = _triangulate_faces(dets, detected, np.arange(68), cams, config)
    if not np.all(np.isfinite(first.points[np.r_[27, 36:48, 57]])):
        raise CameraSolveError(f"the face's landmarks in {len(detected)} of {n} views do not "
                               "meet in 3D with its cameras", TRY_AGAIN)
    head_R, head_o = robust_head_frame(first.points)
    inner = INNER_LANDMARKS
    records = _keyframe_records(dets, detected, first, head_R, head_o, cams)
    coverage = _coverage(records, config)
    gated, widened = _gate(records, config)
    for k, rec in enumerate(records):
        rec["gated"] = k in gated
    final = _triangulate_faces(dets, gated, inner, cams, config)
    triangulated = np.full((68, 3), np.nan)
    triangulated[inner] = final.points
    if np.sum(np.all(np.isfinite(triangulated[inner]), axis=1)) < len(inner) // 2:
        raise CameraSolveError(f"the landmarks of the {len(gated)} confident views do not "
                               "triangulate with its cameras", TRY_AGAIN)
    # Head frame and eye distance from the final inner points (as in the calibration), a
    # missing one from the first pass.
    frame_from = triangulated.copy()
    lost = inner[~np.all(np.isfinite(triangulated[inner]), axis=1)]
    frame_from[lost] = first.points[lost]
    landmarks, correction = triangulated.copy(), None
    if config.convention_correction:
        offsets, correction = load_offsets()
        landmarks = correct(triangulated, offsets, frame_from)
    # A point whose inlier views barely differ in direction is uncertain along their rays
    # (a brow end seen from one side only): the coarse template stands in for it.
    noise_px = float(np.nanmedian(final.errors[final.inliers])) if final.inliers.any() else 1.0
    spread = final.spread(noise_px) / eye_distance(frame_from)
    uncertain = inner[~(spread <= config.max_point_spread)]
    landmarks[uncertain] = np.nan
    _must_be_a_face(landmarks)

    iris_doc = iris.triangulate_irises(dets, records, gated, cams, head_R, config)
    for k, det in enumerate(dets):
        if det is not None and det.irises is not None:
            records[k]["irises"] = {side: f.as_dict() for side, f in det.irises.items()}

    ears = _ear_module()
    ears_doc = _ears3d(video, cams, records, landmarks, ears, config)

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    doc2d = {"image_size": [cams.intrinsics.width, cams.intrinsics.height],
             "detector": DETECTOR,
             "ear_model": ears is not None, "gate_widened": widened,
             "config": config.model_dump(mode="json"), "keyframes": records}
    _write_json(out / LANDMARKS_2D, doc2d)
    _write_json(out / EARS_3D, ears_doc)
    doc3d = _landmarks3d_doc(cams, landmarks, correction, triangulated, gated, uncertain,
                             spread, final, head_R, head_o, iris_doc, len(detected), n,
                             coverage)
    doc3d["seconds"] = {"wall": round(time.perf_counter() - t_wall, 3),
                        "cpu": round(time.process_time() - t_cpu, 3),
                        "cpu_detection": round(t_detect, 3)}
    return Landmarks3d.model_validate(doc3d).write(out / LANDMARKS_3D)


def _write_json(path: Path, doc: dict) -> Path:
    tmp = path.with_name(path.name + ".part")
    tmp.write_text(json.dumps(doc, indent=1))
    tmp.replace(path)
    return path


# --------------------------------------------------------------------------- readers


def load_ears3d(path: str | Path) -> tuple[np.ndarray, np.ndarray, dict]:
    """Vertex ids (k,), points (k, 3) and the document of an ``ears3d.json`` (empty when
    the file is missing)."""
    path = Path(path)
    if not path.is_file():
        return np.zeros(0, np.int64), np.zeros((0, 3)), {"vertex_ids": [], "points": []}
    try:
        doc = json.loads(path.read_text())
        ids = np.asarray(doc["vertex_ids"], np.int64).reshape(-1)
        pts = np.asarray(doc["points"], float).reshape(-1, 3)
    except (ValueError, KeyError, TypeError) as exc:
        raise InputError(f"{path} is not an ears3d.json ({type(exc).__name__})") from None
    if len(ids) != len(pts):
        raise InputError(f"{path}: {len(ids)} vertex ids for {len(pts)} points")
    return ids, pts, doc


def run(inputs: Folders, out: Path, config: LandmarkConfig, params: dict) -> None:
    main(capture_in(inputs["video"]), inputs["poses"] / CAMERAS_JSON, out, config)


def models_digest() -> str:
    """The models and tables the stage runs, as part of its version: the ear model
    (retrained, or replaced through $FACECAP_EAR_MODELS), the face mesh's (mediapipe is
    installed apart from the other dependencies, so its version is not fixed by the
    package's), and the calibrated tables that turn mesh vertices into 3D landmarks (a
    recalibration changes every landmark)."""
    try:
        mesh = f"mediapipe-{version('mediapipe')}"
    except PackageNotFoundError:
        mesh = "no-mediapipe"
    tables = hashlib.sha256(MESH_TO_68_FILE.read_bytes() + OFFSETS_FILE.read_bytes())
    return f"ears-{ears.model_digest()}-{mesh}-tables-{tables.hexdigest()[:12]}"


STAGE = Stage("landmarks", version="8", inputs=("video", "poses"), work_seconds=4.0,
              section="landmarks", run=run, outputs=(LANDMARKS_2D, LANDMARKS_3D, EARS_3D),
              version_suffix=models_digest)
