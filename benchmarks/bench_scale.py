"""Metric scale: each cue's estimate and the combined scale error, on heads the cues were not
calibrated on.

    python benchmarks/bench_scale.py [--subjects ict:200 ... james] [--out out/bench_scale]
    python benchmarks/bench_scale.py --calibrate      # IPD, pupil, iris ratios (ict:1000-1007)

Per subject: a short synthetic sweep (``facecap synth``: 640x360 unless ``--size``, 4 s at
10 fps, yaw -50 to 50 degrees), the landmark stage fed with the ground-truth cameras in a
world scaled by 1/37 (turned and moved; every second frame a keyframe), then
``coarse.metric_scale`` as the coarse stage runs it:

* **no cue given**: the landmark size prior and the iris size (the landmark stage's iris
  measurement against the population's 11.7 mm);
* **--ipd-mm**: those and the interpupillary distance, the truth given as the user would
  (ICT subjects: the distance between the rendered pupils, ``gt/subject.json``; ``james``,
  a head scan whose eyes are its texture: the distance between its ground-truth eye-landmark
  centres times ``CoarseConfig.ipd_ratio``).

The settings ``landmarks only`` (no iris cue) and ``ipd, eye landmarks`` (the IPD against
the eye-landmark centres, no pupils) are the same without the landmark stage's iris
measurement, for comparison.

Printed: per subject each cue's mm-per-unit error (%), the combined error and the stated 1σ;
then, per setting, the RMS and maximum error and the RMS of error/σ (an honest σ gives about
1). Writes OUT/report.md and OUT/results.json.

Split: ``landmark_size`` is calibrated on ICT identities ``ict:1000``-``ict:1199``;
``ipd_ratio``, ``pupil_ratio`` and ``iris_ratio`` on the same captures as here of
``ict:1000``-``ict:1007`` (``--calibrate``: the rendered pupil distance over the triangulated
eye-landmark-centre distance and over the triangulated pupils' distance; each subject's
rendered iris diameter over the stage's measurement); the landmark convention offsets on
``ict:101``-``ict:106``. The default subjects ``ict:200``-``ict:209`` and ``james`` are none
of these. Each ICT subject's iris diameter is drawn from 11.7 ± 0.5 mm by the renderer, so
the iris cue meets the population's spread.
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

from facecap.synthetic import synthesize, write_gt_keyframe_cameras  # noqa: E402
from facecap.synthetic.config import SynthConfig  # noqa: E402
from facecap_core import coarse  # noqa: E402
from facecap_core.assets import default_ict_model  # noqa: E402
from facecap_core.camera import rotation_matrix  # noqa: E402
from facecap_core.coarse import CoarseConfig  # noqa: E402
from facecap_core.landmarks import stage  # noqa: E402
from facecap_core.landmarks.landmarks3d_json import load_landmarks3d  # noqa: E402
from facecap_core.meshio import load_landmarks  # noqa: E402
from facecap_core.template import (  # noqa: E402
    INNER_LANDMARKS,
    Template,
    ict_identity_vertices,
    load_ict_model,
)

WORLD = {"scale": 1 / 37.0, "rotation": rotation_matrix([0.3, 1.0, 0.2], 0.7),
         "translation": np.array([1.0, 2.0, 3.0])}
SUBJECTS = [f"ict:{n}" for n in range(200, 210)] + ["james"]
BAR_RMS_PCT, BAR_MAX_PCT, BAR_IPD_PCT = 4.0, 8.0, 1.5
RENDER = {"width": 640, "height": 360}  # --size


def iris_distance(model: dict, coefficients: np.ndarray | None) -> float:
    """Pupil distance (mm) of an ICT identity: between its two iris centroids."""
    names, material, faces = list(model["material_names"]), model["face_material"], model["faces"]
    verts = ict_identity_vertices(model, coefficients)
    left = np.unique(faces[material == names.index("M_IrisLeft")])
    right = np.unique(faces[material == names.index("M_IrisRight")])
    return float(np.linalg.norm(verts[left].mean(0) - verts[right].mean(0)))


def rendered_eyes(folder: Path) -> dict:
    """The renderer's pupils (mm) and iris diameter of a capture's subject ({} without eyes)."""
    doc = json.loads((folder / "gt" / "subject.json").read_text())
    return {k: doc[k] for k in ("pupils_mm", "iris_diameter_mm") if k in doc}


def true_ipd(subject: str, folder: Path, model: dict, gt_landmarks: np.ndarray,
             config: CoarseConfig) -> float:
    eyes = rendered_eyes(folder)
    if "pupils_mm" in eyes:
        return float(np.linalg.norm(np.subtract(*eyes["pupils_mm"].values())))
    if subject.startswith("ict:"):
        seed = int(subject.split(":")[1])  # the synthetic renderer's identity stream
        return iris_distance(model, np.random.default_rng([seed, 1]).standard_normal(100))
    return config.ipd_ratio * coarse.eye_distance(gt_landmarks)


def capture(subject: str, out: Path, ict_model: str) -> Path:
    folder = out / "captures" / subject.replace(":", "_")
    if (folder / "gt" / "render.json").is_file():
        size = json.loads((folder / "gt" / "render.json").read_text())["intrinsics"]
        if (size["width"], size["height"]) != (RENDER["width"], RENDER["height"]):
            raise SystemExit(f"{folder} was rendered at {size['width']}x{size['height']}, not "
                             f"{RENDER['width']}x{RENDER['height']}: pass another --out")
    else:
        config = SynthConfig(subject=subject, ict_model=ict_model, width=RENDER["width"],
                             height=RENDER["height"], fps=10,
                             duration_s=4.0, yaw_start_deg=-50, yaw_end_deg=50, seed=7)
        synthesize(config, folder, progress=False)
    return folder


def measure(subject: str, out: Path, ict_model: str, model: dict, template: Template) -> dict:
    triangulated_eye_distance_mm(subject, out, ict_model)  # renders and runs the stage once
    folder = out / "captures" / subject.replace(":", "_")
    L, doc3d = load_landmarks3d(out / "runs" / folder.name / "landmarks3d.json")
    measured = doc3d.irises.model_dump()
    gt = load_landmarks(folder / "gt" / "landmarks.json")
    truth = 1 / WORLD["scale"]
    none = np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0, str)
    base = CoarseConfig()
    ipd = true_ipd(subject, folder, model, gt, base)
    row = {"subject": subject, "true_ipd_mm": round(ipd, 2),
           "true_iris_mm": rendered_eyes(folder).get("iris_diameter_mm"),
           "landmarks_mm": landmark_error_mm(L, gt)}
    given = round(ipd, 1)
    for setting, config, irises in (
            ("landmarks only", CoarseConfig(iris_cue=False), None),
            ("no cue", base, measured),
            ("ipd, eye landmarks", CoarseConfig(ipd_mm=given, iris_cue=False), None),
            ("ipd", CoarseConfig(ipd_mm=given), measured)):
        doc = coarse.metric_scale(template, L, *none, config, irises)
        row[setting] = {
            "error_pct": round(100 * (doc["metric_scale"] / truth - 1), 3),
            "sigma_pct": doc["sigma_pct"], "used": doc["used"],
            "dropped": [d["name"] for d in doc["dropped"]],
            "cues_error_pct": {c["name"]: round(100 * (c["mm_per_unit"] / truth - 1), 3)
                               for c in doc["cues"]}}
    return row


def landmark_error_mm(L: np.ndarray, truth: np.ndarray) -> dict:
    """The 3D landmarks' error after a similarity onto the truth (mm): median of the inner 51
    and of each region."""
    from bench_landmarks import REGIONS, landmark_errors

    mm = (np.asarray(L, float) - WORLD["translation"]) @ WORLD["rotation"] / WORLD["scale"]
    e = landmark_errors(mm, truth)
    return {k: round(float(np.nanmedian(e[i])), 3)
            for k, i in {"inner": INNER_LANDMARKS, **REGIONS}.items()}


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
        cams = write_gt_keyframe_cameras(folder / "gt" / "cameras.json",
                                               work / "cameras.json", step=2, **WORLD)
        stage.main(folder / "video.mp4", cams, work)
    L, _ = load_landmarks3d(work / "landmarks3d.json")
    return coarse.eye_distance(L) / WORLD["scale"]


def calibrate(subjects: list[str], out: Path, ict_model: str) -> None:
    """On calibration subjects (the landmark-size prior's identities, never evaluated here):
    the IPD ratio (pupil distance over the triangulated eye-landmark-centre distance), the
    pupil ratio (over the triangulated pupils' distance) and the iris ratio (the rendered iris
    diameter over the landmark stage's measurement), each with its relative spread."""
    model = load_ict_model(ict_model)
    ratios = {"ipd_ratio": [], "pupil_ratio": [], "iris_ratio": []}
    for subject in subjects:
        eye_mm = triangulated_eye_distance_mm(subject, out, ict_model)
        folder = out / "captures" / subject.replace(":", "_")
        _, doc3d = load_landmarks3d(out / "runs" / folder.name / "landmarks3d.json")
        irises = doc3d.irises.model_dump()
        pd = true_ipd(subject, folder, model, np.zeros((68, 3)), CoarseConfig())
        ratios["ipd_ratio"].append(pd / eye_mm)
        line = f"{subject}: pupil distance {pd:.1f} mm, ipd_ratio {ratios['ipd_ratio'][-1]:.4f}"
        if irises.get("pupil_distance"):
            ratios["pupil_ratio"].append(pd / (irises["pupil_distance"] / WORLD["scale"]))
            line += f", pupil_ratio {ratios['pupil_ratio'][-1]:.4f}"
        if irises.get("iris_diameter"):
            true_iris = rendered_eyes(folder)["iris_diameter_mm"]
            ratios["iris_ratio"].append(true_iris / (irises["iris_diameter"] / WORLD["scale"]))
            line += (f", iris {true_iris:.2f} mm, iris_ratio {ratios['iris_ratio'][-1]:.4f} "
                     f"({len(irises['iris_diameter_views'])} eye views)")
        print(line, flush=True)
    defaults = CoarseConfig()
    for name, values in ratios.items():
        if len(values) < 2:
            print(f"{name}: fewer than two calibration captures measured it")
            continue
        v = np.array(values)
        print(f"{name} over {', '.join(subjects)}: mean {v.mean():.4f}, relative spread "
              f"{v.std(ddof=1) / v.mean():.4f} (CoarseConfig: {name} {getattr(defaults, name)})")


def main() -> Path:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--subjects", nargs="*", default=SUBJECTS)
    ap.add_argument("--out", type=Path, default=ROOT / "out/bench_scale")
    ap.add_argument("--ict-model", default=os.environ.get("FACECAP_ICT_MODEL")
                    or str(default_ict_model()))
    ap.add_argument("--size", default="640x360",
                    help="render size WxH (the irises are ~25 px wide at 1280x720, ~12 at "
                         "640x360; a phone records 1920x1080 or more)")
    ap.add_argument("--calibrate", action="store_true")
    ap.add_argument("--calibration-subjects", nargs="*",
                    default=[f"ict:{n}" for n in range(1000, 1008)])
    args = ap.parse_args()
    try:
        RENDER["width"], RENDER["height"] = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        ap.error(f"--size {args.size}: expected WIDTHxHEIGHT, e.g. 1280x720")
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
        cues = r["no cue"]["cues_error_pct"]
        iris = (f"iris cue alone {cues['iris']:+6.2f} %" if "iris" in cues else "no iris cue")
        dropped = r["no cue"]["dropped"]
        print(f"{subject:<9} IPD {r['true_ipd_mm']:5.1f} mm | no cue "
              f"{r['no cue']['error_pct']:+6.2f} % (±{r['no cue']['sigma_pct']:.1f}; landmarks "
              f"{cues['landmarks']:+6.2f} %, {iris}"
              f"{'; dropped ' + ', '.join(dropped) if dropped else ''}) | with IPD "
              f"{r['ipd']['error_pct']:+6.2f} % "
              f"(±{r['ipd']['sigma_pct']:.1f}; IPD cue alone "
              f"{r['ipd']['cues_error_pct']['ipd']:+.2f} %) | {time.perf_counter() - start:.0f} s",
              flush=True)
    settings = {"landmarks only": "", "no cue": f"RMS ≤ {BAR_RMS_PCT}, max ≤ {BAR_MAX_PCT}",
                "ipd, eye landmarks": "", "ipd": f"max ≤ {BAR_IPD_PCT}"}
    result = {"subjects": rows, **{k: summary(rows, k) for k in settings},
              "ict_model": args.ict_model, "world_scale": WORLD["scale"],
              "render_size": [RENDER["width"], RENDER["height"]]}
    lines = ["| setting | RMS error % | max error % | mean % | RMS error/σ | bar |",
             "|---|---:|---:|---:|---:|---|"]
    for setting, bar in settings.items():
        s = result[setting]
        lines.append(f"| {setting} | {s['rms_pct']:.2f} | {s['max_abs_pct']:.2f} | "
                     f"{s['mean_pct']:+.2f} | {s['rms_error_over_sigma']:.2f} | {bar} |")
    lm = np.array([r["landmarks_mm"]["inner"] for r in rows])
    result["landmarks_inner_median_mm"] = {"median": float(np.median(lm)),
                                           "mean": float(lm.mean()), "max": float(lm.max())}
    lines.append(f"\n3D landmarks (GT cameras, after a similarity), inner 51 median per subject: "
                 f"median {np.median(lm):.2f} mm, mean {lm.mean():.2f}, worst {lm.max():.2f}")
    table = "\n".join(lines)
    print(table)
    (args.out / "results.json").write_text(json.dumps(result, indent=1))
    (args.out / "report.md").write_text(f"# Metric scale\n\n{table}\n")
    return args.out / "report.md"


if __name__ == "__main__":
    main()
