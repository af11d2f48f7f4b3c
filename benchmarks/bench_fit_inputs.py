"""Does the fit make more of better inputs? Each input of the fitting stage degraded and
improved on its own, the others held, on subjects with exact ground truth.

    python benchmarks/bench_fit_inputs.py [--subjects james ict:1201] [--out out/bench_fit_inputs]
        [--axes cloud_noise cloud_coverage landmark_noise landmark_bias] [--config FIT.yaml]

Per subject a short synthetic capture (rendered once, cached in ``OUT/captures``) gives the
true surface, its 68 landmarks, its cameras and the keyframes for the silhouettes. The fit's
inputs are made from the truth, with one draw of every random number per subject, so that
along an axis only the size of one defect changes:

* ``cloud_noise``: the sampled surface with Gaussian noise of 0.6, 0.3 and 0.15 mm (the
  same unit draws scaled; each point's standard error is given, as fusion gives it, so the
  fit's noise weighting sees it);
* ``cloud_coverage``: 40, 20 and 5 % of the surface cut away in nested holes (each hole set
  holds the next);
* ``landmark_noise``: the true 68 landmarks with 3, 1.5 and 0.5 mm of Gaussian error per
  coordinate (the same unit draws scaled);
* ``landmark_bias``: a smooth systematic displacement of the landmarks (each group of the
  iBUG 68 shifted by 2 mm in one direction: what a detector convention that is not the
  subject's own does), at full, half and zero size.

The base inputs sit in the middle of every axis (0.3 mm, 20 %, 1.5 mm, half the bias);
outliers (3 %) and the keyframes are the same everywhere. Each row is scored with the
similarity and metric protocols in the face sphere. The bar: along every axis, a better
input never gives a worse mesh (similarity accuracy mean and median, face region) by more
than the resolution of the measure, ``TOLERANCE_MM`` + ``TOLERANCE_REL`` of the figure.
Writes ``OUT/report.md`` and ``OUT/results.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import zlib
from pathlib import Path

import numpy as np
import trimesh
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_fitting import pick_keyframes  # noqa: E402
from captures import capture_for  # noqa: E402

from facecap.synthetic import load_gt_cameras  # noqa: E402
from facecap_core.evaluation import score  # noqa: E402
from facecap_core.fitting import FittingConfig, fit, keyframes_from_video  # noqa: E402
from facecap_core.meshio import load_landmarks, load_mesh  # noqa: E402
from facecap_core.template import Template  # noqa: E402

AXES = {  # name: (values from worst to best, the base value)
    "cloud_noise": ((0.6, 0.3, 0.15), 0.3),
    "cloud_coverage": ((0.4, 0.2, 0.05), 0.2),
    "landmark_noise": ((3.0, 1.5, 0.5), 1.5),
    "landmark_bias": ((1.0, 0.5, 0.0), 0.5),
}
TOLERANCE_MM = 0.005
"""What two fits of equally good inputs differ by: the resolution of the measure (mm)."""
TOLERANCE_REL = 0.01
"""... plus this share of the figure."""
GROUPS = {"brows": range(17, 27), "nose": range(27, 36), "eyes": range(36, 48),
          "mouth": range(48, 68)}
DEFAULT_SUBJECTS = ["james", "ict:1201"]
"""A real scan and an ICT identity that no calibration uses (docs/fitting.md, the split)."""


class Inputs:
    """One subject's random draws; :meth:`cloud` and :meth:`landmarks` scale them."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, landmarks: np.ndarray,
                 seed: int):
        rng = np.random.default_rng([seed, 47])
        mesh = trimesh.Trimesh(vertices, faces, process=False)
        points, face_ids = trimesh.sample.sample_surface(mesh, int(mesh.area * 0.7),
                                                         seed=int(rng.integers(2 ** 31)))
        self.points, self.normals = points, mesh.face_normals[face_ids]
        self.unit_noise = rng.normal(size=points.shape)
        # Nested holes: the first k centres of one list cut the k-hole cloud.
        self.hole_centres = points[rng.integers(len(points), size=200)]
        self.hole_radii = rng.uniform(6.0, 18.0, 200)
        k = int(0.03 * len(points))
        self.outliers = rng.choice(len(points), k, replace=False)
        d = rng.normal(size=(k, 3))
        self.outlier_moves = d / np.linalg.norm(d, axis=1, keepdims=True) \
            * rng.uniform(2.0, 15.0, (k, 1))
        self.truth = np.asarray(landmarks, float)
        self.landmark_unit = rng.normal(size=self.truth.shape)
        self.bias = np.zeros_like(self.truth)
        for ids in GROUPS.values():
            d = rng.normal(size=3)
            self.bias[list(ids)] = 2.0 * d / np.linalg.norm(d)

    def cloud(self, noise_mm: float, holes: float):
        keep = np.ones(len(self.points), bool)
        for c, r in zip(self.hole_centres, self.hole_radii):
            if (~keep).mean() >= holes:
                break
            keep &= np.linalg.norm(self.points - c, axis=1) > r
        pts = self.points + noise_mm * self.unit_noise
        pts[self.outliers] += self.outlier_moves
        errors = np.full(len(pts), noise_mm)
        return pts[keep], self.normals[keep], errors[keep]

    def landmarks(self, noise_mm: float, bias: float) -> np.ndarray:
        return self.truth + noise_mm * self.landmark_unit + bias * self.bias


def run_subject(subject: str, out: Path, axes: list[str], config: FittingConfig) -> list[dict]:
    folder = capture_for(subject, out / "captures", width=640, height=360, duration_s=1.5)
    gt = load_mesh(folder / "gt" / "mesh.ply", "ground-truth mesh")
    gt_v, gt_f = np.asarray(gt.vertices, float), np.asarray(gt.faces, np.int64)
    gt_lm = load_landmarks(folder / "gt" / "landmarks.json")
    intr, poses = load_gt_cameras(folder / "gt" / "cameras.json")
    keyframes = keyframes_from_video(folder / "video.mp4", intr, poses, pick_keyframes(poses, 9))
    inputs = Inputs(gt_v, gt_f, gt_lm, zlib.crc32(subject.encode()))
    template = Template.default()
    base = {axis: AXES[axis][1] for axis in AXES}
    done: dict[tuple, dict] = {}
    rows = []
    for axis in axes:
        for value in AXES[axis][0]:
            setting = {**base, axis: value}
            key = tuple(sorted(setting.items()))
            if key not in done:
                cloud, normals, errors = inputs.cloud(setting["cloud_noise"],
                                                      setting["cloud_coverage"])
                landmarks = inputs.landmarks(setting["landmark_noise"], setting["landmark_bias"])
                t = time.perf_counter()
                result = fit(template, cloud, landmarks, keyframes, None, normals, config,
                             errors)
                s = score(result.vertices, template.faces, gt_v, gt_f, gt_lm,
                          result.vertices[template.landmarks], protocol="similarity")
                m = score(result.vertices, template.faces, gt_v, gt_f, gt_lm,
                          result.vertices[template.landmarks], protocol="metric")
                done[key] = {"similarity_mean": round(s.accuracy.mean, 4),
                             "similarity_median": round(s.accuracy.median, 4),
                             "metric_mean": round(m.accuracy.mean, 4),
                             "metric_median": round(m.accuracy.median, 4),
                             "seconds": round(time.perf_counter() - t, 1)}
            row = {"subject": subject, "axis": axis, "value": value, **done[key]}
            rows.append(row)
            print(json.dumps(row), flush=True)
    return rows


def verdicts(rows: list[dict]) -> list[str]:
    """One line per (subject, axis) where a better input gave a worse mesh."""
    broken = []
    for subject in dict.fromkeys(r["subject"] for r in rows):
        for axis in dict.fromkeys(r["axis"] for r in rows):
            line = [r for r in rows if r["subject"] == subject and r["axis"] == axis]
            for worse, better in zip(line, line[1:]):
                for stat in ("similarity_mean", "similarity_median"):
                    bound = worse[stat] * (1 + TOLERANCE_REL) + TOLERANCE_MM
                    if better[stat] > bound:
                        broken.append(f"{subject}, {axis} {worse['value']} -> {better['value']}: "
                                      f"{stat} {worse[stat]:.3f} -> {better[stat]:.3f} mm")
    return broken


def report(rows: list[dict], out: Path) -> str:
    lines = ["# Better inputs, better mesh? (similarity / metric accuracy, face sphere, mm)", "",
             "| subject | axis | value | sim. mean | sim. median | metric mean | metric median "
             "| fit s |", "|---|---|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['subject']} | {r['axis']} | {r['value']:g} | "
                     f"{r['similarity_mean']:.3f} | {r['similarity_median']:.3f} | "
                     f"{r['metric_mean']:.3f} | {r['metric_median']:.3f} | {r['seconds']} |")
    broken = verdicts(rows)
    lines += ["", "Better inputs never give a worse mesh: " + ("yes" if not broken else "NO")]
    lines += [f"- {b}" for b in broken]
    text = "\n".join(lines) + "\n"
    (out / "report.md").write_text(text)
    (out / "results.json").write_text(json.dumps(rows, indent=1))
    return text


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--subjects", nargs="+", default=DEFAULT_SUBJECTS)
    ap.add_argument("--axes", nargs="+", default=list(AXES), choices=list(AXES))
    ap.add_argument("--out", type=Path, default=Path("out/bench_fit_inputs"))
    ap.add_argument("--config", type=Path, help="FittingConfig YAML (the fitting section)")
    ap.add_argument("--ict-model", default=os.environ.get("FACECAP_ICT_MODEL"))
    args = ap.parse_args(argv)
    if args.ict_model:
        os.environ["FACECAP_ICT_MODEL"] = args.ict_model
    config = FittingConfig(**(yaml.safe_load(args.config.read_text()) or {})
                           if args.config else {})
    config = config.model_copy(update={"texture": False})
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for subject in args.subjects:
        rows += run_subject(subject, args.out, args.axes, config)
        report(rows, args.out)
    print(report(rows, args.out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
