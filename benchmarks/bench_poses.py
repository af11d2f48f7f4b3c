"""Camera tracking against ground truth: keyframes, then three solutions side by side.

    python benchmarks/bench_poses.py [--captures out/captures/ict_0_1280x720_60fps_8s ...]
        [--out out/bench_poses]

Per capture (a synthetic video with gt/cameras.json per video frame): the keyframes (LK
tracking), then on the same keyframes (a) pycolmap incremental mapping as a user would run
it (SIFT on the full-resolution keyframes, sequential matching, RADIAL camera, principal point
at the image centre), (b) our geometric solution ((a) + the LK tracks + bundle adjustment with
the principal point free), (c) photometric bundle adjustment from (b). Errors after a
similarity alignment of the camera centres: median rotation (°), median centre (% of the
mean camera distance), focal length (%), principal point (px), k1; and the surface (%
of the head's size: the true head triangulated from perfect matches with the cameras,
``facecap_core.pose.evaluate.surface_error``). Seconds are wall and CPU
(all threads) on the shared 2-core machine. Writes OUT/report.md and OUT/results.json.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from facecap.synthetic import load_gt_cameras
from facecap_core.keyframes import KeyframeConfig, select_keyframes
from facecap_core.pose.colmap_sfm import run_sfm
from facecap_core.pose.evaluate import head_surface, pose_errors, surface_error
from facecap_core.pose.geometric import refine_with_tracks
from facecap_core.pose.stage import PoseConfig, photometric_refinement
from facecap_core.video import read_frames

CAPTURES = [f"out/captures/{name}_1280x720_30fps_8s"
            for name in ("ict_1", "ict_2", "james", "ict_0_rs20")]
"""The evaluation captures (docs/poses.md says how each is rendered); ict:4, ict:5 and ict:6
are the calibration captures of PBA's settings and are not evaluated here."""
BARS = {"rotation_deg": 0.04, "centre_pct": 0.05, "focal_pct": 0.25}
WORSE_DEG = 0.01
"""Final rotations count as worse than the geometric start's beyond this (the figures'
rounding; bench_pose_starts.py's verdict)."""
ROWS = {"sfm": "(a) pycolmap incremental mapping",
        "geometric": "(b) ours, geometric (SfM + LK tracks + BA)",
        "pba": "(c) ours, photometric BA (the default)",
        "pba_no_blur": "(d) = (c) without the motion-blur model",
        "pba_photometric": "(e) photometric residuals only, intrinsics held, centre prior",
        "pba_pp_free": "(f) = (c) with the principal point free (no prior, as before it)"}
ABLATIONS = {"pba_no_blur": {"motion_blur": False},
             "pba_photometric": {"track_weight": 0.0, "refine_intrinsics": False,
                                 "centre_prior_pct": 0.05},
             "pba_pp_free": {"principal_point_prior_pct": 0.0}}
"""What each PBA ingredient contributes: (c) with one thing taken away."""


class Timer:
    def __enter__(self):
        self.wall, self.cpu = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc):
        self.wall = time.perf_counter() - self.wall
        self.cpu = time.process_time() - self.cpu


def run_capture(capture: Path, work: Path, config: PoseConfig, ablations: bool = True) -> dict:
    video = capture / "video.mp4"
    intr_gt, gt = load_gt_cameras(capture / "gt" / "cameras.json")
    surface = head_surface(capture / "gt" / "mesh.ply")
    with Timer() as t_kf:
        keyframes = select_keyframes(video, KeyframeConfig())
    result = {"capture": capture.name, "keyframes": len(keyframes.indices),
              "frames": keyframes.frames_read,
              "keyframes_s": [round(t_kf.wall, 1), round(t_kf.cpu, 1)], "rows": {}}
    print(f"{capture.name}: {len(keyframes.indices)} keyframes of {keyframes.frames_read} "
          f"frames in {t_kf.wall:.1f} s ({t_kf.cpu:.1f} s CPU)", flush=True)

    def score(name, poses, timer, extra=(0.0, 0.0)):
        idx = poses.frame_indices
        truth = [gt[i]["R"] for i in idx], [gt[i]["t"] for i in idx], intr_gt
        err = pose_errors(poses.R, poses.t, poses.intrinsics, *truth)
        err["surface_pct"] = surface_error(poses.R, poses.t, poses.intrinsics, *truth,
                                           *surface)["surface_pct"]
        err["seconds"] = round(timer.wall + extra[0], 1)
        err["cpu_seconds"] = round(timer.cpu + extra[1], 1)
        err["registered"] = f"{len(idx)}/{len(keyframes.indices)}"
        result["rows"][name] = err
        print(f"  {ROWS[name]}: " + ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else
                                               f"{k} {v}" for k, v in err.items()), flush=True)

    with Timer() as t_sfm:
        images = read_frames(video, keyframes.indices, width=config.sfm_width)
        sfm = run_sfm(images, work / "sfm", keyframes.video_size, overlap=config.match_overlap)
    score("sfm", sfm, t_sfm)
    with Timer() as t_geo:
        geo = refine_with_tracks(sfm, keyframes.observations, keyframes.indices,
                                 work / "geometric")
    # (b) includes (a): its SIFT, matching and mapping are ours too.
    score("geometric", geo, t_geo, (t_sfm.wall, t_sfm.cpu))
    with Timer() as t_pba:
        greys = read_frames(video, geo.frame_indices, grey=True)
        pba = photometric_refinement(geo, [greys[i] for i in geo.frame_indices], config,
                                     keyframes=keyframes)
    score("pba", pba, t_pba, (t_sfm.wall + t_geo.wall, t_sfm.cpu + t_geo.cpu))
    if ablations:
        for name, change in ABLATIONS.items():
            variant = config.model_copy(update={"pba": config.pba.model_copy(update=change)})
            with Timer() as t_var:
                poses = photometric_refinement(geo, [greys[i] for i in geo.frame_indices],
                                               variant, keyframes=keyframes)
            score(name, poses, t_var, (t_sfm.wall + t_geo.wall, t_sfm.cpu + t_geo.cpu))
    result["pba_only_s"] = [round(t_pba.wall, 1), round(t_pba.cpu, 1)]
    result["tracking_keyframes_pba_s"] = [round(t_kf.wall + t_pba.wall, 1),
                                          round(t_kf.cpu + t_pba.cpu, 1)]
    return result


def report(results: list[dict]) -> str:
    lines = ["# Camera tracking benchmark (`benchmarks/bench_poses.py`)", "",
             "Errors after a similarity alignment of the camera centres to ground truth. "
             "Seconds: wall / CPU (all threads) on the 2-core machine; compare wall times only "
             "between quiet runs. "
             "(b) includes the time of (a); (c) includes (a) and (b).", "",
             "| capture | keyframes | solution | rotation ° | centre % | focal % | pp px | k1 err "
             "| surface % | seconds (wall / CPU) |", "|---|---:|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in results:
        for name, e in r["rows"].items():
            lines.append(f"| {r['capture']} | {r['keyframes']} | {ROWS[name]} | "
                         f"{e['rotation_deg']:.3f} | {e['centre_pct']:.3f} | {e['focal_pct']:.3f}"
                         f" | {e['principal_point_px']:.2f} | {e['k1_error']:+.4f} | "
                         f"{e.get('surface_pct', np.nan):.3f} | "
                         f"{e['seconds']:.0f} / {e['cpu_seconds']:.0f} |")
    lines += ["", "| solution | median rotation ° | median centre % | median focal % | median "
              "surface % |", "|---|---:|---:|---:|---:|"]
    for name, label in ROWS.items():
        if not all(name in r["rows"] for r in results):
            continue
        vals = [[r["rows"][name].get(k, np.nan) for r in results]
                for k in (*BARS, "surface_pct")]
        lines.append(f"| {label} | " + " | ".join(f"{np.median(v):.3f}" for v in vals) + " |")
    lines.append("| *bars* | " + " | ".join(f"≤ {v}" for v in BARS.values()) + " | |")
    better = [r["capture"] for r in results
              if all(r["rows"]["pba"][k] < r["rows"]["geometric"][k] for k in BARS)]
    lines += ["", f"(c) better than (b) on rotation, centre and focal length: {len(better)} of "
              f"{len(results)} captures" + (f" ({', '.join(better)})" if better else "")]
    for name in ("pba", "pba_pp_free"):
        worse = [r["capture"] for r in results if name in r["rows"]
                 and r["rows"][name]["rotation_deg"] > r["rows"]["geometric"]["rotation_deg"]
                 + WORSE_DEG]
        lines.append(f"{ROWS[name][:3]} rotations worse than (b)'s by more than {WORSE_DEG}°: "
                     f"{len(worse)} of {len(results)} captures"
                     + (f" ({', '.join(worse)})" if worse else ""))
    lines += ["", "Tracking + keyframes + PBA (bar ≤ 90 s):"]
    for r in results:
        w, c = r["tracking_keyframes_pba_s"]
        lines.append(f"- {r['capture']}: {w:.1f} s wall, {c:.1f} s CPU ({r['frames']} frames; "
                     f"keyframes {r['keyframes_s'][0]} s, PBA {r['pba_only_s'][0]} s)")
    return "\n".join(lines) + "\n"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--captures", nargs="+", default=CAPTURES)
    p.add_argument("--out", default="out/bench_poses")
    p.add_argument("--no-ablations", action="store_true",
                   help="only (a)-(c): skip the PBA runs with one ingredient taken away")
    args = p.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    config = PoseConfig()
    results = []
    for capture in map(Path, args.captures):
        if not (capture / "gt" / "render.json").is_file():
            raise SystemExit(f"{capture} is not a finished capture (no gt/render.json)")
        results.append(run_capture(capture, out / "work" / capture.name, config,
                                   not args.no_ablations))
        (out / "results.json").write_text(json.dumps(results, indent=1))
    text = report(results)
    (out / "report.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
