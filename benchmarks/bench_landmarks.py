"""Benchmark of the landmark stage and the coarse template (issue 4).

    python benchmarks/bench_landmarks.py [--captures DIR ...] [--out out/bench_landmarks]
        [--pipeline] [--deformations rbf nicp none]
    python benchmarks/bench_landmarks.py --calibrate [--calibration-seeds 101 102 ...]

Benchmark: for each capture (default: the three shared 720p sweeps ict:0, ict:1, james in
``out/captures``), the landmark stage is fed with

* **GT cameras**: every 8th frame's ground-truth camera as a keyframe (60 keyframes over
  the 190-degree sweep), in a world scaled by 0.013, turned and moved away from the ground
  truth's (the stage relies on neither its frame nor its millimetres);
* **pipeline cameras** (``--pipeline``): ``facecap reconstruct VIDEO --until poses``,
  run once per capture and cached under ``OUT/poses``.

Printed: 3D landmark error of the inner 51 points after a similarity alignment to the
ground truth, per region (mean / median / max, mm), triangulated as they are and after the
convention correction; the metric scale error (%: estimated mm per camera unit against the
truth — the world's known scale for GT cameras, the similarity of the keyframe camera
centres to the ground truth's for pipeline cameras); the coarse mesh's accuracy and
completion (paper-style rows, ``evaluation.score`` similarity and metric protocols) per
deformation; CPU and wall seconds (wall under load from other work on the machine).
Writes ``OUT/report.md`` and ``OUT/results.json``.

Calibration (``--calibrate``): renders (once, cached in ``OUT/calibration``) short 720p
sweeps (-50 to 50 degrees) of ICT identities that the benchmark does not use; chooses the
face-mesh vertex of each iBUG point on them (``facecap_core/data/face_mesh_to_ibug68.json``),
triangulates them with GT cameras and writes the median per-landmark convention offsets to
``facecap_core/landmarks/ibug68_convention.json``; it also prints the landmark-size prior
(``CoarseConfig.landmark_size``): the mean similarity scale from the template's inner
landmarks to those of 200 random ICT identities, and its spread.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from facecap.synthetic import load_gt_cameras, synthesize, write_gt_keyframe_cameras  # noqa: E402
from facecap.synthetic.config import SynthConfig  # noqa: E402
from facecap_core import coarse  # noqa: E402
from facecap_core.camera import (  # noqa: E402
    CameraSet,
    camera_center,
    rotation_matrix,
)
from facecap_core.coarse import CoarseConfig  # noqa: E402
from facecap_core.evaluation import paper_table, score, score_json  # noqa: E402
from facecap_core.geometry import umeyama  # noqa: E402
from facecap_core.landmarks import stage  # noqa: E402
from facecap_core.landmarks.convention import OFFSETS_FILE, convention_offsets  # noqa: E402
from facecap_core.landmarks.landmarks3d_json import load_landmarks3d  # noqa: E402
from facecap_core.landmarks.stage import LandmarkConfig  # noqa: E402
from facecap_core.meshio import load_landmarks, load_mesh  # noqa: E402
from facecap_core.pose.cameras_json import read_cameras_json  # noqa: E402
from facecap_core.template import INNER_LANDMARKS, Template  # noqa: E402

CAPTURES = [ROOT / "out/captures" / f"{s}_1280x720_60fps_8s" for s in ("ict_0", "ict_1", "james")]
DEFAULT_ICT = ROOT.parent / "shared/data/ict_face_model/ict_face_model.npz"
REGIONS = {"brows": np.r_[17:27], "nose": np.r_[27:36], "eyes": np.r_[36:48],
           "mouth": np.r_[48:68]}
# The stage's world: x' = S Q x + D (ground truth x in mm).
WORLD = {"scale": 0.013, "rotation": rotation_matrix([0.3, 1.0, 0.2], 0.7),
         "translation": np.array([1.0, 2.0, 3.0])}
KEYFRAME_STEP = 8
BAR_LANDMARKS_MM = 1.5
BAR_SCALE_PERCENT = 3.0


def cpu_wall(fn, *args, **kwargs):
    c, w = time.process_time(), time.perf_counter()
    out = fn(*args, **kwargs)
    return out, time.process_time() - c, time.perf_counter() - w


# --------------------------------------------------------------------------- measures


def landmark_errors(L: np.ndarray, G: np.ndarray) -> np.ndarray:
    """Per-point distance (68,) after the similarity of the inner points onto the truth
    (NaN for the jaw contour)."""
    ok = np.all(np.isfinite(L[INNER_LANDMARKS]), axis=1)
    idx = INNER_LANDMARKS[ok]
    s, R, t = umeyama(L[idx], G[idx])
    e = np.full(68, np.nan)
    e[idx] = np.linalg.norm(s * L[idx] @ R.T + t - G[idx], axis=1)
    return e


def region_stats(e: np.ndarray) -> dict:
    out = {}
    for name, idx in {**REGIONS, "inner": INNER_LANDMARKS}.items():
        v = e[idx][np.isfinite(e[idx])]
        out[name] = {"mean": float(v.mean()), "median": float(np.median(v)),
                     "max": float(v.max())}
    return out


def true_scale_pipeline(cams: CameraSet, gt_cameras: Path) -> float:
    """mm per camera unit of estimated cameras: similarity of their centres to the GT's."""
    _, poses = load_gt_cameras(gt_cameras)
    by_index = {int(p["index"]): p for p in poses}
    est = np.array([camera_center(R, t) for R, t in zip(cams.R, cams.t)])
    gt = np.array([camera_center(by_index[i]["R"], by_index[i]["t"])
                   for i in cams.frame_indices])
    s, _, _ = umeyama(est, gt)
    return s


# --------------------------------------------------------------------------- runs


def pipeline_cameras(capture: Path, out: Path) -> Path | None:
    """``facecap reconstruct --until poses`` once per capture (cached)."""
    folder = out / "poses" / capture.name
    path = folder / "cameras.json"
    if not path.is_file():
        print(f"  reconstructing poses of {capture.name} (facecap reconstruct --until poses)",
              flush=True)
        cmd = [sys.executable, "-m", "facecap", "reconstruct", str(capture / "video.mp4"),
               "--out", str(folder), "--until", "poses"]
        result = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
        if result.returncode != 0 or not path.is_file():
            print(f"  pose reconstruction failed: {result.stderr.strip()[-300:]}")
            return None
    return path


def run_capture(capture: Path, out: Path, cameras: str, deformations: list[str],
                template: Template) -> dict:
    work = out / capture.name / cameras
    G = load_landmarks(capture / "gt" / "landmarks.json")
    gt_mesh = load_mesh(capture / "gt" / "mesh.ply")
    if cameras == "gt":
        cams_path = write_gt_keyframe_cameras(capture / "gt" / "cameras.json",
                                                    work / "cameras.json", step=KEYFRAME_STEP,
                                                    **WORLD)
        mm_per_unit = 1.0 / WORLD["scale"]
    else:
        cams_path = pipeline_cameras(capture, out)
        if cams_path is None:
            return {}
        mm_per_unit = true_scale_pipeline(read_cameras_json(cams_path),
                                          capture / "gt" / "cameras.json")
    lm_path, cpu, wall = cpu_wall(stage.main, capture / "video.mp4", cams_path, work / "landmarks")
    L, doc = load_landmarks3d(lm_path)
    raw = np.array([[np.nan] * 3 if p is None else p for p in doc.triangulated], float)
    doc2d = json.loads((work / "landmarks" / "landmarks2d.json").read_text())
    rec = {"keyframes": doc.keyframes, "detected": doc.detected,
           "gated": len(doc.views), "stage_cpu_s": cpu, "stage_wall_s": wall,
           "reprojection_px": doc.reprojection_px.model_dump(),
           "landmarks_raw": region_stats(landmark_errors(raw, G)),
           "landmarks": region_stats(landmark_errors(L, G)),
           "ears": sum(len(r["ears"]) for r in doc2d["keyframes"]), "coarse": {}}
    for deformation in deformations:
        config = CoarseConfig(deformation=deformation)
        ply, ccpu, cwall = cpu_wall(coarse.main, work / "landmarks", cams_path,
                                    work / f"coarse_{deformation}", template, config)
        cdoc = json.loads((work / f"coarse_{deformation}" / "coarse.json").read_text())
        m = cdoc["scale"]["metric_scale"]
        mesh = load_mesh(ply)
        mesh_lm = load_landmarks(work / f"coarse_{deformation}" / "landmarks3d.json")
        scores = {p: score_json(score(mesh.vertices, mesh.faces, gt_mesh.vertices,
                                      gt_mesh.faces, G, mesh_lm, protocol=p))
                  for p in ("similarity", "metric")}
        rec["coarse"][deformation] = {"cpu_s": ccpu, "wall_s": cwall, "scores": scores}
        rec["metric_scale"] = m
        rec["scale_error_percent"] = 100.0 * (m / mm_per_unit - 1.0)
        rec["scale_how"] = cdoc["scale"]["how"]
    return rec


# --------------------------------------------------------------------------- report


def report(results: dict, deformations: list[str]) -> str:
    lines = ["# Landmarks, coarse template and metric scale (issue 4)", ""]
    for cams in ("gt", "pipeline"):
        rows = {c: r[cams] for c, r in results.items() if r.get(cams)}
        if not rows:
            continue
        lines += [f"## {'GT cameras' if cams == 'gt' else 'pipeline cameras'}", "",
                  "3D landmarks after a similarity alignment to the ground truth (mm, "
                  "mean / median / max; raw = triangulated, corr. = convention-corrected):", "",
                  "| capture | keyframes (detected / gated) | brows | nose | eyes | mouth | "
                  "inner 51 | inner 51 raw | reproj. px (median) | scale error | stage CPU s |",
                  "|---|---|---|---|---|---|---|---|---:|---:|---:|"]
        for c, r in rows.items():
            cells = [f"{r['landmarks'][k]['mean']:.2f} / {r['landmarks'][k]['median']:.2f} / "
                     f"{r['landmarks'][k]['max']:.2f}" for k in ("brows", "nose", "eyes",
                                                                 "mouth", "inner")]
            raw = r["landmarks_raw"]["inner"]
            lines.append(f"| {c} | {r['keyframes']} ({r['detected']} / {r['gated']}) | "
                         + " | ".join(cells)
                         + f" | {raw['mean']:.2f} / {raw['median']:.2f} / {raw['max']:.2f}"
                         f" | {r['reprojection_px']['median']:.2f} | "
                         f"{r['scale_error_percent']:+.2f} % | {r['stage_cpu_s']:.1f} |")
        med = [r["landmarks"]["inner"]["median"] for r in rows.values()]
        sc = [abs(r["scale_error_percent"]) for r in rows.values()]
        lines += ["", f"Bars: inner median <= {BAR_LANDMARKS_MM} mm: "
                      f"{'met' if max(med) <= BAR_LANDMARKS_MM else 'NOT met'} "
                      f"(worst {max(med):.2f} mm); metric scale within {BAR_SCALE_PERCENT} %: "
                      f"{'met' if max(sc) <= BAR_SCALE_PERCENT else 'NOT met'} "
                      f"(worst {max(sc):.2f} %).", ""]
        table_rows = []
        for d in deformations:
            for p in ("similarity", "metric"):
                recs = [r["coarse"][d]["scores"][p] for r in rows.values() if d in r["coarse"]]
                table_rows.append((f"Coarse template, {d} ({p})", recs))
        lines += ["Coarse mesh (paper-style; the paper's landmark-fitting rows: 2.2-2.5 mm "
                  "accuracy mean):", "", paper_table(table_rows), "",
                  "| capture | " + " | ".join(f"{d} CPU s" for d in deformations) + " |",
                  "|---|" + "---:|" * len(deformations)]
        for c, r in rows.items():
            lines.append(f"| {c} | " + " | ".join(f"{r['coarse'][d]['cpu_s']:.2f}"
                                                  for d in deformations) + " |")
        lines.append("")
    return "\n".join(lines)


# --------------------------------------------------------------------------- calibration


def calibration_capture(seed: int, out: Path, ict_model: str) -> Path:
    folder = out / "calibration" / f"ict_{seed}"
    if not (folder / "gt" / "render.json").is_file():
        # The sweep's angular speed and motion blur match the 8 s, 60 fps captures at a
        # quarter of the frames: every frame is a keyframe ~3 degrees from the last.
        config = SynthConfig(subject=f"ict:{seed}", ict_model=ict_model, width=1280,
                             height=720, fps=7.5, duration_s=4.2, yaw_start_deg=-50,
                             yaw_end_deg=50, exposure_fraction=0.031, seed=seed)
        print(f"rendering calibration capture ict:{seed} ...", flush=True)
        synthesize(config, folder, progress=False)
    return folder


# MediaPipe face-mesh vertices along the inner edge of the upper and of the lower lip.
UPPER_INNER_LIP = [78, 191, 80, 81, 82, 13, 312, 311, 310, 415, 308]
LOWER_INNER_LIP = [78, 95, 88, 178, 87, 14, 317, 402, 318, 324, 308]


def calibrate_mesh_vertices(folders: list[Path], command: str) -> None:
    """Which face-mesh vertex stands for each iBUG point (``facecap_core/face.py``): over every
    frame of the calibration sweeps, the vertex whose image lies nearest the projected
    ground-truth landmark (median distance per face box size). Writes ``MESH_TO_68_FILE``.

    Choosing a left-right pair together, as mirror vertices (the mirror map from the
    captures' triangulated meshes), did worse on these captures: 0.0168 of the face box
    median against 0.0143, 2.5-4.4 mm raw 3D error per capture against 2.0-3.4."""
    from facecap_core import face
    from facecap_core.camera import project
    from facecap_core.landmarks.triangulate import box_size
    from facecap_core.video import iter_frames

    face.mesh_to_68.cache_clear()
    before = face.mesh_to_68()
    costs = []
    for folder in folders:
        intr, poses = load_gt_cameras(folder / "gt" / "cameras.json")
        G = load_landmarks(folder / "gt" / "landmarks.json")
        for frame, pose in zip(iter_frames(folder / "video.mp4"), poses):
            det = face.detect(frame.image)
            if det is None:
                continue
            truth, _ = project(G, pose["R"], pose["t"], intr)
            costs.append(np.linalg.norm(det.mesh[None, :468] - truth[:, None], axis=2)
                         / box_size(det.box))
    median = np.median(np.stack(costs), axis=0)  # (68 points, 468 vertices)
    # The rendered mouths are closed, so the upper and lower inner lip coincide there: each
    # inner-lip point is chosen on its own lip's inner edge of the mesh.
    allowed = median.copy()
    for points, ring in ((np.r_[61:64], UPPER_INNER_LIP), (np.r_[65:68], LOWER_INNER_LIP)):
        outside = np.setdiff1d(np.arange(468), ring)
        allowed[np.ix_(points, outside)] = np.inf
    vertices = allowed.argmin(axis=1)
    rows = np.arange(68)
    doc = {"what": "MediaPipe face-mesh vertex (0-467) of each iBUG 300-W point: the vertex "
                   "whose image lies nearest the projected ground-truth landmark, median over "
                   "the calibration frames, per face box size",
           "captures": [f.name for f in folders], "frames": len(costs), "command": command,
           "median_rel_before": median[rows, before].round(5).tolist(),
           "median_rel": median[rows, vertices].round(5).tolist(),
           "vertices": vertices.tolist()}
    face.MESH_TO_68_FILE.write_text(json.dumps(doc, indent=1))
    face.mesh_to_68.cache_clear()
    changed = int(np.sum(vertices != before))
    print(f"wrote {face.MESH_TO_68_FILE}: {changed} of 68 vertices changed; inner 51 median "
          f"{np.median(median[rows, before][INNER_LANDMARKS]):.4f} -> "
          f"{np.median(median[rows, vertices][INNER_LANDMARKS]):.4f} of the face box")


def calibrate(seeds: list[int], out: Path, ict_model: str) -> None:
    from facecap_core.geometry import robust_similarity
    from facecap_core.template import ict_identity_vertices, load_ict_model

    offsets, used = [], []
    config = LandmarkConfig(convention_correction=False)
    command = ("python benchmarks/bench_landmarks.py --calibrate --calibration-seeds "
               + " ".join(map(str, seeds)))
    folders = [calibration_capture(seed, out, ict_model) for seed in seeds]
    calibrate_mesh_vertices(folders, command)
    for seed, folder in zip(seeds, folders):
        work = out / "calibration_runs" / folder.name
        cams = write_gt_keyframe_cameras(folder / "gt" / "cameras.json",
                                               work / "cameras.json", step=1, **WORLD)
        L, _ = load_landmarks3d(stage.main(folder / "video.mp4", cams, work, config))
        L_mm = (L - WORLD["translation"]) @ WORLD["rotation"] / WORLD["scale"]
        G = load_landmarks(folder / "gt" / "landmarks.json")
        offsets.append(convention_offsets(L_mm, G))
        used.append(f"ict:{seed}")
        e = landmark_errors(L_mm, G)[INNER_LANDMARKS]
        print(f"ict:{seed}: raw inner median {np.median(e):.2f} mm")
    doc = {"what": "median offset from triangulated face-mesh 68-point landmarks to ground-truth 3D "
                   "landmarks, inner points 17-67, head-frame axes (x subject's left, y up, z "
                   "out of the face), per eye-centre distance",
           "captures": used, "command": command,
           "stage_config": config.model_dump(mode="json"),
           "spread": np.nanstd(offsets, axis=0).round(5).tolist(),
           # The median over captures: a point triangulated badly in one capture (dropped
           # there as uncertain) does not move the table.
           "offsets": np.nan_to_num(np.nanmedian(offsets, axis=0)).round(5).tolist()}
    OFFSETS_FILE.write_text(json.dumps(doc, indent=1))
    print(f"wrote {OFFSETS_FILE}")

    model = load_ict_model(ict_model)
    template = Template.default()
    src = template.vertices[template.landmarks[INNER_LANDMARKS]]
    sizes = []
    prior = CoarseConfig()
    for seed in range(1000, 1200):
        c = np.random.default_rng([seed, 1]).standard_normal(100)
        G = ict_identity_vertices(model, c)[model["landmarks68"]]
        sizes.append(robust_similarity(src, G[INNER_LANDMARKS], None, prior.robust_iterations,
                                       prior.scale_cauchy_mm)[0])
    sizes = np.array(sizes)
    print(f"landmark size prior over 200 ICT identities: mean {sizes.mean():.4f}, relative "
          f"spread {sizes.std() / sizes.mean():.4f} (CoarseConfig: landmark_size "
          f"{prior.landmark_size}, landmark_size_spread {prior.landmark_size_spread})")


# --------------------------------------------------------------------------- main


def main() -> Path:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--captures", nargs="*", type=Path, default=CAPTURES)
    ap.add_argument("--out", type=Path, default=ROOT / "out/bench_landmarks")
    ap.add_argument("--pipeline", action="store_true", help="also run with pipeline cameras")
    ap.add_argument("--deformations", nargs="*", default=["rbf", "nicp", "none"])
    ap.add_argument("--calibrate", action="store_true")
    ap.add_argument("--calibration-seeds", nargs="*", type=int,
                    default=[101, 102, 103, 104, 105, 106])
    ap.add_argument("--ict-model", default=os.environ.get("FACECAP_ICT_MODEL", str(DEFAULT_ICT)))
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    if args.calibrate:
        calibrate(args.calibration_seeds, args.out, args.ict_model)
        return OFFSETS_FILE
    template = Template.default()
    results = {}
    for capture in args.captures:
        if not (capture / "gt" / "render.json").is_file():
            print(f"skipping {capture}: not rendered (no gt/render.json)")
            continue
        name = capture.name.split("_1280")[0]
        print(f"{name}: GT cameras", flush=True)
        results[name] = {"gt": run_capture(capture, args.out, "gt", args.deformations,
                                           template)}
        if args.pipeline:
            print(f"{name}: pipeline cameras", flush=True)
            results[name]["pipeline"] = run_capture(capture, args.out, "pipeline",
                                                    args.deformations, template)
    text = report(results, args.deformations)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    text += f"\nPeak memory {peak:.0f} MB. Command: python benchmarks/bench_landmarks.py " \
            + " ".join(sys.argv[1:]) + "\n"
    print(text)
    (args.out / "results.json").write_text(json.dumps(results, indent=1))
    path = args.out / "report.md"
    path.write_text(text)
    return path


if __name__ == "__main__":
    main()
