"""Benchmark of the ear detector + ear-contour predictor (issue 4, item 3).

    python benchmarks/bench_ears.py [--views 60] [--size 480] [--frames 24]
        [--subjects ict:0 ict:1 james] [--captures DIR ...] [--out out/bench_ears]
        [--ict-model PATH] [--james-contour JSON | --james-contour template]
        [--real-labels JSON] [--real-images DIR] [--real-only | --no-real]

Three parts; the first two on subjects never used for training (ICT identities 0 and 1, and
James), the third on real photos:

1. **Renders**: ``--views`` views per subject (sides at random) at yaw 45-100 deg, elevation
   -15..20 deg, roll +-10 deg, 300-550 mm from the head, ear contour 80-170 px tall in a
   ``--size`` square image, in random textured rooms (seeds distinct from training), with
   exposure, noise, blur and JPEG compression; ground truth as in training (projected
   contour points, ray-cast visibility).
2. **Captures**: frames of the shared synthetic 720p captures whose ground-truth camera is
   45-100 deg from frontal (``--frames`` per capture, spread over both sides); ground truth
   from the capture's GT cameras (with lens distortion) and the subject's 3D contour.
3. **Real photos**: the hand-labelled ears of ``--real-labels`` (default
   ``benchmarks/data/photo_set_31_ears.json``: 12 contour points per ear, by the definition
   of docs/ears.md, on photos of ``../shared/data/real/photo_set_31/images``, which are not
   in the repository; ``--real-images`` points elsewhere). The ground-truth box is built from
   the labelled points by the renders' rule. Besides detection and NME it counts false
   boxes: the detector is run on every photo of the folder for the side facing the camera
   (both sides on near-frontal photos) and every box that is not on a labelled ear (IoU < 0.5,
   or no ear labelled there) is one. Skipped with a notice when the folder is missing;
   ``--real-only`` runs this part alone.

The 3D contour of an ICT identity comes from the shipped ICT transfer (barycentrics).
James's scan has no ear geometry (his ears are texture on a flat, hair-covered surface), so
his contour is the hand-labelled one of ``--james-contour`` (default
``benchmarks/data/james_ear_contour.json``: 12 points per side on the ear his texture shows,
triangulated from labelled renders and snapped to the scan; how it was made and its
uncertainty are in the file's header and docs/ears.md) when that file is present.
``--james-contour template`` (or a missing file) gives the old ground truth: the contour of
the template fitted to the scan, which sits several millimetres above and behind the textured
ear; any other mesh subject gets that template fit too (cached in ``OUT/cache``). Each
subject's rooms and views are seeded by its place in the default subject list, so
``--subjects james`` draws the same James views as a full run.

Figures: detection rate (a box with IoU >= 0.5 against the ground-truth box; bar >= 90 %),
normalised mean error (mean distance of the visible contour points over the diagonal of
the ground-truth contour's bounding box, detected views only; bar <= 0.08), and seconds per
image (CPU and wall; wall under whatever load the machine has). Writes ``OUT/report.md``,
``OUT/results.json``, overlay PNGs of the worst cases and, for the real photos, one overlay
per labelled ear and per false box (``OUT/real/``: labels green, prediction red).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import facecap.ear_training as et  # noqa: E402
from facecap.ear_training.config import EarTrainingConfig  # noqa: E402
from facecap.synthetic import Room, load_gt_cameras, make_subject  # noqa: E402
from facecap.synthetic.config import SynthConfig  # noqa: E402
from facecap_core.camera import camera_center, project  # noqa: E402
from facecap_core.config import load_yaml  # noqa: E402
from facecap_core.landmarks.ears import (  # noqa: E402
    EAR_VERTEX_IDS,
    detect_ears,
    model_available,
    models_dir,
)
from facecap_core.render import RaycastScene  # noqa: E402
from facecap_core.template import Template  # noqa: E402

BARS = {"detection_rate": 0.90, "nme": 0.08}
ROOT = Path(__file__).resolve().parents[1]
DEFAULT_ICT = ROOT.parent / "shared/data/ict_face_model/ict_face_model.npz"
DEFAULT_REAL_LABELS = ROOT / "benchmarks/data/photo_set_31_ears.json"
DEFAULT_REAL_IMAGES = ROOT.parent / "shared/data/real/photo_set_31/images"
DEFAULT_JAMES_CONTOUR = ROOT / "benchmarks/data/james_ear_contour.json"
DEFAULT_CAPTURES = [ROOT / "out/captures" / f"{s}_1280x720_60fps_8s"
                    for s in ("ict_0", "ict_1", "james")]
SUBJECTS = ("ict:0", "ict:1", "james")


def load_hand_contour(path: Path) -> dict:
    """A hand-labelled 3D ear contour file (``benchmarks/data/james_ear_contour.json``): the
    12 points per side, head frame, mm."""
    doc = json.loads(Path(path).read_text())
    return {side: np.asarray(doc["contour"][side], float) for side in et.SIDES}


def subject_contours(subject, name: str, ict_transfer: dict, cache: Path,
                     hand: dict | None = None) -> dict:
    """The subject's 3D ear contours (head frame, mm) per side: the ICT transfer for an ICT
    identity, the hand-labelled file of ``hand[name]`` when there is one and it exists, else
    the contour of the template fitted to the mesh."""
    if name.startswith("ict:"):
        return {side: sp.on(subject.vertices) for side, sp in ict_transfer.items()}
    path = (hand or {}).get(name)
    if path is not None and Path(path).is_file():
        return load_hand_contour(path)
    path = cache / f"{name.replace(':', '_')}_ear_contour.npz"
    if path.is_file():
        with np.load(path) as z:
            return {side: z[side] for side in et.SIDES}
    template = Template.default()
    snapped = et.fitted_ear_contour(template, EAR_VERTEX_IDS, subject.vertices, subject.faces,
                                    subject.landmarks)
    contours = {side: sp.on(subject.vertices) for side, (sp, _) in snapped.items()}
    cache.mkdir(parents=True, exist_ok=True)
    np.savez(path, **contours)
    return contours


def run_detector(sample) -> tuple[dict, object]:
    wall, cpu = time.perf_counter(), time.process_time()
    det = detect_ears(sample.image, sample.side)
    score = et.score_detection(sample, det)
    score.update(fired=det is not None, wall_s=time.perf_counter() - wall,
                 cpu_s=time.process_time() - cpu,
                 side=sample.side, yaw_deg=round(sample.yaw_deg, 1))
    return score, det


YAW_BANDS = ((45, 60), (60, 80), (80, 101))
REAL_YAW_BANDS = ((0, 45),) + YAW_BANDS  # the photos' yaw: eyeballed guesses


def summarise(scores: list[dict], bands=YAW_BANDS) -> dict:
    det = np.array([s["detected"] for s in scores], bool)
    nme = np.array([s["nme"] for s in scores if s["detected"]], float)
    out = {"images": len(scores), "detection_rate": float(det.mean()) if len(det) else 0.0,
           "any_box_rate": float(np.mean([s["fired"] for s in scores])) if scores else 0.0,
           "cpu_s_per_image": float(np.mean([s["cpu_s"] for s in scores])),
           "wall_s_per_image": float(np.mean([s["wall_s"] for s in scores]))}
    if len(nme):
        out.update(nme_mean=float(nme.mean()), nme_median=float(np.median(nme)),
                   nme_p90=float(np.percentile(nme, 90)), nme_max=float(nme.max()))
    else:
        out.update(nme_mean=float("nan"), nme_median=float("nan"), nme_p90=float("nan"),
                   nme_max=float("nan"))
    for lo, hi in bands:
        sel = [s for s in scores if lo <= s["yaw_deg"] < hi]
        if sel:
            d = np.array([s["detected"] for s in sel])
            e = [s["nme"] for s in sel if s["detected"]]
            out[f"yaw_{lo}_{min(hi, 100)}"] = {
                "images": len(sel), "detection_rate": float(d.mean()),
                "nme_mean": float(np.mean(e)) if e else float("nan")}
    return out


def overlay(sample, det, score: dict) -> np.ndarray:
    img = cv2.cvtColor(sample.image, cv2.COLOR_RGB2BGR) if sample.image.ndim == 3 else \
        cv2.cvtColor(sample.image, cv2.COLOR_GRAY2BGR)
    et.draw_contour(img, sample.points, sample.visible, (0, 255, 0))
    if det is not None:
        et.draw_contour(img, det.points, None, (0, 0, 255))
        cv2.rectangle(img, det.box[:2], det.box[2:], (0, 0, 255), 1)
    cv2.putText(img, f"{sample.side} yaw {sample.yaw_deg:.0f} nme {score['nme']:.3f}", (5, 18),
                cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 0), 1)
    return img


def subject_seed(subjects, name: str) -> int:
    """A subject's seed for its rooms and views: its place in the default ``SUBJECTS`` (so a
    run on some of them draws the same views as the full run), else after them."""
    if name in SUBJECTS:
        return SUBJECTS.index(name)
    return len(SUBJECTS) + list(subjects).index(name)


def bench_renders(subjects, views: int, size: int, ict_model: str, ict_transfer: dict,
                  out: Path, hand: dict | None = None) -> dict:
    config = EarTrainingConfig(yaw_deg=(45.0, 100.0), ear_height_px=(80.0, 170.0))
    results = {}
    for name in subjects:
        k = subject_seed(subjects, name)
        subject = make_subject(SynthConfig(subject=name, ict_model=ict_model))
        contours = subject_contours(subject, name, ict_transfer, out / "cache", hand)
        # Rooms and draws seeded apart from training (which uses [seed, 7, k] and [seed, id]).
        room = Room.random(np.random.default_rng([2024, k]))
        renderer = et.EarRenderer(subject, contours, room)
        rng = np.random.default_rng([4242, k])
        scores, worst = [], []
        while len(scores) < views:
            view = et.draw_views(config, 1, rng)[0]
            sample = renderer.view(**view, size=size, rng=rng)
            if not et.usable(sample, size, 0.5):
                continue
            renderer.render(sample, rng, mirror_right=False)
            score, det = run_detector(sample)
            scores.append(score)
            worst.append((-np.inf if not score["detected"] else -score["nme"], len(worst),
                          sample, det, score))
        worst.sort(key=lambda w: w[:2])  # misses first, then the largest errors
        for i, (_, _, sample, det, score) in enumerate(worst[:4]):
            cv2.imwrite(str(out / f"worst_{name.replace(':', '_')}_{i}.png"),
                        overlay(sample, det, score))
        results[name] = {**summarise(scores), "views": scores}
        print(f"renders {name}: {json.dumps(summarise(scores))}", flush=True)
    return results


def capture_samples(folder: Path, frames: int, ict_model: str, ict_transfer: dict, out: Path,
                    hand: dict | None = None):
    """Ground-truth ear views of a capture's frames 45-100 deg from frontal."""
    from facecap_core.video import read_frames

    config = load_yaml(SynthConfig, folder / "gt" / "config.yaml")
    if config.subject.startswith("ict:"):
        config = config.model_copy(update={"ict_model": config.ict_model or ict_model})
    subject = make_subject(config)
    contours = subject_contours(subject, config.subject, ict_transfer, out / "cache", hand)
    intr, poses = load_gt_cameras(folder / "gt" / "cameras.json")
    scene = RaycastScene()
    scene.add(subject.vertices, subject.faces)
    picks = []
    for f in poses:
        c = camera_center(f["R"], f["t"])
        yaw = np.degrees(np.arctan2(abs(c[0]), c[2]))
        if 45 <= yaw <= 100:
            picks.append((f, "left" if c[0] > 0 else "right", float(yaw)))
    chosen = []
    for side in et.SIDES:
        same = [p for p in picks if p[1] == side]
        if same:
            idx = np.linspace(0, len(same) - 1, min(frames // 2, len(same))).round().astype(int)
            chosen += [same[i] for i in np.unique(idx)]
    images = read_frames(folder / "video.mp4", [p[0]["index"] for p in chosen])
    samples = []
    for f, side, yaw in chosen:
        uv, _ = project(contours[side], f["R"], f["t"], intr)
        vis = et.visible_points(scene, camera_center(f["R"], f["t"]), contours[side])
        box = et.ear_box(uv, 0.75, 0.15)
        lo, hi = uv.min(0), uv.max(0)
        samples.append(et.EarSample(images[f["index"]], uv, vis, box,
                                    (lo[0], lo[1], hi[0], hi[1]), side, yaw, False))
    return config.subject, samples


def bench_captures(folders, frames: int, ict_model: str, ict_transfer: dict, out: Path,
                   hand: dict | None = None) -> dict:
    results = {}
    for folder in folders:
        if not (folder / "gt" / "render.json").is_file():
            print(f"captures: {folder} missing, skipped", flush=True)
            continue
        name, samples = capture_samples(folder, frames, ict_model, ict_transfer, out, hand)
        scores = []
        for i, sample in enumerate(samples):
            score, det = run_detector(sample)
            scores.append(score)
            if i % max(1, len(samples) // 3) == 0:
                cv2.imwrite(str(out / f"capture_{folder.name}_{i:02d}.png"),
                            overlay(sample, det, score))
        results[folder.name] = {"subject": name, **summarise(scores), "views": scores}
        print(f"capture {folder.name}: {json.dumps(summarise(scores))}", flush=True)
    return results


def load_real_labels(path: Path) -> dict:
    """The hand-labelled real-photo ear contours (``benchmarks/data/*_ears.json``)."""
    doc = json.loads(path.read_text())
    for ear in doc["ears"]:
        ear["points"] = np.asarray(ear["points"], float)
        ear["visible"] = np.asarray(ear["visible"], bool)
    return doc


def real_sample(image: np.ndarray, ear: dict) -> et.EarSample:
    """A labelled ear as an ``EarSample``: the ground-truth box by the renders' rule (the
    points' extent, fixed aspect, padding per side: ``EarTrainingConfig``)."""
    config = EarTrainingConfig()
    pts = ear["points"]
    lo, hi = pts.min(0), pts.max(0)
    return et.EarSample(image, pts, ear["visible"],
                        et.ear_box(pts, config.box_aspect, config.box_padding),
                        (lo[0], lo[1], hi[0], hi[1]), ear["side"],
                        float(ear.get("yaw_deg_guess", float("nan"))), False)


def along_rim(rim: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each point's distance to the labelled rim (a polyline) and its position along it
    (0 = helix root, 1 = lobe bottom): tells a point off the rim from one on the rim but
    elsewhere along it."""
    a, d = rim[:-1], np.diff(rim, axis=0)
    length = np.maximum((d ** 2).sum(1), 1e-12)
    t = np.clip(((points[:, None] - a) * d).sum(2) / length, 0, 1)  # (K, S)
    dist = np.linalg.norm(a + t[..., None] * d - points[:, None], axis=2)
    seg = np.argmin(dist, axis=1)
    arc = np.r_[0.0, np.cumsum(np.sqrt(length))]
    k = np.arange(len(points))
    return dist[k, seg], (arc[seg] + t[k, seg] * np.sqrt(length[seg])) / arc[-1]


def real_overlay(sample, det, score: dict, name: str, zoom: int = 4) -> np.ndarray:
    """The whole photo (labels green, prediction red, boxes thin) beside an enlarged crop
    around the ear."""
    img = cv2.cvtColor(sample.image, cv2.COLOR_RGB2BGR)
    boxes = [sample.box] + ([det.box] if det is not None else [])
    full = img.copy()
    cv2.rectangle(full, sample.box[:2], sample.box[2:], (0, 255, 0), 1)
    if det is not None:
        cv2.rectangle(full, det.box[:2], det.box[2:], (0, 0, 255), 1)
    l = max(0, min(b[0] for b in boxes) - 10)
    t = max(0, min(b[1] for b in boxes) - 10)
    r = min(img.shape[1], max(b[2] for b in boxes) + 10)
    b = min(img.shape[0], max(b[3] for b in boxes) + 10)
    crop = cv2.resize(img[t:b, l:r], None, fx=zoom, fy=zoom, interpolation=cv2.INTER_CUBIC)
    shift = np.array([l, t], float)

    def up(p):
        return (np.asarray(p, float) - shift + 0.5) * zoom - 0.5

    et.draw_contour(crop, up(sample.points), sample.visible, (0, 255, 0))
    gt_box = np.round(up(np.reshape(sample.box, (2, 2)))).astype(int)
    cv2.rectangle(crop, tuple(gt_box[0]), tuple(gt_box[1]), (0, 255, 0), 1)
    if det is not None:
        et.draw_contour(crop, up(det.points), None, (0, 0, 255))
        det_box = np.round(up(np.reshape(det.box, (2, 2)))).astype(int)
        cv2.rectangle(crop, tuple(det_box[0]), tuple(det_box[1]), (0, 0, 255), 1)
    for pts, colour in ((sample.points, (0, 160, 0)),
                        (det.points if det is not None else (), (0, 0, 200))):
        for i, p in enumerate(up(pts) if len(pts) else ()):
            cv2.putText(crop, str(i + 1), (int(p[0]) + 4, int(p[1]) - 4),
                        cv2.FONT_HERSHEY_SIMPLEX, 0.4, colour, 1, cv2.LINE_AA)
    text = (f"{name} {sample.side} yaw~{sample.yaw_deg:.0f} iou {score['iou']:.2f} "
            f"nme {score['nme']:.3f}" + ("" if det is not None else " NO BOX"))
    cv2.putText(full, text, (5, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 0), 1,
                cv2.LINE_AA)
    h = max(full.shape[0], crop.shape[0])
    pad = lambda a: cv2.copyMakeBorder(a, 0, h - a.shape[0], 0, 0,  # noqa: E731
                                       cv2.BORDER_CONSTANT, value=(255, 255, 255))
    return np.hstack([pad(full), pad(crop)])


def bench_real(labels_path: Path, images: Path, out: Path) -> dict:
    """Hand-labelled real photos: detection, any box and NME on the labelled ears, and the
    boxes returned where no ear is labelled (every photo, the side(s) facing the camera)."""
    doc = load_real_labels(labels_path)
    folder = out / "real"
    folder.mkdir(parents=True, exist_ok=True)
    labelled = {(e["file"], e["side"]): e for e in doc["ears"]}
    scores = []
    for (file, side), ear in sorted(labelled.items()):
        image = cv2.cvtColor(cv2.imread(str(images / file)), cv2.COLOR_BGR2RGB)
        sample = real_sample(image, ear)
        score, det = run_detector(sample)
        score.update(file=file, box=list(sample.box),
                     det_box=list(det.box) if det is not None else None,
                     det_score=det.score if det is not None else None,
                     points_error_px=(np.linalg.norm(det.points - sample.points, axis=1)
                                      .round(1).tolist() if det is not None else None))
        if det is not None and score["detected"]:
            dist, pos = along_rim(np.asarray(ear.get("rim_trace", ear["points"]), float),
                                  det.points)
            score.update(rim_nme=float(dist.mean() / sample.diagonal),
                         rim_dist_px=dist.round(1).tolist(), rim_position=pos.round(3).tolist())
        scores.append(score)
        cv2.imwrite(str(folder / f"{Path(file).stem}_{side}.png"),
                    real_overlay(sample, det, score, Path(file).stem))
    # Every photo, the side facing the camera (both for near-frontal ones): a box where no
    # ear is labelled, or one that misses the labelled ear (IoU < 0.5), is a false box.
    false_boxes, runs = [], 0
    for file in sorted(p.name for p in images.iterdir() if p.suffix.lower() in (".jpg", ".png")):
        facing = doc.get("facing", {}).get(Path(file).stem.removeprefix("img_"), "frontal")
        image = None
        for side in (et.SIDES if facing == "frontal" else (facing,)):
            if (file, side) in labelled:
                s = next(s for s in scores if s["file"] == file and s["side"] == side)
                runs += 1
                if s["fired"] and not s["detected"]:
                    false_boxes.append({"file": file, "side": side, "labelled": True,
                                        "box": s["det_box"], "score": s["det_score"],
                                        "iou": s["iou"]})
                continue
            if image is None:
                image = cv2.cvtColor(cv2.imread(str(images / file)), cv2.COLOR_BGR2RGB)
            det = detect_ears(image, side)
            runs += 1
            if det is not None:
                false_boxes.append({"file": file, "side": side, "labelled": False,
                                    "box": list(det.box), "score": det.score})
                img = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
                et.draw_contour(img, det.points, None, (0, 0, 255))
                cv2.rectangle(img, det.box[:2], det.box[2:], (0, 0, 255), 1)
                cv2.imwrite(str(folder / f"unlabelled_{Path(file).stem}_{side}.png"), img)
    on_rim = [s for s in scores if "rim_nme" in s]
    result = {"labels": str(labels_path), "images_dir": str(images),
              **summarise(scores, REAL_YAW_BANDS),
              "rim_nme_mean": float(np.mean([s["rim_nme"] for s in on_rim]))
              if on_rim else float("nan"),
              "point_error_px_mean": np.mean([s["points_error_px"] for s in on_rim], axis=0)
              .round(1).tolist() if on_rim else [],
              "position_of_first_last": np.mean([np.array(s["rim_position"])[[0, -1]]
                                                 for s in on_rim], axis=0).round(3).tolist()
              if on_rim else [],
              "views": scores, "detector_runs": runs, "false_boxes": false_boxes,
              "not_labelled": doc.get("not_labelled", [])}
    print(f"real {labels_path.stem}: {json.dumps(summarise(scores, REAL_YAW_BANDS))}; "
          f"false boxes {len(false_boxes)} of {runs} runs", flush=True)
    return result


def fmt(x: float, pct: bool = False) -> str:
    if x != x:
        return "–"
    return f"{100 * x:.1f} %" if pct else f"{x:.3f}"


def report(results: dict, args, path: Path) -> Path:
    lines = ["# Ear detector + contour predictor benchmark", "",
             f"Models: `{results['models']}`; command: `{results['command']}`", "",
             f"James's ground-truth contour: {results.get('james_contour', 'template fit')}.", "",
             "Detection: box IoU >= 0.5 with the ground-truth box (any box: the detector "
             "returned a box at all). NME: mean error of the "
             "visible contour points / diagonal of the ground-truth contour's bounding box, "
             "over detected images. Seconds per image: wall under the machine's load at "
             "the time, and CPU.", "",
             "| set | images | detection | any box | NME mean | NME median | NME p90 "
             "| s/image (wall) | s/image (CPU) |", "|---|---|---|---|---|---|---|---|---|"]
    for part in ("renders", "captures"):
        for name, r in results[part].items():
            lines.append(f"| {part}: {name} | {r['images']} | {fmt(r['detection_rate'], True)} "
                         f"| {fmt(r['any_box_rate'], True)} | {fmt(r['nme_mean'])} "
                         f"| {fmt(r['nme_median'])} | {fmt(r['nme_p90'])} "
                         f"| {r['wall_s_per_image']:.3f} | {r['cpu_s_per_image']:.3f} |")
    real = results.get("real")
    if real:
        lines.append(f"| real photos: {Path(real['labels']).stem} | {real['images']} "
                     f"| {fmt(real['detection_rate'], True)} | {fmt(real['any_box_rate'], True)} "
                     f"| {fmt(real['nme_mean'])} | {fmt(real['nme_median'])} "
                     f"| {fmt(real['nme_p90'])} | {real['wall_s_per_image']:.3f} "
                     f"| {real['cpu_s_per_image']:.3f} |")
    if results["renders"]:
        lines += ["", "By yaw (renders): detection rate / NME mean", ""]
    for name, r in results["renders"].items():
        parts = [f"{k[4:].replace('_', '-')}°: {fmt(v['detection_rate'], True)} / "
                 f"{fmt(v['nme_mean'])}" for k, v in r.items() if k.startswith("yaw_")]
        lines.append(f"- {name}: " + "; ".join(parts))
    held = [results["renders"][s] for s in ("ict:0", "ict:1") if s in results["renders"]]
    if held:
        rate = np.mean([r["detection_rate"] for r in held])
        nme = np.mean([r["nme_mean"] for r in held])
        lines += ["", f"Bars (held-out ICT renders): detection {fmt(rate, True)} (>= 90 %: "
                  f"{'met' if rate >= BARS['detection_rate'] else 'NOT met'}), NME {fmt(nme)} "
                  f"(<= 0.08: {'met' if nme <= BARS['nme'] else 'NOT met'})."]
    if real:
        lines += real_report(real)
    path.write_text("\n".join(lines) + "\n")
    return path


def real_report(real: dict) -> list[str]:
    """The real-photo section of the report: per ear, false boxes, ears left unlabelled."""
    lines = ["", f"## Real photos ({real['images_dir']})", "",
             f"Hand-labelled ears (labels: `{real['labels']}`; yaw: eyeballed guess). "
             "By yaw: " + "; ".join(
                 f"{k[4:].replace('_', '-')}°: {v['images']} ears, "
                 f"{fmt(v['detection_rate'], True)} / {fmt(v['nme_mean'])}"
                 for k, v in real.items() if k.startswith("yaw_")) + ".", "",
             "NME against the labelled points, and *rim NME*: the predicted points' mean "
             "distance to the labelled rim (the hand-traced polyline) over the same diagonal, "
             "blind to where along the rim a point sits; *reach*: where the predicted first and "
             "last points fall along the labelled rim (0 = helix root, 1 = lobe bottom).", "",
             "| photo | side | yaw | box | IoU | score | NME | rim NME | reach | "
             "worst point (px) |",
             "|---|---|---:|---|---:|---:|---:|---:|---|---|"]
    for v in real["views"]:
        err = v["points_error_px"]
        worst = f"{int(np.argmax(err)) + 1}: {max(err):.1f}" if err else "–"
        state = ("detected" if v["detected"] else "wrong place" if v["fired"] else "none")
        score = "–" if v["det_score"] is None else f"{v['det_score']:.2f}"
        reach = (f"{v['rim_position'][0]:.2f}–{v['rim_position'][-1]:.2f}"
                 if "rim_position" in v else "–")
        lines.append(f"| {v['file']} | {v['side']} | {v['yaw_deg']:.0f} | {state} "
                     f"| {v['iou']:.2f} | {score} | {fmt(v['nme'])} "
                     f"| {fmt(v.get('rim_nme', float('nan')))} | {reach} | {worst} |")
    if real["point_error_px_mean"]:
        first, last = real["position_of_first_last"]
        lines += ["", f"Detected ears: rim NME mean {fmt(real['rim_nme_mean'])}; mean error "
                  "per point (px, 1 = helix root … 12 = lobe bottom): "
                  + ", ".join(f"{e:.1f}" for e in real["point_error_px_mean"])
                  + f"; predicted contour from {first:.2f} to {last:.2f} of the labelled rim "
                  "on average."]
    false = real["false_boxes"]
    lines += ["", f"False boxes (every photo, the side facing the camera, both sides on "
              f"near-frontal ones; a box not on a labelled ear): {len(false)} of "
              f"{real['detector_runs']} detector runs" + (":" if false else "."), ""]
    lines += [f"- {f['file']} {f['side']}: box {f['box']}, score {f['score']:.2f}"
              + (f", IoU {f['iou']:.2f} with the labelled ear" if f["labelled"]
                 else ", no ear labelled there") for f in false]
    if real["not_labelled"]:
        lines += ["", "Visible ears not labelled (doubt):", ""]
        lines += [f"- {n['file']} ({n['side']}): {n['reason']}" for n in real["not_labelled"]]
    return lines


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--views", type=int, default=60, help="render views per subject")
    parser.add_argument("--size", type=int, default=480, help="render size (px, square)")
    parser.add_argument("--frames", type=int, default=24, help="frames per capture")
    parser.add_argument("--subjects", nargs="*", default=list(SUBJECTS))
    parser.add_argument("--captures", nargs="*", type=Path, default=DEFAULT_CAPTURES)
    parser.add_argument("--out", type=Path, default=ROOT / "out/bench_ears")
    parser.add_argument("--ict-model", default=os.environ.get("FACECAP_ICT_MODEL",
                                                              str(DEFAULT_ICT)))
    parser.add_argument("--james-contour", default=str(DEFAULT_JAMES_CONTOUR),
                        help="James's hand-labelled 3D ear contour (JSON), or 'template' for "
                             "the contour of the template fitted to his scan")
    parser.add_argument("--real-labels", type=Path, default=DEFAULT_REAL_LABELS,
                        help="hand-labelled ears on real photos (JSON)")
    parser.add_argument("--real-images", type=Path, default=DEFAULT_REAL_IMAGES,
                        help="folder of the labelled photos (not in the repository)")
    which = parser.add_mutually_exclusive_group()
    which.add_argument("--real-only", action="store_true",
                       help="only the real photos (no renders, no captures)")
    which.add_argument("--no-real", action="store_true", help="skip the real photos")
    args = parser.parse_args(argv)
    if not model_available():
        print(f"no ear model in {models_dir()}", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    ict_transfer = et.load_contour_file(models_dir() / et.CONTOUR_FILE)["ict"]
    hand = {}
    if args.james_contour != "template":
        if Path(args.james_contour).is_file():
            hand["james"] = Path(args.james_contour)
        else:
            print(f"james contour: {args.james_contour} missing, the template fit is used",
                  flush=True)
    results = {"models": str(models_dir()),
               "command": "python benchmarks/bench_ears.py " + " ".join(argv or sys.argv[1:]),
               "james_contour": (f"hand-labelled, `{hand['james']}`" if hand else
                                 "template fitted to the scan"),
               "renders": {}, "captures": {}}
    if not args.real_only:
        results["renders"] = bench_renders(args.subjects, args.views, args.size,
                                           args.ict_model, ict_transfer, args.out, hand)
        results["captures"] = bench_captures(args.captures, args.frames, args.ict_model,
                                             ict_transfer, args.out, hand)
    if not args.no_real:
        if not args.real_images.is_dir():
            print(f"real photos: {args.real_images} missing, skipped", flush=True)
        elif not args.real_labels.is_file():
            print(f"real photos: labels {args.real_labels} missing, skipped", flush=True)
        else:
            results["real"] = bench_real(args.real_labels, args.real_images, args.out)
    (args.out / "results.json").write_text(json.dumps(results, indent=1))
    path = report(results, args, args.out / "report.md")
    print(path.read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
