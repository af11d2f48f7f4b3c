"""Training the ear detector (dlib HOG) and contour predictor (dlib ERT), and the
``facecap train-ears`` / ``python -m facecap.ear_training`` entry point."""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from facecap.ear_training.config import EarTrainingConfig
from facecap.ear_training.contour import (
    CONTOUR_FILE,
    DETECTOR_FILE,
    MODEL_FILES,
    PREDICTOR_FILE,
    SIDES,
    load_contour_file,
    write_contour_file,
)
from facecap.ear_training.render import (
    EarSample,
    grey,
    load_dataset,
    render_dataset,
    render_key,
    save_dataset,
)
from facecap.tasks.outputs import ResultWriter, check_results_folder
from facecap.tasks.runner import default_store_url
from facecap.tasks.scratch import process_scratch
from facecap_core.config import load_yaml
from facecap_core.errors import FacecapError, InputError
from facecap_core.settings import settings

# Imported where used: dlib (the trainer) only where a model is trained.


def iou(a, b) -> float:
    l, t = max(a[0], b[0]), max(a[1], b[1])
    r, btm = min(a[2], b[2]), min(a[3], b[3])
    inter = max(0, r - l) * max(0, btm - t)
    area = lambda x: max(0, x[2] - x[0]) * max(0, x[3] - x[1])  # noqa: E731
    union = area(a) + area(b) - inter
    return inter / union if union > 0 else 0.0


def train_detector(samples: list[EarSample], config: EarTrainingConfig, progress: bool):
    import dlib

    options = dlib.simple_object_detector_training_options()
    options.add_left_right_image_flips = False  # the model is for left-ear views only
    options.C = config.detector_c
    options.epsilon = config.detector_epsilon
    options.detection_window_size = int(config.detector_window_px ** 2 * config.box_aspect)
    options.num_threads = config.threads
    options.upsample_limit = 0
    options.be_verbose = progress
    images = [grey(s.image) for s in samples]
    boxes = [[dlib.rectangle(*s.box)] for s in samples]
    return dlib.train_simple_object_detector(images, boxes, options)


def predictor_boxes(detector, samples: list[EarSample]) -> tuple[list, int]:
    """The detector's box where it finds the ear (IoU >= 0.5), else the ground-truth box."""
    import dlib

    out, found = [], 0
    for s in samples:
        dets = detector(grey(s.image))
        best = max(dets, key=lambda r: iou((r.left(), r.top(), r.right(), r.bottom()), s.box),
                   default=None)
        if best is not None and iou((best.left(), best.top(), best.right(), best.bottom()),
                                    s.box) >= 0.5:
            out.append(best)
            found += 1
        else:
            out.append(dlib.rectangle(*s.box))
    return out, found


def train_predictor(samples: list[EarSample], boxes: list, config: EarTrainingConfig,
                    progress: bool):
    import dlib

    options = dlib.shape_predictor_training_options()
    options.cascade_depth = config.predictor_cascade_depth
    options.tree_depth = config.predictor_tree_depth
    options.num_trees_per_cascade_level = config.predictor_trees_per_level
    options.nu = config.predictor_nu
    options.oversampling_amount = config.predictor_oversampling
    options.oversampling_translation_jitter = config.predictor_translation_jitter
    options.feature_pool_size = config.predictor_feature_pool_size
    options.num_test_splits = config.predictor_test_splits
    options.num_threads = config.threads
    options.random_seed = str(config.seed)
    options.be_verbose = progress
    images = [grey(s.image) for s in samples]
    objects = [[dlib.full_object_detection(box, [dlib.point(int(round(x)), int(round(y)))
                                                 for x, y in s.points])]
               for s, box in zip(samples, boxes)]
    return dlib.train_shape_predictor(images, objects, options)


def score_detection(sample: EarSample, detection, min_iou: float = 0.5) -> dict:
    """Compare a detection (an ``EarDetection`` or None) with a view's ground truth.

    ``detected``: a box overlapping the ground-truth box with IoU >= ``min_iou``; ``nme``:
    mean distance of the visible contour points to the truth over the diagonal of the
    truth's tight bounding box (nan when not detected)."""
    if detection is None:
        return {"detected": False, "iou": 0.0, "nme": float("nan")}
    overlap = iou(detection.box, sample.box)
    err = np.linalg.norm(np.asarray(detection.points) - sample.points, axis=1)
    vis = sample.visible if sample.visible.any() else np.ones(len(err), bool)
    detected = overlap >= min_iou
    return {"detected": bool(detected), "iou": float(overlap),
            "nme": float(err[vis].mean() / sample.diagonal) if detected else float("nan")}


def sha256(path: str | Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def save_previews(samples: list[EarSample], folder: Path, count: int = 8) -> list[Path]:
    """Overlay PNGs of a few training views (box, contour, hidden points hollow)."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    step = max(1, len(samples) // count)
    for k, s in enumerate(samples[::step][:count]):
        img = cv2.cvtColor(s.image, cv2.COLOR_GRAY2BGR if s.image.ndim == 2 else
                           cv2.COLOR_RGB2BGR)
        draw_contour(img, s.points, s.visible, (0, 0, 255))
        cv2.rectangle(img, s.box[:2], s.box[2:], (0, 255, 0), 1)
        path = folder / f"train_{k:02d}_{s.side}_yaw{s.yaw_deg:.0f}.png"
        cv2.imwrite(str(path), img)
        paths.append(path)
    return paths


def draw_contour(img: np.ndarray, points: np.ndarray, visible: np.ndarray | None,
                 colour: tuple[int, int, int]) -> None:
    pts = np.round(points).astype(np.int32)
    cv2.polylines(img, [pts.reshape(-1, 1, 2)], False, colour, 1, cv2.LINE_AA)
    for i, p in enumerate(pts):
        filled = -1 if visible is None or visible[i] else 1
        cv2.circle(img, tuple(int(v) for v in p), 2, colour, filled, cv2.LINE_AA)


def train(out_dir: str | Path, config: EarTrainingConfig | None = None,
          progress: bool = True, extra_inputs: tuple = ()) -> Path:
    """Render the training set and train the ear detector and predictor into ``out_dir``.

    Writes ``ear_contour.json``, ``ear_detector.svm``, ``ear_predictor.dat``,
    ``training.json`` (config, counts, timings, sha256 of the model files),
    ``dataset.npz`` (the renders, reused by a later run with the same rendering settings)
    and ``previews/*.png``; returns ``out_dir``. They are made in this process's scratch
    folder and written through :class:`facecap.tasks.outputs.ResultWriter`: never through a
    link, never over an input (the ICT model, ``extra_inputs``), never outside ``out_dir``;
    a folder of the store or of facecap's own is refused before anything is rendered.
    """
    config = config or EarTrainingConfig()
    ict_model = config.ict_model or settings().ict_model
    if not ict_model:
        raise InputError("ear training needs the ICT Face Model: set ict_model or "
                         "FACECAP_ICT_MODEL to PATH/ict_face_model.npz")
    out = Path(out_dir)
    inputs = (ict_model, *extra_inputs)
    check_results_folder(out, default_store_url(),
                         [*MODEL_FILES, "training.json", "dataset.npz"], inputs)
    # Made in this process's scratch, then written as the reconstruction writes its results:
    # all at once, never through a link planted in ``out``, never over an input.
    with tempfile.TemporaryDirectory(dir=process_scratch()) as scratch:
        made = _train_into(Path(scratch), out, config, ict_model, progress)
        with ResultWriter(out, inputs) as writer:
            for name in made:
                writer.add(name, source=Path(scratch) / name)
            writer.commit()
    return out


def _train_into(scratch: Path, out: Path, config: EarTrainingConfig, ict_model,
                progress: bool) -> list[str]:
    """Every file of a training into the empty folder ``scratch`` (the renders of an earlier
    run in ``out`` reused when they are a plain file there); returns their names."""
    wall0, cpu0 = time.perf_counter(), time.process_time()
    timings: dict[str, dict] = {}
    last = [wall0, cpu0]

    def lap(name: str) -> None:
        w, c = time.perf_counter(), time.process_time()
        timings[name] = {"wall_s": round(w - last[0], 2), "cpu_s": round(c - last[1], 2)}
        last[:] = [w, c]

    write_contour_file(scratch / CONTOUR_FILE, config, ict_model)
    transfer = load_contour_file(scratch / CONTOUR_FILE)["ict"]
    lap("contour_fit")
    # The renders are kept (``dataset.npz``) so that retraining with other detector or
    # predictor settings does not render again (read only from a plain file, not a link).
    key = render_key(config)
    kept = out / "dataset.npz"
    samples = None if kept.is_symlink() else load_dataset(kept, key)
    made = [*MODEL_FILES, "training.json"]
    if samples is None:
        samples = render_dataset(config, ict_model, transfer, progress)
        if not samples:
            raise InputError("no usable ear views were rendered: widen the view ranges")
        previews = save_previews(samples, scratch / "previews")
        save_dataset(scratch / "dataset.npz", samples, key)
        made += ["dataset.npz", *(f"previews/{p.name}" for p in previews)]
    lap("render")
    detector = train_detector(samples, config, progress)
    detector.save(str(scratch / DETECTOR_FILE))
    lap("detector")
    boxes, found = predictor_boxes(detector, samples)
    lap("detector_on_training_set")
    predictor = train_predictor(samples, boxes, config, progress)
    predictor.save(str(scratch / PREDICTOR_FILE))
    lap("predictor")
    report = {
        "config": config.model_dump(mode="json"),
        "samples": len(samples),
        "samples_per_side": {s: sum(x.side == s for x in samples) for s in SIDES},
        "detector_training_recall": found / len(samples),
        "timings": timings,
        "total": {"wall_s": round(time.perf_counter() - wall0, 1),
                  "cpu_s": round(time.process_time() - cpu0, 1)},
        "sha256": {name: sha256(scratch / name) for name in MODEL_FILES},
        "bytes": {name: (scratch / name).stat().st_size for name in MODEL_FILES},
    }
    (scratch / "training.json").write_text(json.dumps(report, indent=1))
    return made


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m facecap.ear_training",
        description="Render ICT heads and train the ear detector + ear contour predictor.")
    parser.add_argument("--out", required=True, help="output folder for the model files")
    parser.add_argument("--config", help="EarTrainingConfig YAML (defaults otherwise)")
    parser.add_argument("--quiet", action="store_true", help="no progress output")
    args = parser.parse_args(argv)

    try:
        config = load_yaml(EarTrainingConfig, args.config) if args.config else EarTrainingConfig()
        out = train(args.out, config, progress=not args.quiet, extra_inputs=(args.config,))
    except FacecapError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    report = json.loads((out / "training.json").read_text())
    print(json.dumps({"out": str(out), "samples": report["samples"], "total": report["total"],
                      "sha256": report["sha256"]}, indent=1))
    return 0

