"""Face landmark detectors compared: facecap's (MediaPipe's face mesh, ``facecap_core/face.py``)
and dlib's 68-point predictor (``benchmarks/dlib68.py``; measured only when installed by hand).

    python benchmarks/bench_landmark_detectors.py [--captures DIR ...] [--real NAME ...]
        [--max-yaw 30] [--out out/bench_landmark_detectors]

* **Renders** (default: the 1280x720 sweeps that ``bench_scale.py --size 1280x720 --out
  out/bench_scale_720`` renders of ict:200-205 and ``james``, none used for calibration): each
  frame within ``--max-yaw`` of frontal, the 68 points against the projected ground-truth
  landmarks, median px per group (jaw, brows, nose, eyes, mouth, inner 51); and the share of
  all frames (yaw -50..50 degrees) where a face is found.
* **Real photos** (``../shared/data/real``): the share of images with a face; with cameras
  (``photo_set_31``: the pose stage's, ``--real-cameras``), the agreement across views: the
  inner points of every detection triangulated robustly (as the landmark stage does), the
  median reprojection error of each view's inner points, px and relative to its face box.

Writes OUT/report.md and OUT/results.json.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import dlib68  # noqa: E402

from facecap.synthetic import load_gt_cameras  # noqa: E402
from facecap_core import face  # noqa: E402
from facecap_core.camera import camera_center, project  # noqa: E402
from facecap_core.landmarks.stage import LandmarkConfig  # noqa: E402
from facecap_core.landmarks.triangulate import box_size, triangulate  # noqa: E402
from facecap_core.meshio import load_landmarks  # noqa: E402
from facecap_core.pose.cameras_json import read_cameras_json  # noqa: E402
from facecap_core.template import INNER_LANDMARKS  # noqa: E402
from facecap_core.video import iter_frames  # noqa: E402

GROUPS = {"jaw": np.r_[0:17], "brows": np.r_[17:27], "nose": np.r_[27:36],
          "eyes": np.r_[36:48], "mouth": np.r_[48:68], "inner 51": INNER_LANDMARKS}
SHARED = ROOT.parent / "shared" / "data" / "real"
CAPTURES = sorted((ROOT / "out/bench_scale_720/captures").glob("*"))
REAL = ["photo_set_31", "frontal_small_motion", "head_turn_fixed_camera"]
REAL_CAMERAS = {"photo_set_31": ROOT / "out/real_check/cameras.json"}


def detectors() -> dict:
    """name -> image -> (68 points, box) or None."""
    def mediapipe(image):
        det = face.detect(image)
        return None if det is None else (det.points, det.box)

    found = {"mediapipe": mediapipe}
    if dlib68.available():
        def dlib(image):
            det = dlib68.detect(image)
            return None if det is None else (det[0], det[2])

        found["dlib"] = dlib
    return found


def render_errors(capture: Path, detect, max_yaw: float) -> dict:
    intr, poses = load_gt_cameras(capture / "gt" / "cameras.json")
    truth = load_landmarks(capture / "gt" / "landmarks.json")
    errors, frames, detected, seconds = [], 0, 0, 0.0
    for frame, pose in zip(iter_frames(capture / "video.mp4"), poses):
        frames += 1
        start = time.perf_counter()
        found = detect(frame.image)
        seconds += time.perf_counter() - start
        if found is None:
            continue
        detected += 1
        c = camera_center(pose["R"], pose["t"])
        if abs(np.degrees(np.arctan2(c[0], c[2]))) > max_yaw:
            continue
        uv, _ = project(truth, pose["R"], pose["t"], intr)
        errors.append(np.linalg.norm(found[0] - uv, axis=1))
    e = np.array(errors)
    return {"frames": frames, "detected": detected, "frontal_frames": len(e),
            "ms_per_frame": 1000 * seconds / max(frames, 1),
            "median_px": {g: float(np.median(e[:, i])) for g, i in GROUPS.items()} if len(e)
            else {}}


def real_agreement(name: str, detect, cameras: Path | None) -> dict:
    path = SHARED / name
    source = path / "images" if (path / "images").is_dir() else path / "video.mp4"
    step = 5 if source.suffix == ".mp4" else 1
    found, total = {}, 0
    for frame in iter_frames(source):
        if frame.index % step:
            continue
        total += 1
        det = detect(frame.image)
        if det is not None:
            found[frame.index] = det
    row = {"images": total, "detected": len(found)}
    if cameras is None or not cameras.is_file():
        return row
    cams = read_cameras_json(cameras)
    views = [k for k, i in enumerate(cams.frame_indices) if i in found]
    uv = np.stack([found[cams.frame_indices[k]][0][INNER_LANDMARKS] for k in views])
    size = np.array([box_size(found[cams.frame_indices[k]][1]) for k in views])
    config = LandmarkConfig()
    tri = triangulate(uv, cams.R[views], cams.t[views], cams.intrinsics,
                      config.outlier_threshold * size, config.huber * size, 2,
                      config.min_parallax_deg)
    per_view = np.nanmedian(tri.errors, axis=1)
    row.update(views=len(views), reprojection_px=float(np.nanmedian(per_view)),
               reprojection_rel=float(np.nanmedian(per_view / size)),
               within_gate=int(np.sum(per_view / size <= config.gate_max_reprojection)))
    return row


def report(results: dict) -> str:
    names = list(results["detectors"])
    lines = ["# Face landmark detectors", "",
             f"Renders: frames within {results['max_yaw']:g}° of frontal, median px from the "
             "projected ground-truth landmarks; found: frames with a face / all (±50°).", "",
             "| capture | detector | jaw | brows | nose | eyes | mouth | inner 51 | found | "
             "ms/frame |", "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for capture, rows in results["renders"].items():
        for name in names:
            r = rows[name]
            cells = " | ".join(f"{r['median_px'].get(g, float('nan')):.2f}" for g in GROUPS)
            lines.append(f"| {capture} | {name} | {cells} | {r['detected']}/{r['frames']} | "
                         f"{r['ms_per_frame']:.0f} |")
    for name in names:
        med = {g: np.median([rows[name]["median_px"][g] for rows in results["renders"].values()
                             if rows[name]["median_px"]]) for g in GROUPS}
        lines.append(f"| **median** | {name} | "
                     + " | ".join(f"**{med[g]:.2f}**" for g in GROUPS) + " | | |")
    lines += ["", "Real photos: faces found; with cameras, the inner points' median "
              "reprojection error per view against their robust triangulation (px, and per "
              "face box size; views within the landmark gate's 0.02).", "",
              "| capture | detector | found | reprojection px | relative | within gate |",
              "|---|---|---:|---:|---:|---:|"]
    for capture, rows in results["real"].items():
        for name in names:
            r = rows[name]
            extra = (f"{r['reprojection_px']:.2f} | {r['reprojection_rel']:.4f} | "
                     f"{r['within_gate']}/{r['views']}" if "views" in r else "– | – | –")
            lines.append(f"| {capture} | {name} | {r['detected']}/{r['images']} | {extra} |")
    return "\n".join(lines) + "\n"


def main() -> Path:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--captures", nargs="*", type=Path, default=CAPTURES)
    ap.add_argument("--real", nargs="*", default=REAL)
    ap.add_argument("--real-cameras", nargs="*", default=[],
                    help="NAME=cameras.json pairs (default: photo_set_31's reconstruction in "
                         "out/real_check)")
    ap.add_argument("--max-yaw", type=float, default=30.0)
    ap.add_argument("--out", type=Path, default=ROOT / "out/bench_landmark_detectors")
    args = ap.parse_args()
    cameras = dict(REAL_CAMERAS)
    cameras.update({k: Path(v) for k, v in (p.split("=", 1) for p in args.real_cameras)})
    found = detectors()
    if "dlib" not in found:
        print("dlib's 68-point model is not installed: measuring facecap's detector alone "
              "(benchmarks/dlib68.py says how to add it)")
    results = {"detectors": list(found), "max_yaw": args.max_yaw, "renders": {}, "real": {}}
    for capture in args.captures:
        if not (capture / "gt" / "render.json").is_file():
            print(f"skipping {capture}: not rendered")
            continue
        results["renders"][capture.name] = {n: render_errors(capture, d, args.max_yaw)
                                            for n, d in found.items()}
        print(capture.name, {n: round(r["median_px"].get("inner 51", np.nan), 2)
                             for n, r in results["renders"][capture.name].items()}, flush=True)
    for name in args.real:
        if not (SHARED / name).is_dir():
            print(f"skipping {name}: not in {SHARED}")
            continue
        results["real"][name] = {n: real_agreement(name, d, cameras.get(name))
                                 for n, d in found.items()}
        print(name, results["real"][name], flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(results, indent=1))
    text = report(results)
    print(text)
    path = args.out / "report.md"
    path.write_text(text)
    return path


if __name__ == "__main__":
    main()
