"""Anatomical measurements: does the stated uncertainty cover the true distance?

    python benchmarks/bench_measure.py [--out out/bench_measure]     # the held-out captures
    python benchmarks/bench_measure.py --calibrate                   # PLACEMENT, ict:101-106
    python benchmarks/bench_measure.py --results RESULT:GT_LANDMARKS ...   # runs already made

Each capture is rendered (``facecap synth``) and reconstructed with its scan (``facecap
reconstruct --scan --scan-landmarks``) as a user would, once per ``--out``; a capture whose
``report.json`` is there is scored again without running. Per preset of
:data:`facecap_core.measure.PRESETS` it compares the fitted mesh's straight distance between
the two landmark vertices with the distance between the same two landmarks of the ground
truth (the renderer's landmarks: the ICT model's own landmark vertices, or the scan's
landmarks), and splits the error in two: the metric scale's (the evaluation's similarity
scale) and the landmark vertices' *placement* (the distance at the true scale minus the
truth), which the scale's σ does not count.

``--calibrate`` prints each preset's placement bias (mean) and spread (the standard
deviation × sqrt(1 + 1/n), a new capture's spread about a mean of n) over the calibration
captures, the table :data:`facecap_core.measure.PLACEMENT` holds (its coverage lines are
against the table in the code when it ran). The report says, for each capture and preset,
where the truth lies against the figure the report states
(``figures.measurements[*].anatomical``: the mesh's distance less the bias, ± the scale's
and the placement's 1σ in quadrature) and against the scale's σ alone: the share within 1σ
and 2σ (an honest σ covers ~68 % and ~95 %).

Split: calibration on ICT identities 101-106 (also the landmark convention's calibration
heads, so their landmarks may sit better than other heads'), 101-103 at 1280×720 clean and
104-106 at ``phone_512``; the report on ICT identities 11 and 12 at ``phone_512``, ict:2 at
1280×720 and the james scan (a real head) at ``phone_512`` and ``phone_240`` — none of them
calibrated on. Run ``--results`` once per group to count the ICT heads and the real scan
apart (``docs/results_page.md``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.bench_real_conditions import PHONE  # noqa: E402
from facecap_core.measure import PRESETS, anatomical  # noqa: E402
from facecap_core.meshio import load_landmarks  # noqa: E402

HD = {"width": 1280, "height": 720}
"""A clean 720p capture: the renderer's defaults otherwise."""
PHONE_512 = {"width": 512, "height": 512, **PHONE}
PHONE_240 = {"width": 240, "height": 320, **PHONE}
CALIBRATION = {
    "ict101_hd": ("ict:101", 1, HD), "ict102_hd": ("ict:102", 2, HD),
    "ict103_hd": ("ict:103", 3, HD), "ict104_p512": ("ict:104", 1, PHONE_512),
    "ict105_p512": ("ict:105", 2, PHONE_512), "ict106_p512": ("ict:106", 3, PHONE_512),
}
"""name: (subject, seed, render settings) of the captures the placement is calibrated on."""
EVALUATION = {
    "ict11_p512": ("ict:11", 0, PHONE_512), "ict12_p512": ("ict:12", 0, PHONE_512),
    "ict2_hd": ("ict:2", 0, HD), "james_p512": ("james", 2, PHONE_512),
    "james_p240": ("james", 1, PHONE_240),
}
"""name: (subject, seed, render settings) of the held-out captures reported on."""
SECONDS = 4.0
"""Length of each sweep (s)."""


def reconstruct(name: str, subject: str, seed: int, settings: dict, out: Path) -> Path:
    """The result folder of ``name``'s capture under ``out``, rendered and reconstructed the
    first time."""
    folder = out / name
    result = folder / "result"
    if (result / "report.json").is_file():
        return result
    folder.mkdir(parents=True, exist_ok=True)
    values = {"subject": subject, "seed": seed, "duration_s": SECONDS, **settings}
    if not subject.startswith("ict:"):
        values.pop("skin_detail", None)  # a scan keeps its own texture
    (folder / "synth.yaml").write_text(yaml.safe_dump(values, sort_keys=False))
    env = {**os.environ, "FACECAP_STORE": str(out / "store")}
    py, capture = sys.executable, folder / "capture"
    print(f"{name}: rendering and reconstructing ...", flush=True)
    with open(folder / "run.log", "w") as log:
        if not (capture / "video.mp4").is_file():
            subprocess.run([py, "-m", "facecap", "synth", "--config", str(folder / "synth.yaml"),
                            "--out", str(capture), "--quiet"], cwd=ROOT, env=env, stdout=log,
                           stderr=subprocess.STDOUT, check=True)
        gt = capture / "gt"
        subprocess.run([py, "-m", "facecap", "reconstruct", str(capture / "video.mp4"), "--out",
                        str(result), "--scan", str(gt / "mesh.ply"), "--scan-landmarks",
                        str(gt / "landmarks.json")], cwd=ROOT, env=env,
                       stdout=log, stderr=subprocess.STDOUT, check=True)
    return result


def score(result: Path, gt_landmarks: Path) -> dict:
    """Per preset: the stated figures, the truth and the placement error (mm)."""
    report = json.loads((result / "report.json").read_text())
    stated = report["figures"]["measurements"]
    sigma_pct = (report["figures"].get("scale") or {}).get("sigma_pct")
    scale = json.loads((result / "evaluation.json").read_text())["similarity"]["scale"]
    truth = load_landmarks(gt_landmarks)
    rows = {}
    for key, _, i, j in PRESETS:
        m = stated[key]
        true = float(np.linalg.norm(truth[i] - truth[j]))
        mesh = m["straight"]["mm"]
        rows[key] = {"true": true, "mesh": mesh, "scale_sigma": m["straight"]["sigma_mm"],
                     "placement": mesh * scale - true,
                     "anatomical": anatomical(key, mesh, sigma_pct)}  # today's PLACEMENT
    return rows


def calibrate(scored: dict[str, dict]) -> dict:
    """PLACEMENT: per preset (bias, spread) of the placement error over the captures (mm):
    the mean, and the spread of a new capture's error about it (the standard deviation
    times sqrt(1 + 1/n): the mean is itself estimated from n captures)."""
    table = {}
    for key, *_ in PRESETS:
        e = np.array([rows[key]["placement"] for rows in scored.values()])
        table[key] = (round(float(e.mean()), 2),
                      round(float(e.std(ddof=1) * np.sqrt(1 + 1 / len(e))), 2))
    return table


def coverage(scored: dict[str, dict]) -> str:
    """Where the truth lies against the stated figure and against the scale's σ alone."""
    lines = ["| capture | preset | truth | mesh | placement | stated | error/σ | "
             "mesh error/scale σ |", "|---|---|---|---|---|---|---|---|"]
    within = {"stated": [], "scale": []}
    for name, rows in scored.items():
        for key, r in rows.items():
            z_scale = abs(r["mesh"] - r["true"]) / r["scale_sigma"] if r["scale_sigma"] else None
            a = r["anatomical"]
            z = abs(a["mm"] - r["true"]) / a["sigma_mm"] if a and a.get("sigma_mm") else None
            within["scale"].append(z_scale)
            within["stated"].append(z)
            lines.append(f"| {name} | {key} | {r['true']:.1f} | {r['mesh']:.1f} | "
                         f"{r['placement']:+.1f} | "
                         + (f"{a['mm']:.1f} ± {a['sigma_mm']:.1f}" if z is not None else "–")
                         + f" | {z if z is not None else float('nan'):.2f} | "
                         f"{z_scale if z_scale is not None else float('nan'):.2f} |")
    lines.append("")
    for what, all_z in within.items():
        zs = [z for z in all_z if z is not None]
        if zs:
            lines.append(f"{what}: within 1σ {sum(z <= 1 for z in zs)} of {len(zs)}, within 2σ "
                         f"{sum(z <= 2 for z in zs)} of {len(zs)}"
                         + (f" ({len(all_z) - len(zs)} without a σ: the scale's unknown)"
                            if len(zs) < len(all_z) else ""))
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "bench_measure")
    ap.add_argument("--calibrate", action="store_true",
                    help="run the calibration captures and print PLACEMENT")
    ap.add_argument("--results", nargs="+", metavar="RESULT:GT_LANDMARKS",
                    help="score these result folders (with their ground-truth landmarks)")
    args = ap.parse_args()
    if args.results:
        pairs = {}
        for item in args.results:
            if ":" not in item:
                sys.exit(f"bench_measure: {item}: give RESULT:GT_LANDMARKS")
            r, g = item.rsplit(":", 1)
            # A capture's name: its result folder's, or the folder above a "result".
            name = Path(r).parent.name if Path(r).name == "result" else Path(r).name
            pairs[name] = (Path(r), Path(g))
    else:
        captures = CALIBRATION if args.calibrate else EVALUATION
        pairs = {}
        for name, (subject, seed, settings) in captures.items():
            result = reconstruct(name, subject, seed, settings, args.out)
            pairs[name] = (result, args.out / name / "capture" / "gt" / "landmarks.json")
    scored = {name: score(result, gt) for name, (result, gt) in pairs.items()}
    if args.calibrate and len(scored) < 2:
        sys.exit("bench_measure: --calibrate needs two captures or more (a spread)")
    text = coverage(scored)
    if args.calibrate:
        text += "\n\nPLACEMENT = " + json.dumps(calibrate(scored))
    print(text)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / ("calibration.md" if args.calibrate else "report.md")).write_text(text + "\n")


if __name__ == "__main__":
    main()
