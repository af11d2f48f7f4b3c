"""Two ``bench_pipeline.py`` runs side by side, per capture: time, cameras, cloud, mesh.

    python benchmarks/compare_pipeline.py BEFORE AFTER [--out report.md]

BEFORE and AFTER are the ``--out`` folders of two ``bench_pipeline.py`` runs over the same
rendered captures (fresh stores). Per capture and run: wall time and the stages' seconds as
computed (depth: the maps' seconds summed, over the run's two workers: about the stage's
wall time), the pose figures against the ground-truth cameras
(:func:`facecap_core.pose.evaluate.pose_errors`), the fused cloud's accuracy median (its
points in the face sphere to the scan, the scan moved into the run's frame by the
similarity that maps the true camera centres onto the estimated ones), the mesh's accuracy
mean / median in the face sphere and the ear region (similarity and metric protocols), the
mesh's sanity and roughness. Ends with the change of each median, in per cent.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import open3d as o3d
from captures import true_frames, truth_to_run

from facecap_core.evaluation import distances, region_sphere
from facecap_core.meshio import load_landmarks, load_mesh
from facecap_core.pose.cameras_json import read_cameras_json
from facecap_core.pose.evaluate import pose_errors

STAGES = ("keyframes", "poses", "landmarks", "depth", "fusion", "fitting", "evaluation")
WORKERS = 2


def capture_figures(result: Path) -> dict:
    """The figures of one capture's ``full`` run folder."""
    report = json.loads((result / "report.json").read_text())
    gt_dir = Path(report["video"]).parent / "gt"
    seconds: dict[str, float] = {}
    for name, info in report["stages"].items():
        key = "depth" if name.startswith("depth_") else name
        seconds[key] = seconds.get(key, 0.0) + (info["seconds"] or 0.0)
    seconds["depth"] = seconds.get("depth", 0.0) / WORKERS
    cams = read_cameras_json(result / "cameras.json")
    gt_intr, gt = true_frames(gt_dir)
    indices = [i for i in cams.frame_indices if i in gt]
    poses = [cams.pose(i) for i in indices]
    pose = pose_errors([p[0] for p in poses], [p[1] for p in poses], cams.intrinsics,
                       [gt[i]["R"] for i in indices], [gt[i]["t"] for i in indices], gt_intr)
    s, R, t = truth_to_run(cams, gt, indices)
    scan = load_mesh(gt_dir / "mesh.ply")
    centre, radius = region_sphere(load_landmarks(gt_dir / "landmarks.json"))
    cloud = _cloud_points(result / "cloud.ply")
    in_gt = ((cloud - t) @ R) / s
    inside = np.linalg.norm(in_gt - centre, axis=1) <= radius
    cloud_acc = float(np.median(distances(in_gt[inside], np.asarray(scan.vertices, float),
                                          np.asarray(scan.faces))))
    ev = report["figures"]["evaluation"]
    fig = report["figures"]
    return {"wall_s": report["wall_seconds"], "seconds": seconds, "pose": pose,
            "cloud_accuracy_median_mm": cloud_acc,
            "face": {p: (ev[p]["accuracy"]["mean"], ev[p]["accuracy"]["median"])
                     for p in ("similarity", "metric")},
            "ears": {p: (ev[p]["ears"]["accuracy"]["mean"], ev[p]["ears"]["accuracy"]["median"])
                     for p in ("similarity", "metric") if ev[p].get("ears")},
            "sanity": fig["mesh_sanity"], "roughness": fig["roughness"]}


def _cloud_points(path: Path) -> np.ndarray:
    return np.asarray(o3d.io.read_point_cloud(str(path)).points, float)


def table(runs: dict[str, dict[str, dict]]) -> str:
    names = list(runs)
    subjects = [s for s in runs[names[0]] if all(s in runs[n] for n in names)]
    lines = ["| capture | run | wall s | " + " | ".join(STAGES) + " | rotation ° | centre % | "
             "focal % | pp px | cloud acc. median | face sim. mean/median | face metric "
             "mean/median | ears sim. | ears metric | flipped / stretched / intersecting | "
             "bent % |", "|---|---|" + "---:|" * (len(STAGES) + 14)]
    for subject in subjects:
        for name in names:
            f = runs[name][subject]
            p, sec = f["pose"], f["seconds"]
            ears = [f"{f['ears'][q][0]:.2f} / {f['ears'][q][1]:.2f}" if q in f["ears"] else "-"
                    for q in ("similarity", "metric")]
            san = f["sanity"]
            lines.append(
                f"| {subject} | {name} | {f['wall_s']:.0f} | "
                + " | ".join(f"{sec.get(s, 0.0):.1f}" for s in STAGES)
                + f" | {p['rotation_deg']:.3f} | {p['centre_pct']:.3f} | {p['focal_pct']:.2f} | "
                f"{p['principal_point_px']:.2f} | {f['cloud_accuracy_median_mm']:.3f} | "
                f"{f['face']['similarity'][0]:.3f} / {f['face']['similarity'][1]:.3f} | "
                f"{f['face']['metric'][0]:.3f} / {f['face']['metric'][1]:.3f} | {ears[0]} | "
                f"{ears[1]} | {san['flipped']} / {san['stretched_edges']} / "
                f"{san['self_intersecting_pairs']} | {f['roughness']['bent_share_pct']} |")
    if len(names) == 2:
        a, b = (runs[n] for n in names)
        lines.append("")
        lines.append(f"Change of the medians over captures, {names[0]} → {names[1]}:")

        def med(run, get):
            return float(np.median([get(run[s]) for s in subjects]))

        for label, get in (
                ("wall s", lambda f: f["wall_s"]),
                ("rotation °", lambda f: f["pose"]["rotation_deg"]),
                ("cloud accuracy median mm", lambda f: f["cloud_accuracy_median_mm"]),
                ("face accuracy median, similarity mm", lambda f: f["face"]["similarity"][1]),
                ("face accuracy median, metric mm", lambda f: f["face"]["metric"][1]),
                ("ear accuracy median, similarity mm",
                 lambda f: f["ears"].get("similarity", (np.nan, np.nan))[1]),
                ("ear accuracy median, metric mm",
                 lambda f: f["ears"].get("metric", (np.nan, np.nan))[1])):
            x, y = med(a, get), med(b, get)
            lines.append(f"- {label}: {x:.3f} → {y:.3f} ({100 * (y / x - 1):+.1f} %)")
    return "\n".join(lines)


def main() -> Path | None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path, help="bench_pipeline.py --out folders")
    ap.add_argument("--out", type=Path, help="write the table here too")
    args = ap.parse_args()
    runs = {}
    for folder in args.runs:
        runs[folder.name] = {sub.name: capture_figures(sub / "full")
                             for sub in sorted(folder.iterdir())
                             if (sub / "full" / "report.json").is_file()}
    text = table(runs)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")
    return args.out


if __name__ == "__main__":
    main()
