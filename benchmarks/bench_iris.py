"""Iris localisation in images against the renderer's truth: pupil-centre error and horizontal
iris-diameter error in pixels.

    python benchmarks/bench_iris.py [--captures out/bench_scale/captures] [--max-yaw 15]
        [--methods limbus mediapipe]

On each synthetic capture (``facecap synth`` folders, e.g. those ``bench_scale.py`` renders):
every second frame whose camera is within ``--max-yaw`` degrees of frontal; the face and its
68 points (:func:`facecap_core.face.detect`), then each iris found by

* ``limbus``: :func:`iris_limbus.fit_iris` (a circle on the lateral limbus arcs near the
  eye points; not used by the pipeline);
* ``mediapipe``: :func:`facecap_core.landmarks.iris.detect_irises` (the face mesh's iris
  points, the pupil refined to the dark centroid; what the landmark stage uses);
  ``mediapipe raw``: the same with MediaPipe's own iris centre; ``mediapipe+limbus``: the
  limbus fit started from MediaPipe's iris.

Truth: the renderer paints each iris as a disk of the subject's ``iris_diameter_mm`` around
the gaze axis (``gt/subject.json``: ``pupils_mm``); the pupil and the limbus's horizontal ends
are projected with the frame's camera. Printed per method: found / tried eyes, median and
95th-percentile pupil error (px), and the diameter error (px and %: mean, RMS).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from iris_limbus import LEFT_EYE, RIGHT_EYE, fit_iris  # noqa: E402

from facecap.synthetic import load_gt_cameras  # noqa: E402
from facecap_core.camera import camera_center, project  # noqa: E402
from facecap_core.face import detect  # noqa: E402
from facecap_core.landmarks import iris  # noqa: E402
from facecap_core.video import iter_frames  # noqa: E402


def truth(folder: Path, frame: dict, intr) -> dict:
    """Projected pupil and horizontal iris diameter (px) of each eye in one frame."""
    subject = json.loads((folder / "gt" / "subject.json").read_text())
    radius = 0.5 * subject["iris_diameter_mm"]
    out = {}
    for side, pupil in subject["pupils_mm"].items():
        pupil = np.asarray(pupil, float)
        # The limbus lies behind the corneal front by the sagitta of the eyeball's sphere.
        ends = pupil + np.array([[-radius, 0, -1.7], [radius, 0, -1.7]])
        uv, _ = project(np.vstack([pupil, ends]), frame["R"], frame["t"], intr)
        out[side] = {"pupil": uv[0], "diameter": float(np.linalg.norm(uv[2] - uv[1]))}
    return out


def mediapipe_irises(image: np.ndarray, det, refine_pupil: bool = True) -> dict:
    if det is None:
        return {}
    return {side: {"pupil": f.centre, "diameter": f.diameter}
            for side, f in iris.detect_irises(image, det, refine_pupil=refine_pupil).items()}


def mediapipe_raw_irises(image: np.ndarray, det) -> dict:
    return mediapipe_irises(image, det, refine_pupil=False)


def refined_irises(image: np.ndarray, det) -> dict:
    out = {}
    for side, m in mediapipe_irises(image, det).items():
        ids = RIGHT_EYE if side == "right" else LEFT_EYE
        fit = fit_iris(image, det.points[ids], start=(m["pupil"], 0.5 * m["diameter"]))
        if fit is not None:
            out[side] = {"pupil": fit.centre, "diameter": 2 * fit.radius}
    return out


def limbus_irises(image: np.ndarray, det) -> dict:
    out = {}
    if det is None:
        return out
    for side, ids in (("right", RIGHT_EYE), ("left", LEFT_EYE)):
        fit = fit_iris(image, det.points[ids])
        if fit is not None:
            out[side] = {"pupil": fit.centre, "diameter": 2 * fit.radius}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--captures", type=Path, default=ROOT / "out/bench_scale/captures")
    ap.add_argument("--max-yaw", type=float, default=15.0)
    ap.add_argument("--methods", nargs="*", default=["limbus", "mediapipe", "mediapipe+limbus",
                                                     "mediapipe raw"])
    args = ap.parse_args()
    methods = {"limbus": limbus_irises, "mediapipe raw": mediapipe_raw_irises,
               "mediapipe": mediapipe_irises, "mediapipe+limbus": refined_irises}
    methods = {k: v for k, v in methods.items() if k in args.methods}
    rows = {m: [] for m in methods}
    separations = {m: [] for m in methods}  # (capture, pupil-separation error %) per frame
    tried = 0
    for folder in sorted(p for p in args.captures.iterdir() if (p / "gt/subject.json").is_file()):
        if "pupils_mm" not in json.loads((folder / "gt/subject.json").read_text()):
            continue  # a head without eyes
        intr, frames = load_gt_cameras(folder / "gt" / "cameras.json")
        wanted = {}
        for f in frames:
            c = camera_center(f["R"], f["t"])
            if f["index"] % 2 == 0 and abs(np.degrees(np.arctan2(c[0], c[2]))) <= args.max_yaw:
                wanted[f["index"]] = f
        for frame in iter_frames(folder / "video.mp4", indices=list(wanted)):
            gt = truth(folder, wanted[frame.index], intr)
            det = detect(frame.image)
            tried += 2
            for name, method in methods.items():
                found = method(frame.image, det)
                if len(found) == 2:
                    sep = np.linalg.norm(found["left"]["pupil"] - found["right"]["pupil"])
                    true_sep = np.linalg.norm(gt["left"]["pupil"] - gt["right"]["pupil"])
                    separations[name].append((folder.name, 100 * (sep / true_sep - 1)))
                for side, m in found.items():
                    rows[name].append({
                        "capture": folder.name, "frame": frame.index, "side": side,
                        "pupil_px": float(np.linalg.norm(m["pupil"] - gt[side]["pupil"])),
                        "diameter_px": m["diameter"] - gt[side]["diameter"],
                        "diameter_pct": 100 * (m["diameter"] / gt[side]["diameter"] - 1),
                        "true_diameter_px": gt[side]["diameter"]})
    for name, r in rows.items():
        if not r:
            print(f"{name}: nothing found in {tried} eyes")
            continue
        pe = np.array([x["pupil_px"] for x in r])
        de = np.array([x["diameter_px"] for x in r])
        dp = np.array([x["diameter_pct"] for x in r])
        td = np.array([x["true_diameter_px"] for x in r])
        # Per-capture median of the diameter ratio: what the scale cue takes.
        caps = sorted({x["capture"] for x in r})
        med = np.array([np.median([x["diameter_pct"] for x in r if x["capture"] == c])
                        for c in caps])
        print(f"{name}: {len(r)}/{tried} eyes | pupil error median {np.median(pe):.2f} px, "
              f"p95 {np.percentile(pe, 95):.2f} px | diameter (true {np.median(td):.1f} px) "
              f"error mean {de.mean():+.2f} px, RMS {np.sqrt(np.mean(de ** 2)):.2f} px, "
              f"mean {dp.mean():+.1f} %, RMS {np.sqrt(np.mean(dp ** 2)):.1f} % | per-capture "
              f"median: mean {med.mean():+.2f} %, spread (1σ) {med.std(ddof=1):.2f} %")
        sep = np.array([np.median([e for c2, e in separations[name] if c2 == c])
                        for c in caps if any(c2 == c for c2, _ in separations[name])])
        print(f"    pupil separation (per-capture median) error: mean {sep.mean():+.2f} %, "
              f"spread (1σ) {sep.std(ddof=1):.2f} %, max |.| {np.abs(sep).max():.2f} %")


if __name__ == "__main__":
    main()
