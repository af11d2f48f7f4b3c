"""Dense MVS stage against ground truth: depth-map error, fused-cloud accuracy/completion, speed.

    python benchmarks/bench_mvs.py [--subjects ict:0 ict:1 james] [--width 1280 --height 720]
        [--keyframes 40] [--proc-width 640] [--out out/bench_mvs] [--no-peer]
        [--pipeline out/bench_pipeline [--pipeline-only]]

Per subject a synthetic capture is rendered once (cached under OUT/captures). The stage is
fed ground-truth cameras, keyframes evenly spaced over the sweep, sparse points = GT mesh
vertices (subsampled, visibility by ray casting) and a coarse mesh = the GT mesh smoothed
and offset by a ~2.5 mm low-frequency field, so that MVS is judged alone. A fronto-parallel
plane sweep (numpy/OpenCV) on the same inputs, filtered and fused the same way, is the peer.
Prints a table and writes OUT/report.md.

With ``--pipeline`` the stage is judged a second time on the pipeline's own inputs: the
depth maps, views and coarse mesh that ``benchmarks/bench_pipeline.py`` left in its store
(PBA cameras, landmark-fitted coarse mesh), scored against the ground truth moved into the
run's frame by the similarity that best maps the true camera centres onto the estimated ones
(so the figures hold the pose stage's errors, not its gauge). The peer runs on the same inputs.
"""

from __future__ import annotations

import argparse
import resource
import time
import zlib
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numba
import numpy as np
import trimesh
from captures import capture_for, true_frames, truth_to_run
from scipy.spatial import cKDTree

from facecap.synthetic import load_gt_cameras
from facecap.synthetic.ground_truth import coarse_from_gt, even_keyframes, gt_depth, load_views
from facecap_core.evaluation import distances, region_sphere
from facecap_core.meshio import load_landmarks, load_mesh
from facecap_core.mvs.depth import compute_depth_map
from facecap_core.mvs.filtering import filter_with_prior, geometric_filter
from facecap_core.mvs.fusion import fuse, write_ply
from facecap_core.mvs.prior import coarse_prior
from facecap_core.mvs.sweep import sweep_depth as plane_sweep
from facecap_core.mvs.views import choose_sources, sparse_from_mesh, visible_points
from facecap_core.pipeline import MVSConfig

BARS = {"depth_median_mm": 0.5, "coverage_pct": 90.0, "accuracy_median_mm": 0.5,
        "completion_pct": 95.0, "s_per_map": 10.0}


def depth_scores(maps, views, V, F, centre, radius):
    """Per map: (median |depth error| mm, coverage %) on face pixels (GT hit in the sphere)."""
    errs, covs = [], []
    for dm, view in zip(maps, views):
        d, P = gt_depth(view, V, F)
        face = np.isfinite(d) & (np.linalg.norm(np.nan_to_num(P) - centre, axis=-1) <= radius)
        if face.sum() < 100:
            continue
        ok = face & (dm.depth > 0)
        errs.append(np.median(np.abs(dm.depth[ok] - d[ok])) if ok.any() else np.nan)
        covs.append(100.0 * ok.sum() / face.sum())
    return float(np.nanmedian(errs)), float(np.median(covs)), float(np.min(covs))


def cloud_scores(cloud, V, F, centre, radius, samples, seen):
    """Accuracy median (cloud points in the sphere -> GT surface), completion (% of GT face
    area samples within 2 mm of the cloud), points in the sphere, and the completion of the
    samples ``seen`` by at least two views (the mouth's inside, the nostrils and the skin
    under the chin are in the sphere but no keyframe sees them well)."""
    inside = np.linalg.norm(cloud.points - centre, axis=1) <= radius
    acc = distances(cloud.points[inside], V, F)
    if len(cloud.points) == 0:
        return np.nan, 0.0, 0, 0.0
    dist, _ = cKDTree(cloud.points).query(samples)
    near = dist <= 2.0
    return (float(np.median(acc)), float(100.0 * np.mean(near)), int(inside.sum()),
            float(100.0 * np.mean(near[seen])))


def seen_twice(samples, views, V, F):
    """Which samples at least two of the views see (in the image, not occluded)."""
    return visible_points(samples, [(v.intr, v.R, v.t) for v in views], V, F).sum(0) >= 2


def face_samples(V, F, centre, radius, count=20000, seed=0):
    mesh = trimesh.Trimesh(V, F, process=False)
    pts, _ = trimesh.sample.sample_surface_even(mesh, count * 4, seed=seed)
    return pts[np.linalg.norm(pts - centre, axis=1) <= radius]



def consistent_and_fused(maps, views, config):
    """The geometric-consistency filter and the fusion, as the stage runs them."""
    f = config.fusion
    geo = geometric_filter(maps, f.min_consistent_views, f.max_depth_mm, f.max_reprojection_px,
                           f.max_normal_deg)
    cloud = fuse(geo, [v.rgb for v in views], f.min_consistent_views, f.max_depth_mm,
                 f.max_reprojection_px, f.max_normal_deg)
    return geo, cloud

def run_subject(subject, args, config, out):
    folder = capture_for(subject, out / "captures", args.ict_model, width=args.width,
                         height=args.height)
    gt = load_mesh(folder / "gt" / "mesh.ply")
    V, F = np.asarray(gt.vertices, float), np.asarray(gt.faces)
    centre, radius = region_sphere(load_landmarks(folder / "gt" / "landmarks.json"))
    _, frames = load_gt_cameras(folder / "gt" / "cameras.json")
    keyframes = even_keyframes(len(frames), args.keyframes)
    views = load_views(folder, keyframes, args.proc_width)
    coarse = coarse_from_gt(V, F, seed=zlib.crc32(subject.encode()) % 1000)  # stable per subject
    points, vis = sparse_from_mesh(views, V, F, count=4000)
    sources = choose_sources(views, points, vis, config.views)
    samples = face_samples(V, F, centre, radius)
    seen = seen_twice(samples, views, V, F)
    rows = {}

    # Speed on one core: a few maps one after another on this thread.
    numba.set_num_threads(1)
    compute_depth_map(views[0], [views[j] for j in sources[0]], coarse, F, config.depth)  # JIT/cache
    mid = len(views) // 2
    single = [compute_depth_map(views[i], [views[j] for j in sources[i]], coarse, F, config.depth)[0]
              for i in range(mid - args.speed_maps // 2, mid - args.speed_maps // 2 + args.speed_maps)]

    # All keyframes with ``workers`` threads.
    t0 = time.perf_counter()
    with ThreadPoolExecutor(config.workers) as pool:
        res = list(pool.map(lambda i: compute_depth_map(
            views[i], [views[j] for j in sources[i]], coarse, F, config.depth), range(len(views))))
    t_maps = time.perf_counter() - t0
    raw = [r[0] for r in res]
    filt = [r[1] for r in res]
    t1 = time.perf_counter()
    geo, cloud = consistent_and_fused(filt, views, config)
    t_fuse = time.perf_counter() - t1
    write_ply(cloud, out / f"{subject.replace(':', '_')}_cloud.ply")
    rows["patchmatch"] = {
        "raw": depth_scores(raw, views, V, F, centre, radius),
        "filtered": depth_scores(filt, views, V, F, centre, radius),
        "geometric": depth_scores(geo, views, V, F, centre, radius),
        "cloud": cloud_scores(cloud, V, F, centre, radius, samples, seen),
        "points": len(cloud),
        "wall_1core": float(np.median([m.seconds for m in single])),
        "cpu_per_map": float(np.median([m.cpu_seconds for m in raw])),
        "total_s": t_maps, "fuse_s": t_fuse,
        "pixels": float(np.median([(m.cost < 2).sum() for m in raw])),
    }

    if args.peer:
        t0 = time.perf_counter()

        def peer(i):
            prior = coarse_prior(views[i], coarse, F, config.depth.depth_margin_mm,
                                 config.depth.head_dilation_px)
            dm = plane_sweep(views[i], [views[j] for j in sources[i]], prior,
                             config.depth.depth_margin_mm, config.depth.sweep_step_mm,
                             radius=config.depth.window_radius,
                             nbest=config.depth.num_best_views)
            return dm, filter_with_prior(dm, prior, config.depth.max_cost,
                                         config.depth.coarse_max_distance_mm, config.depth.depth_margin_mm)

        with ThreadPoolExecutor(config.workers) as pool:
            pres = list(pool.map(peer, range(len(views))))
        t_maps = time.perf_counter() - t0
        pfilt = [r[1] for r in pres]
        t1 = time.perf_counter()
        pgeo, pcloud = consistent_and_fused(pfilt, views, config)
        rows["plane sweep (peer)"] = {
            "raw": depth_scores([r[0] for r in pres], views, V, F, centre, radius),
            "filtered": depth_scores(pfilt, views, V, F, centre, radius),
            "geometric": depth_scores(pgeo, views, V, F, centre, radius),
            "cloud": cloud_scores(pcloud, V, F, centre, radius, samples, seen),
            "points": len(pcloud),
            "wall_1core": float("nan"),
            "cpu_per_map": float(np.median([r[0].cpu_seconds for r in pres])),
            "total_s": t_maps, "fuse_s": time.perf_counter() - t1,
            "pixels": float(np.median([(r[0].cost < 2).sum() for r in pres])),
        }
    return rows, len(views)


def pipeline_subject(result: Path, config, peer: bool):
    """Scores of a bench_pipeline run (``result``: its ``<subject>/full`` folder)."""
    import json
    from types import SimpleNamespace

    from facecap.tasks.store import open_store
    from facecap_core.mvs.depth import load_depth_map
    from facecap_core.mvs.images import load_view
    from facecap_core.mvs.views import read_views
    from facecap_core.pose.cameras_json import read_cameras_json

    report = json.loads((result / "report.json").read_text())
    store, stages = open_store(report["store"]), report["stages"]
    frames, coarse_dir, views_dir = (store.get(stages[n]["key"]) for n in ("frames", "coarse",
                                                                            "views"))
    cams = read_cameras_json(coarse_dir / "cameras.json")
    gt_dir = Path(report["video"]).parent / "gt"
    gt_intr, gt_frames = true_frames(gt_dir)
    indices = sorted(read_views(views_dir / "views.json"))
    s, R, t = truth_to_run(cams, gt_frames, indices)  # ground truth -> the run's frame
    gt = load_mesh(gt_dir / "mesh.ply")
    V, F = np.asarray(gt.vertices, float), np.asarray(gt.faces)
    Vp = s * V @ R.T + t
    centre, radius = region_sphere(load_landmarks(gt_dir / "landmarks.json"))
    centre_p, radius_p = s * R @ centre + t, s * radius
    maps = [load_depth_map(store.get(stages[f"depth_{i:05d}"]["key"]) / f"depth_{i:05d}.npz")
            for i in indices]
    width = int(round(maps[0].intr.width))
    views = [load_view(frames, cams, i, width) for i in indices]
    coarse = load_mesh(coarse_dir / "coarse.ply")
    samples = face_samples(V, F, centre, radius)

    def to_gt(cloud):
        return SimpleNamespace(points=((cloud.points - t) @ R) / s)

    # Seen by the true cameras of the same keyframes.
    true_views = [SimpleNamespace(intr=gt_intr, R=gt_frames[i]["R"], t=gt_frames[i]["t"])
                  for i in indices]
    seen = seen_twice(samples, true_views, V, F)

    def scores(filtered, raw=None):
        geo, cloud = consistent_and_fused(filtered, views, config)
        return {"raw": depth_scores(raw or filtered, views, Vp, F, centre_p, radius_p),
                "filtered": depth_scores(filtered, views, Vp, F, centre_p, radius_p),
                "geometric": depth_scores(geo, views, Vp, F, centre_p, radius_p),
                "cloud": cloud_scores(to_gt(cloud), V, F, centre, radius, samples, seen),
                "points": len(cloud)}

    metas = [json.loads((store.get(stages[f"depth_{i:05d}"]["key"]) /
                         f"depth_{i:05d}.json").read_text()) for i in indices]
    speed = {"wall_1core": float("nan"),
             "cpu_per_map": float(np.median([m["cpu_seconds"] for m in metas])),
             "total_s": sum(stages[f"depth_{i:05d}"]["seconds"] for i in indices) / config.workers,
             "fuse_s": float(stages["fusion"]["seconds"])}
    rows = {"patchmatch": {**scores(maps), **speed}}
    if peer:
        sources = read_views(views_dir / "views.json")
        by_index = dict(zip(indices, views))
        all_views = {**by_index, **{j: load_view(frames, cams, j, width)
                                    for js in sources.values() for j in js if j not in by_index}}

        def sweep(i):
            prior = coarse_prior(by_index[i], coarse.vertices, coarse.faces,
                                 config.depth.depth_margin_mm, config.depth.head_dilation_px)
            dm = plane_sweep(by_index[i], [all_views[j] for j in sources[i]], prior,
                             config.depth.depth_margin_mm, config.depth.sweep_step_mm,
                             radius=config.depth.window_radius,
                             nbest=config.depth.num_best_views)
            return dm, filter_with_prior(dm, prior, config.depth.max_cost,
                                         config.depth.coarse_max_distance_mm, config.depth.depth_margin_mm)

        t0 = time.perf_counter()
        with ThreadPoolExecutor(config.workers) as pool:
            pres = list(pool.map(sweep, indices))
        total = time.perf_counter() - t0
        speed = {"wall_1core": float("nan"),
                 "cpu_per_map": float(np.median([r[0].cpu_seconds for r in pres])),
                 "total_s": total, "fuse_s": float("nan")}
        rows["plane sweep (peer)"] = {**scores([r[1] for r in pres], [r[0] for r in pres]),
                                      **speed}
    return rows, len(indices)


def table(results, args, config) -> str:
    head = ("| subject | method | depth med mm (raw / filtered) | coverage % filtered (min) "
            "| after geo-filter: med mm, cov % | cloud acc med mm | completion % ≤2 mm "
            "(of the surface seen twice) | points "
            "| s/map 1 core wall | CPU s/map | total s (2 workers) | fuse s |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for subject, (rows, _) in results.items():
        for name, r in rows.items():
            raw, fl, ge, cl = r["raw"], r["filtered"], r["geometric"], r["cloud"]
            lines.append(
                f"| {subject} | {name} | {raw[0]:.3f} / {fl[0]:.3f} | {fl[1]:.1f} ({fl[2]:.1f}) "
                f"| {ge[0]:.3f}, {ge[1]:.1f} | {cl[0]:.3f} | {cl[1]:.1f} ({cl[3]:.1f}) | {r['points']} "
                f"| {r['wall_1core']:.2f} | {r['cpu_per_map']:.2f} | {r['total_s']:.1f} "
                f"| {r['fuse_s']:.1f} |")
    return "\n".join(lines)


def main(argv=None) -> Path:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--subjects", nargs="+", default=["ict:0", "ict:1", "james"])
    p.add_argument("--width", type=int, default=1280)
    p.add_argument("--height", type=int, default=720)
    p.add_argument("--keyframes", type=int, default=40)
    p.add_argument("--proc-width", type=int, default=640)
    p.add_argument("--speed-maps", type=int, default=3)
    p.add_argument("--out", type=Path, default=Path("out/bench_mvs"))
    p.add_argument("--ict-model", default=None)
    p.add_argument("--no-peer", dest="peer", action="store_false")
    p.add_argument("--pipeline", type=Path, metavar="BENCH_PIPELINE_OUT",
                   help="also score the depth maps and cloud of this bench_pipeline output "
                        "(its <subject>/full runs) on the pipeline's own inputs")
    p.add_argument("--pipeline-only", action="store_true",
                   help="skip the run on ground-truth inputs")
    p.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE",
                   help="MVSConfig overrides, e.g. --set depth.iterations=6 views.num_sources=8")
    args = p.parse_args(argv)
    sections: dict = {"depth": {"processing_width": args.proc_width}}
    for kv in args.set:
        name, value = kv.split("=", 1)
        section, _, field = name.partition(".")
        sections.setdefault(section, {})[field] = value
    config = MVSConfig.model_validate(sections)
    args.out.mkdir(parents=True, exist_ok=True)
    results = {}
    for subject in args.subjects if not args.pipeline_only else ():
        results[subject] = run_subject(subject, args, config, args.out)
        print(table({subject: results[subject]}, args, config), flush=True)
    piped = {}
    for subject in args.subjects if args.pipeline else ():
        result = args.pipeline / subject.replace(":", "_") / "full"
        if not (result / "report.json").is_file():
            print(f"{result}/report.json missing: run benchmarks/bench_pipeline.py first")
            continue
        piped[subject] = pipeline_subject(result, config, args.peer)
        print(table({subject: piped[subject]}, args, config), flush=True)
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    report = (f"# bench_mvs\n\n{len(args.subjects)} subjects, {args.width}x{args.height} "
              f"captures, {args.keyframes} keyframes, processing width {args.proc_width}, "
              f"{config.views.num_sources} sources, {config.depth.iterations} iterations, window radius "
              f"{config.depth.window_radius} step {config.depth.window_step}, best {config.depth.num_best_views}"
              f" views; {config.workers} workers. Peak RSS {peak_mb:.0f} MB.\n\n"
              f"{table(results, args, config)}\n\n"
              f"Bars: depth median ≤ {BARS['depth_median_mm']} mm, coverage ≥ "
              f"{BARS['coverage_pct']} %, cloud accuracy median ≤ {BARS['accuracy_median_mm']}"
              f" mm, completion ≥ {BARS['completion_pct']} %, ≤ {BARS['s_per_map']} s/map on "
              "one core.\n")
    if piped:
        report += ("\n## On the pipeline's own inputs\n\nThe depth maps, views and coarse "
                   f"mesh of {args.pipeline} (PBA cameras, landmark-fitted coarse mesh; "
                   "CPU s/map and total from the run's artifacts, total = sum / workers); "
                   "ground truth moved into the run's frame by the similarity of the camera "
                   "centres. Depth errors in the run's millimetres, cloud figures in the "
                   f"true ones.\n\n{table(piped, args, config)}\n")
    print("\n" + report)
    path = args.out / ("report_pipeline.md" if args.pipeline_only else "report.md")
    path.write_text(report)
    return path


if __name__ == "__main__":
    main()
