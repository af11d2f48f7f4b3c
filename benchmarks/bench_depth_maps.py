"""Depth-map settings side by side on a rendered capture's own stored run: accuracy on the
face and the ears against the renderer's truth, and seconds per map.

    python benchmarks/bench_depth_maps.py RUN [SETTINGS ...] [--maps 6]

RUN is the output folder of ``facecap reconstruct CAPTURE --scan ...`` of a capture made by
``facecap synth`` (its ``report.json`` names the store and the frames, coarse and views
artifacts; the capture's ``gt/`` folder holds the truth). Each SETTINGS is a JSON object of
``mvs.depth`` fields (``'{}'``: the defaults; ``'{"start": "sweep"}'``). The maps of
``--maps`` keyframes evenly spaced over the run's reference keyframes are computed again with
each setting, one after another on one thread, and scored against the true depth moved into
the run's frame by the similarity that best maps the true camera centres onto the estimated
ones: per setting the median over maps of the per-map median |depth error| on the face
sphere's pixels, the coverage there after the per-map filter, and on the ear region's pixels
(in either ear sphere, outside the face sphere) the median error, the mean error with each
clipped at 10 mm (the ears' outliers, without one wild pixel deciding it) and the coverage.
Seconds are ``compute_depth_map``'s wall time per map with OpenCV on one thread, after one
untimed map of each setting that loads the numba kernels it uses: run on a quiet machine.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import numpy as np
from captures import true_frames, truth_to_run

from facecap.synthetic.ground_truth import gt_depth
from facecap.tasks.store import open_store
from facecap_core.evaluation import region_sphere
from facecap_core.evaluation.region import ear_spheres
from facecap_core.meshio import load_landmarks, load_mesh
from facecap_core.mvs.depth import DepthMapConfig, compute_depth_map
from facecap_core.mvs.images import load_view
from facecap_core.mvs.views import read_views
from facecap_core.pose.cameras_json import read_cameras_json

EAR_ERROR_CLIP_MM = 10.0


def region_masks(view, V, F, face: tuple[np.ndarray, float], ears: tuple[np.ndarray, float]):
    """True depth of ``view`` and its face and ear pixels (the truth's hit point in the face
    sphere; in an ear sphere and not in the face sphere)."""
    depth, points = gt_depth(view, V, F)
    hit = np.isfinite(depth)
    p = np.nan_to_num(points)
    in_face = np.linalg.norm(p - face[0], axis=-1) <= face[1]
    in_ear = np.linalg.norm(p[..., None, :] - ears[0], axis=-1).min(-1) <= ears[1]
    return depth, hit & in_face, hit & in_ear & ~in_face


def score(maps, truth) -> dict:
    """Face: median over maps of the per-map median error, coverage median; ears: pooled."""
    face_err, face_cov, ear_err, ear_ok, ear_all = [], [], [], 0, 0
    for dm, (depth, face, ear) in zip(maps, truth, strict=True):
        ok = face & (dm.depth > 0)
        if face.sum() >= 100:
            face_err.append(np.median(np.abs(dm.depth[ok] - depth[ok])) if ok.any() else np.nan)
            face_cov.append(100.0 * ok.sum() / face.sum())
        seen = ear & (dm.depth > 0)
        ear_err.append(np.abs(dm.depth[seen] - depth[seen]))
        ear_ok += int(seen.sum())
        ear_all += int(ear.sum())
    ears = np.concatenate(ear_err) if ear_err else np.zeros(0)
    return {"face_median_mm": float(np.nanmedian(face_err)) if face_err else float("nan"),
            "face_coverage_pct": float(np.median(face_cov)) if face_cov else float("nan"),
            "ears_median_mm": float(np.median(ears)) if ears.size else float("nan"),
            "ears_mean10_mm": (float(np.mean(np.minimum(ears, EAR_ERROR_CLIP_MM)))
                               if ears.size else float("nan")),
            "ears_coverage_pct": 100.0 * ear_ok / max(ear_all, 1)}


def main(argv=None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("settings", nargs="*", default=["{}"])
    parser.add_argument("--maps", type=int, default=6)
    args = parser.parse_args(argv)

    report = json.loads((args.run / "report.json").read_text())
    store, stages = open_store(report["store"]), report["stages"]
    frames, coarse_dir, views_dir = (store.get(stages[name]["key"])
                                     for name in ("frames", "coarse", "views"))
    cams = read_cameras_json(coarse_dir / "cameras.json")
    sources = read_views(views_dir / "views.json")
    indices = sorted(sources)
    gt_dir = Path(report["video"]).parent / "gt"
    _, gt_frames = true_frames(gt_dir)
    s, R, t = truth_to_run(cams, gt_frames, indices)
    gt = load_mesh(gt_dir / "mesh.ply")
    V = s * np.asarray(gt.vertices, float) @ R.T + t
    F = np.asarray(gt.faces)
    landmarks = load_landmarks(gt_dir / "landmarks.json")
    centre, radius = region_sphere(landmarks)
    ear_centres, ear_radius = ear_spheres(landmarks)
    face = (s * R @ centre + t, s * radius)
    ears = (s * ear_centres @ R.T + t, s * ear_radius)
    coarse = load_mesh(coarse_dir / "coarse.ply")

    picks = np.linspace(0, len(indices) - 1, min(args.maps, len(indices))).round().astype(int)
    pick = [indices[k] for k in np.unique(picks)]
    # One core, as a depth map has in the stage (OpenCV would spread the sweep's filters over
    # every core while numba's PatchMatch keeps to one).
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        return _compare(args.settings, pick, frames, cams, sources, coarse, V, F, face, ears)
    finally:
        cv2.setNumThreads(threads)


def _compare(settings, pick, frames, cams, sources, coarse, V, F, face, ears) -> list[dict]:
    """Each setting's maps of ``pick``, scored and timed (one untimed map first, which loads
    the numba kernels the setting uses)."""
    rows, truth, views = [], {}, {}
    for text in settings:
        config = DepthMapConfig(**json.loads(text))
        width = config.processing_width
        if width not in views:
            views[width] = {i: (load_view(frames, cams, i, width),
                                [load_view(frames, cams, j, width) for j in sources[i]])
                            for i in pick}
            truth[width] = [region_masks(views[width][i][0], V, F, face, ears) for i in pick]
        maps, seconds = [], []
        ref, srcs = views[width][pick[0]]
        compute_depth_map(ref, srcs, coarse.vertices, coarse.faces, config)
        for i in pick:
            ref, srcs = views[width][i]
            start = time.perf_counter()
            _, filtered = compute_depth_map(ref, srcs, coarse.vertices, coarse.faces, config)
            seconds.append(time.perf_counter() - start)
            maps.append(filtered)
        row = {"settings": json.loads(text), **score(maps, truth[width]),
               "s_per_map": float(np.mean(seconds))}
        rows.append(row)
        print(f"{text}: face {row['face_median_mm']:.3f} mm ({row['face_coverage_pct']:.1f} %), "
              f"ears {row['ears_median_mm']:.3f} / {row['ears_mean10_mm']:.3f} mm "
              f"({row['ears_coverage_pct']:.1f} %), {row['s_per_map']:.2f} s/map", flush=True)
    return rows


if __name__ == "__main__":
    main()
