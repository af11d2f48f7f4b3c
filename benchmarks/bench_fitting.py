"""Isolated benchmark of the fitting stage (issue 6) on synthetic subjects.

    python benchmarks/bench_fitting.py [--subjects ict:0 ict:1 james] [--width 1280 --height 720]
        [--seconds 1.5] [--out out/bench_fitting] [--keyframes 9] [--ict-model PATH]

Per subject: a synthetic capture (rendered once, cached in ``OUT/captures``) gives the
ground-truth mesh, landmarks and cameras; the fitting inputs are made from the ground truth:

* cloud: the GT surface sampled at ~0.7 point/mm², 0.5 mm Gaussian noise, 20 % of it cut
  away in spatially coherent holes, 5 % outliers 2-15 mm off the surface; normals jittered;
* landmarks: the GT 68 with 1 mm Gaussian noise per coordinate;
* keyframes: ``--keyframes`` frames of the video spread over the sweep's yaw, GT cameras;
* template: ``Template.default()`` (53,349 vertices) by a similarity from its inner
  landmarks to the noisy ones.

Rows (paper-style table, similarity and metric protocols of ``evaluation.score``, in the face
sphere and in the ear region): the mean template, landmarks only, w/o edges, w/o ear
landmarks, full. Speed: wall and CPU seconds, optimal steps and factorisations of the full fit.
Writes ``OUT/report.md`` and ``OUT/results.json``; meshes per subject and row in
``OUT/<subject>/<row>/``.
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

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from captures import capture_for  # noqa: E402

from facecap.synthetic import load_gt_cameras  # noqa: E402
from facecap.synthetic.cloud import mvs_like_cloud  # noqa: E402
from facecap_core.camera import camera_center  # noqa: E402
from facecap_core.evaluation import PROTOCOLS, paper_table, score, score_json  # noqa: E402
from facecap_core.fitting import FittingConfig, fit, keyframes_from_video, write_mesh  # noqa: E402
from facecap_core.meshio import load_landmarks, load_mesh  # noqa: E402
from facecap_core.nonrigid.nicp import initial_similarity  # noqa: E402
from facecap_core.template import Template  # noqa: E402

BARS = {"accuracy": 0.3, "completion": 0.4}
ROWS = ("mean template", "landmarks only", "w/o edges", "w/o ear landmarks", "full")
DEFAULT_ICT = Path(__file__).resolve().parents[2] / "shared/data/ict_face_model/ict_face_model.npz"


def pick_keyframes(poses: list[dict], count: int) -> list[int]:
    """Frame indices whose camera yaws are spread evenly over the sweep."""
    yaw = np.array([np.degrees(np.arctan2(*camera_center(p["R"], p["t"])[[0, 2]])) for p in poses])
    wanted = np.linspace(yaw.min(), yaw.max(), count)
    return sorted({int(poses[int(np.argmin(np.abs(yaw - w)))]["index"]) for w in wanted})


def row_configs(base: FittingConfig) -> dict[str, FittingConfig | None]:
    return {
        "mean template": None,
        "landmarks only": base.model_copy(update={"use_cloud": False, "use_edges": False}),
        "w/o edges": base.model_copy(update={"use_edges": False}),
        "w/o ear landmarks": base.model_copy(update={"use_ear_landmarks": False}),
        "full": base,
    }


def run(subjects: list[str], out: Path, width: int, height: int, seconds: float,
        n_keyframes: int, ict_model: str | None, rows: list[str]) -> str:
    template = Template.default()
    base = FittingConfig()
    configs = row_configs(base)
    records = {p: {r: [] for r in rows} for p in PROTOCOLS}
    timings, notes = [], []
    for subject in subjects:
        folder = capture_for(subject, out / "captures", ict_model, width=width, height=height,
                             duration_s=seconds)
        gt = load_mesh(folder / "gt" / "mesh.ply", "ground-truth mesh")
        gt_v, gt_f = np.asarray(gt.vertices, float), np.asarray(gt.faces, np.int64)
        gt_lm = load_landmarks(folder / "gt" / "landmarks.json")
        seed = int(subject[4:]) if subject[4:].isdigit() else zlib.crc32(subject.encode()) % 1000
        cloud, normals = mvs_like_cloud(gt_v, gt_f, density=0.7, noise_mm=0.5, holes=0.2,
                                        outliers=0.05, seed=seed)
        rng = np.random.default_rng([seed, 7])
        landmarks = gt_lm + rng.normal(0.0, 1.0, gt_lm.shape)
        intr, poses = load_gt_cameras(folder / "gt" / "cameras.json")
        kf_ids = pick_keyframes(poses, n_keyframes)
        keyframes = keyframes_from_video(folder / "video.mp4", intr, poses, kf_ids)
        print(f"{subject}: cloud {len(cloud)} points, {len(keyframes)} keyframes {kf_ids}",
              flush=True)
        ear_points = None  # no ear landmark source yet (a later stage)
        full_result = None
        for row in rows:
            cfg = configs[row]
            if row == "w/o ear landmarks" and ear_points is None and full_result is not None:
                result = full_result  # identical inputs: no ear points exist yet
            elif cfg is None:
                result = None
            else:
                result = fit(template, cloud, landmarks, keyframes, ear_points, normals, cfg)
            verts = initial_similarity(template, landmarks) if cfg is None else result.vertices
            if row == "full":
                full_result = result
                t = result.timing()
                timings.append({"subject": subject, **t})
                print(f"  full fit: {t['iterations']} steps, {t['factorizations']} "
                      f"factorisations, wall {t['wall_s']:.1f} s, CPU {t['cpu_s']:.1f} s, "
                      f"{t['wall_s_per_iteration']:.2f} s/step (wall)", flush=True)
            row_dir = out / subject.replace(":", "_") / row.replace(" ", "_").replace("/", "")
            write_mesh(row_dir, verts, template.faces)
            for p in PROTOCOLS:
                s = score(verts, template.faces, gt_v, gt_f, gt_lm, verts[template.landmarks],
                          protocol=p)
                records[p][row].append(score_json(s))
                if p == "metric":
                    print(f"  {row:18s} metric accuracy median {s.accuracy.median:.3f} "
                          f"completion median {s.completion.median:.3f} mm; ears "
                          f"{s.ears.accuracy.median:.3f} / {s.ears.completion.median:.3f} mm",
                          flush=True)
        if "w/o ear landmarks" in rows and full_result is not None and ear_points is None:
            notes.append(f"{subject}: no ear points yet (ear landmarks are a later stage): the "
                         "'w/o ear landmarks' fit has the same inputs as the full one")
    return report(records, timings, notes, subjects, width, height, seconds, n_keyframes, out)


def report(records, timings, notes, subjects, width, height, seconds, n_kf, out: Path) -> str:
    lines = ["# Fitting benchmark (isolated: cloud and landmarks from the ground truth)", "",
             f"Subjects: {', '.join(subjects)}; captures {width}x{height}, {seconds:g} s; "
             f"{n_kf} keyframes; cloud 0.7 pt/mm², 0.5 mm noise, 20 % holes, 5 % outliers; "
             "landmarks with 1 mm noise; template: default (53,349 vertices).", ""]
    for p in PROTOCOLS:
        lines += [f"## Protocol: {p}, face sphere", "",
                  paper_table([(r, records[p][r]) for r in records[p]]), ""]
    # The ear region beside the face sphere: "w/o ear landmarks" against "full" there is what
    # the ear landmarks are for.
    for p in PROTOCOLS:
        lines += [f"## Protocol: {p}, ear region (ear spheres outside the face sphere)", "",
                  paper_table([(r, records[p][r]) for r in records[p]], region="ears"), ""]
    full = records["metric"].get("full", [])
    if full:
        acc = np.mean([r["accuracy"]["median"] for r in full])
        comp = np.mean([r["completion"]["median"] for r in full])
        lines += [f"Bars (metric, full): accuracy median {acc:.3f} mm (bar {BARS['accuracy']}: "
                  f"{'met' if acc <= BARS['accuracy'] else 'NOT met'}), completion median "
                  f"{comp:.3f} mm (bar {BARS['completion']}: "
                  f"{'met' if comp <= BARS['completion'] else 'NOT met'}).", ""]
    if timings:
        lines += ["## Speed (full fit, default template)", "",
                  "| Subject | Steps | Factorisations | Wall s | CPU s | Wall s/step |",
                  "|---|---:|---:|---:|---:|---:|"]
        for t in timings:
            lines.append(f"| {t['subject']} | {t['iterations']} | {t['factorizations']} | "
                         f"{t['wall_s']:.1f} | {t['cpu_s']:.1f} | {t['wall_s_per_iteration']:.2f} |")
        cpu = max(t["cpu_s"] for t in timings)
        lines += ["", f"Speed bar (<= 60 s, goal 30 s, one core): worst CPU {cpu:.1f} s: "
                  f"{'met' if cpu <= 60 else 'NOT met'}"
                  f"{' (goal met)' if cpu <= 30 else ''}. Wall time includes other users of "
                  "this 2-core machine.", ""]
    lines += [f"- {n}" for n in notes]
    text = "\n".join(lines) + "\n"
    out.mkdir(parents=True, exist_ok=True)
    (out / "report.md").write_text(text)
    (out / "results.json").write_text(json.dumps({"records": records, "timings": timings},
                                                 indent=1))
    return text


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--subjects", nargs="+", default=["ict:0", "ict:1", "james"])
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--height", type=int, default=720)
    ap.add_argument("--seconds", type=float, default=1.5)
    ap.add_argument("--keyframes", type=int, default=9)
    ap.add_argument("--out", type=Path, default=Path("out/bench_fitting"))
    ap.add_argument("--ict-model", default=os.environ.get("FACECAP_ICT_MODEL") or
                    (str(DEFAULT_ICT) if DEFAULT_ICT.is_file() else None))
    ap.add_argument("--rows", nargs="+", default=list(ROWS), choices=ROWS)
    args = ap.parse_args(argv)
    start = time.perf_counter()
    text = run(args.subjects, args.out, args.width, args.height, args.seconds, args.keyframes,
               args.ict_model, args.rows)
    print(text)
    print(f"total {time.perf_counter() - start:.0f} s; report in {args.out / 'report.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
