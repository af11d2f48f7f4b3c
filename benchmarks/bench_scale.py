"""Metric scale: each cue's estimate and the combined scale error, on heads the cues were not
calibrated on.

    python benchmarks/bench_scale.py [--subjects ict:200 ... james] [--out out/bench_scale]
    python benchmarks/bench_scale.py --calibrate      # prints the IPD ratio (ict:1000-1007)

Per subject: a short synthetic sweep (``facecap synth``: 640x360, 4 s at 10 fps, yaw -50 to
50 degrees), the landmark stage fed with the ground-truth cameras in a world scaled by 1/37
(turned and moved; every second frame a keyframe), then ``coarse.metric_scale`` as the coarse
stage runs it:

* **no cue given**: the landmark size prior alone;
* **--ipd-mm**: the prior and the interpupillary distance, the truth given as the user would
  (ICT subjects: the distance between the iris centroids of the subject's own eyes; ``james``,
  a head scan without eyes: the distance between its ground-truth eye-landmark centres times
  ``CoarseConfig.ipd_ratio``).

Printed: per subject each cue's mm-per-unit error (%), the combined error and the stated 1σ;
then, per setting, the RMS and maximum error and the RMS of error/σ (an honest σ gives about
1). Writes OUT/report.md and OUT/results.json.

Split: ``landmark_size`` is calibrated on ICT identities ``ict:1000``-``ict:1199``;
``ipd_ratio`` on the same captures as here of ``ict:1000``-``ict:1007`` (``--calibrate``: iris
distance over the triangulated eye-landmark-centre distance); the landmark convention offsets
on ``ict:101``-``ict:106``. The default subjects ``ict:200``-``ict:209`` and ``james`` are none
of these.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from facecap_core import coarse  # noqa: E402
from facecap_core.assets import default_ict_model  # noqa: E402
from facecap_core.camera import rotation_matrix  # noqa: E402
from facecap_core.config import CoarseConfig, SynthConfig  # noqa: E402
from facecap_core.landmarks import stage  # noqa: E402
from facecap_core.meshio import load_landmarks  # noqa: E402
from facecap_core.synthetic import synthesize  # noqa: E402
from facecap_core.template import Template, ict_identity_vertices, load_ict_model  # noqa: E402

WORLD = {"scale": 1 / 37.0, "rotation": rotation_matrix([0.3, 1.0, 0.2], 0.7),
         "translation": np.array([1.0, 2.0, 3.0])}
SUBJECTS = [f"ict:{n}" for n in range(200, 210)] + ["james"]
BAR_RMS_PCT, BAR_MAX_PCT, BAR_IPD_PCT = 4.0, 8.0, 1.5


def iris_distance(model: dict, coefficients: np.ndarray | None) -> float:
    """Pupil distance (mm) of an ICT identity: between its two iris centroids."""
    names, material, faces = list(model["material_names"]), model["face_material"], model["faces"]
    verts = ict_identity_vertices(model, coefficients)
    left = np.unique(faces[material == names.index("M_IrisLeft")])
    right = np.unique(faces[material == names.index("M_IrisRight")])
    return float(np.linalg.norm(verts[left].mean(0) - verts[right].mean(0)))


def true_ipd(subject: str, model: dict, gt_landmarks: np.ndarray, config: CoarseConfig) -> float:
    if subject.startswith("ict:"):
        seed = int(subject.split(":")[1])  # the synthetic renderer's identity stream
        return iris_distance(model, np.random.default_rng([seed, 1]).standard_normal(100))
    return config.ipd_ratio * coarse.eye_distance(gt_landmarks)


def capture(subject: str, out: Path, ict_model: str) -> Path:
    folder = out / "captures" / subject.replace(":", "_")
    if not (folder / "gt" / "render.json").is_file():
        config = SynthConfig(subject=subject, ict_model=ict_model, width=640, height=360, fps=10,
                             duration_s=4.0, yaw_start_deg=-50, yaw_end_deg=50, seed=7)
        synthesize(config, folder, progress=False)
    return folder


def measure(subject: str, out: Path, ict_model: str, model: dict, template: Template) -> dict:
    triangulated_eye_distance_mm(subject, out, ict_model)  # renders and runs the stage once
    folder = out / "captures" / subject.replace(":", "_")
    L, _ = stage.load_landmarks3d(out / "runs" / folder.name / "landmarks3d.json")
    gt = load_landmarks(folder / "gt" / "landmarks.json")
    truth = 1 / WORLD["scale"]
    none = np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0, str)
    base = CoarseConfig()
    ipd = true_ipd(subject, model, gt, base)
    row = {"subject": subject, "true_ipd_mm": round(ipd, 2)}
    for setting, config in (("no cue", base), ("ipd", CoarseConfig(ipd_mm=round(ipd, 1)))):
        doc = coarse.metric_scale(template, L, *none, config)
        row[setting] = {
            "error_pct": round(100 * (doc["metric_scale"] / truth - 1), 3),
            "sigma_pct": doc["sigma_pct"], "used": doc["used"],
            "dropped": [d["name"] for d in doc["dropped"]],
            "cues_error_pct": {c["name"]: round(100 * (c["mm_per_unit"] / truth - 1), 3)
                               for c in doc["cues"]}}
    return row


def summary(rows: list[dict], setting: str) -> dict:
    err = np.array([r[setting]["error_pct"] for r in rows])
    z = err / np.array([r[setting]["sigma_pct"] for r in rows])
    return {"rms_pct": float(np.sqrt(np.mean(err ** 2))), "max_abs_pct": float(np.abs(err).max()),
            "mean_pct": float(err.mean()), "rms_error_over_sigma": float(np.sqrt(np.mean(z ** 2)))}


def triangulated_eye_distance_mm(subject: str, out: Path, ict_model: str) -> float:
    """The distance between the eye-landmark centres as the landmark stage triangulates them
    (GT cameras), in mm."""
    folder = capture(subject, out, ict_model)
    work = out / "runs" / folder.name
    if not (work / "landmarks3d.json").is_file():
        cams = stage.write_gt_keyframe_cameras(folder / "gt" / "cameras.json",
                                               work / "cameras.json", step=2, **WORLD)
        stage.main(folder / "video.mp4", cams, work)
    L, _ = stage.load_landmarks3d(work / "landmarks3d.json")
    return coarse.eye_distance(L) / WORLD["scale"]


def calibrate(subjects: list[str], out: Path, ict_model: str) -> None:
    """The IPD ratio: pupil distance over the triangulated eye-landmark-centre distance, on
    calibration subjects (the landmark-size prior's identities, never evaluated here)."""
    model = load_ict_model(ict_model)
    ratios = []
    for subject in subjects:
        seed = int(subject.split(":")[1])
        pd = iris_distance(model, np.random.default_rng([seed, 1]).standard_normal(100))
        ratios.append(pd / triangulated_eye_distance_mm(subject, out, ict_model))
        print(f"{subject}: pupil distance {pd:.1f} mm, ratio {ratios[-1]:.4f}", flush=True)
    ratios = np.array(ratios)
    print(f"ipd_ratio over {', '.join(subjects)}: mean {ratios.mean():.4f}, relative spread "
          f"{ratios.std(ddof=1) / ratios.mean():.4f} (CoarseConfig: ipd_ratio "
          f"{CoarseConfig().ipd_ratio}, ipd_spread {CoarseConfig().ipd_spread})")


def main() -> Path:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--subjects", nargs="*", default=SUBJECTS)
    ap.add_argument("--out", type=Path, default=ROOT / "out/bench_scale")
    ap.add_argument("--ict-model", default=os.environ.get("FACECAP_ICT_MODEL")
                    or str(default_ict_model()))
    ap.add_argument("--calibrate", action="store_true")
    ap.add_argument("--calibration-subjects", nargs="*",
                    default=[f"ict:{n}" for n in range(1000, 1008)])
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    if args.calibrate:
        calibrate(args.calibration_subjects, args.out, args.ict_model)
        return args.out
    model, template = load_ict_model(args.ict_model), Template.default()
    rows = []
    for subject in args.subjects:
        start = time.perf_counter()
        rows.append(measure(subject, args.out, args.ict_model, model, template))
        r = rows[-1]
        print(f"{subject:<9} IPD {r['true_ipd_mm']:5.1f} mm | no cue {r['no cue']['error_pct']:+6.2f} % "
              f"(±{r['no cue']['sigma_pct']:.1f}) | with IPD {r['ipd']['error_pct']:+6.2f} % "
              f"(±{r['ipd']['sigma_pct']:.1f}; IPD cue alone "
              f"{r['ipd']['cues_error_pct']['ipd']:+.2f} %) | {time.perf_counter() - start:.0f} s",
              flush=True)
    result = {"subjects": rows, "no cue": summary(rows, "no cue"), "ipd": summary(rows, "ipd"),
              "ict_model": args.ict_model, "world_scale": WORLD["scale"]}
    lines = ["| setting | RMS error % | max error % | mean % | RMS error/σ | bar |",
             "|---|---:|---:|---:|---:|---|"]
    for setting, bar in (("no cue", f"RMS ≤ {BAR_RMS_PCT}, max ≤ {BAR_MAX_PCT}"),
                         ("ipd", f"max ≤ {BAR_IPD_PCT}")):
        s = result[setting]
        lines.append(f"| {setting} | {s['rms_pct']:.2f} | {s['max_abs_pct']:.2f} | "
                     f"{s['mean_pct']:+.2f} | {s['rms_error_over_sigma']:.2f} | {bar} |")
    table = "\n".join(lines)
    print(table)
    (args.out / "results.json").write_text(json.dumps(result, indent=1))
    (args.out / "report.md").write_text(f"# Metric scale\n\n{table}\n")
    return args.out / "report.md"


if __name__ == "__main__":
    main()
