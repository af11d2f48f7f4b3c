"""Where photometric bundle adjustment ends worse than its start: captures × SfM seeds ×
threads, PBA's variants side by side.

    python benchmarks/bench_pose_starts.py [--out out/bench_pose_starts] [--seeds 0 1 2]
        [--threads 1 2] [--captures NAME ...] [--variants pba_prior ...] [--rescore]

    # the principal point at 720p, 1080p and 4K (one start each):
    python benchmarks/bench_pose_starts.py --seeds 0 --threads 2 --captures
        ict1_1280x720_off_centre ict2_1920x1080_centred ict1_3840x2160_off_centre

Per capture (rendered once into OUT/captures/, exact cameras in gt/), per start (the SfM
random seed and the thread count of SfM and of the numba kernels): the keyframes, SfM, the
geometric refinement with a fifth of the LK tracks held out, then PBA from it in each of
the ``--variants`` (``VARIANTS``; by default the principal point free, with its prior (the
default setting) and held). With two threads an SfM seed does not fix the start (COLMAP's
threaded matching), so variants are compared within one run. Every solution's cameras are
saved in OUT/work/CAPTURE/SEED-THREADS/; ``--rescore`` computes the truth's errors again
from them.

Two verdicts of the truth on whether PBA ended worse than its start: its rotations (median °,
more than ``WORSE_DEG`` worse, after a similarity alignment of the camera centres) and the
surface (``facecap_core.pose.evaluate.surface_error``: the true head triangulated from
perfect matches with the solution's cameras, aligned by a similarity; more than
``WORSE_SURFACE`` worse). The second is what a reconstruction from perfect matches sees: a
principal point shifted against a turn of every camera in its own frame costs rotation
error and hardly any surface. Beside them an
internal criterion that needs no truth: the held-out tracks' median reprojection error after
triangulating them with each solution's cameras (smaller: the cameras agree better with
tracks that neither solve saw); the table says how often its verdict matches the surface's.

The default captures are evaluation identities and render settings (ICT identities 1, 2 and
11); the ``cal_`` ones are identities 4, 5 and 6, on which PBA's settings are chosen
(docs/poses.md). The prior's width
is not fitted to them: it is the spread of the principal point of facecap's sensor model
(1 % of the image size, SynthConfig.principal_point_jitter) and of the one real phone
calibration at hand (a 240×320 sweep: 0.4 % from the centre).
Writes OUT/report.md and OUT/results.json.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from facecap.synthetic import load_gt_cameras, synthesize
from facecap.synthetic.config import SynthConfig
from facecap_core.assets import default_ict_model
from facecap_core.camera import Intrinsics
from facecap_core.keyframes import KeyframeConfig, select_keyframes
from facecap_core.pose.colmap_sfm import run_sfm
from facecap_core.pose.evaluate import head_surface, pose_errors, surface_error
from facecap_core.pose.geometric import refine_with_tracks, triangulate
from facecap_core.pose.stage import PoseConfig, photometric_refinement
from facecap_core.video import read_frames

CAPTURES = {
    # name: render settings (an 8 s 720p sweep is bench_poses.py's; these are short)
    "ict1_640x360_centred": dict(subject="ict:1", width=640, height=360, duration_s=3.0,
                                 principal_point_jitter=0.0, seed=11),
    "ict2_640x360": dict(subject="ict:2", width=640, height=360, duration_s=3.0, seed=12),
    "ict1_640x360_off_centre": dict(subject="ict:1", width=640, height=360, duration_s=3.0,
                                    principal_point_jitter=0.03, seed=13),
    "ict11_240x320_15fps": dict(subject="ict:11", width=240, height=320, fps=15.0,
                                duration_s=6.0, seed=14),
    # Larger sensors (not in the default list: a 4K frame renders in ~20-40 s on 2 cores).
    "ict1_1280x720_off_centre": dict(subject="ict:1", width=1280, height=720, duration_s=3.0,
                                     principal_point_jitter=0.03, seed=15),
    "ict2_1920x1080_centred": dict(subject="ict:2", width=1920, height=1080, duration_s=3.0,
                                   principal_point_jitter=0.0, seed=16),
    "ict1_3840x2160_off_centre": dict(subject="ict:1", width=3840, height=2160, fps=10.0,
                                      duration_s=3.0, principal_point_jitter=0.03, seed=17),
    # bench_poses.py's capture where PBA ends worse than its start (an 8 s 720p sweep).
    "ict2_1280x720_8s": dict(subject="ict:2", width=1280, height=720, duration_s=8.0, seed=2),
    # Calibration captures (identities 4-6, PBA's calibration set, docs/poses.md): a setting
    # is chosen on these and then evaluated on the ones above.
    "cal_ict4_640x360": dict(subject="ict:4", width=640, height=360, duration_s=3.0, seed=4),
    "cal_ict5_1280x720_8s": dict(subject="ict:5", width=1280, height=720, duration_s=8.0,
                                 seed=5),
    "cal_ict6_640x360": dict(subject="ict:6", width=640, height=360, duration_s=3.0, seed=6),
}
DEFAULT_CAPTURES = list(CAPTURES)[:4]
VARIANTS = {"pba_free": {"principal_point_prior_pct": 0.0},
            "pba_prior": {},
            "pba_prior_1pct": {"principal_point_prior_pct": 1.0},
            "pba_held": {"hold_principal_point": True},
            "pba_photometric": {"track_weight": 0.0},
            "pba_photometric_centres": {"track_weight": 0.0, "centre_prior_pct": 0.05},
            "pba_weak_tracks": {"track_weight": 3.0},
            "pba_photometric_anchored": {"track_weight": 3.0, "refine_intrinsics": False}}
"""PBA's settings compared from each start: the principal point free, with its prior
around the image centre (the default, 0.3 %; and 1 %, the default the docs' figures of
2026-11-27 were measured with), held where the geometric refinement put it; the
photometric residuals alone (no tracks, so the intrinsics stay the geometric step's), the
same with the camera centres held near the start's; the tracks weighed 3 instead of 30,
with the intrinsics free or held."""
DEFAULT_VARIANTS = ["pba_free", "pba_prior", "pba_held"]
"""Run unless ``--variants`` says otherwise (each variant is one more PBA per start)."""
WORSE_DEG = 0.01
"""PBA's rotations count as worse than its start beyond this (the figures' rounding)."""
WORSE_SURFACE = 0.02
"""PBA's surface error counts as worse than its start's beyond this fraction of it."""
LABELS = {"pba_free": "PBA, pp free", "pba_prior": "PBA, pp prior (default)",
          "pba_held": "PBA, pp held", "pba_photometric": "PBA, photometric only",
          "pba_photometric_centres": "PBA, photometric, centres held 0.05 %",
          "pba_weak_tracks": "PBA, tracks weighed 3",
          "pba_photometric_anchored": "PBA, tracks weighed 3, intrinsics held"}
HELD_OUT = 5
"""One track in this many is held out of both solves (by its id)."""


def capture_folder(out: Path, name: str) -> Path:
    folder = out / "captures" / name
    if not (folder / "gt" / "render.json").is_file():
        config = SynthConfig(ict_model=default_ict_model(), **CAPTURES[name])
        synthesize(config, folder, progress=False)
    return folder


def held_out_error(observations: np.ndarray, poses) -> float:
    """Median reprojection error (px) of the held-out tracks triangulated with ``poses``'
    cameras (each track seen by 3 views or more; none dropped for its error)."""
    view_of = {int(i): v for v, i in enumerate(poses.frame_indices)}
    rows = [(o[1], view_of[int(o[0])], o[2], o[3]) for o in observations
            if int(o[0]) in view_of]
    points, kept = triangulate(np.array(rows), poses.R, poses.t, poses.intrinsics,
                               min_views=3, max_error_px=1e9, min_angle_deg=0.5)
    from facecap_core.camera import project

    errors = [np.linalg.norm(project(points[int(p)][None], poses.R[int(v)], poses.t[int(v)],
                                     poses.intrinsics)[0][0] - (x, y))
              for p, v, x, y in kept]
    return float(np.median(errors)) if errors else float("nan")


def run_start(folder: Path, keyframes, seed: int, threads: int, work: Path,
              variants: list[str]) -> dict:
    import numba

    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    video = folder / "video.mp4"
    config = PoseConfig()
    images = read_frames(video, keyframes.indices, width=config.sfm_width)
    # The pose stage's own steps, not estimate_poses: the SfM seed is varied on purpose and
    # is no setting of the stage, and the variants must share one start (with two threads a
    # second SfM run is another start).
    sfm = run_sfm(images, work / "sfm", keyframes.video_size, overlap=config.match_overlap,
                  threads=threads, seed=seed, ordered=keyframes.ordered,
                  focal_px=keyframes.focal_px, extraction_threads=config.extraction_threads)
    # keyframes.observations rows: keyframe number, track id, x, y.
    obs = np.asarray(keyframes.observations, float)
    held = obs[:, 1].astype(np.int64) % HELD_OUT == 0
    geo = refine_with_tracks(sfm, obs[~held], keyframes.indices, work / "geometric")
    held_rows = np.column_stack([np.asarray(keyframes.indices)[obs[held, 0].astype(int)],
                                 obs[held, 1:]])
    greys = read_frames(video, geo.frame_indices, width=config.pba.max_width, grey=True)
    grey_list = [greys[i] for i in geo.frame_indices]
    solutions = {"sfm": sfm, "geometric": geo}
    for name in variants:
        update = VARIANTS[name]
        variant = config.model_copy(update={"pba": config.pba.model_copy(update=update)})
        solutions[name] = photometric_refinement(geo, grey_list, variant, keyframes=keyframes)
    row = {"seed": seed, "threads": threads}
    for name, poses in solutions.items():
        np.savez(work / f"{name}.npz", R=np.asarray(poses.R), t=np.asarray(poses.t),
                 frame_indices=np.asarray(poses.frame_indices), **poses.intrinsics.to_dict())
        row[name] = {"held_out_px": held_out_error(held_rows, poses)}
    return score(folder, work, row)


def score(folder: Path, work: Path, row: dict) -> dict:
    """``row`` with the truth's errors of each solution saved in ``work`` (its held-out
    error kept)."""
    intr_gt, gt = load_gt_cameras(folder / "gt" / "cameras.json")
    surface = head_surface(folder / "gt" / "mesh.ply")
    for name in [k for k in row if isinstance(row[k], dict)]:
        if not (work / f"{name}.npz").is_file():
            continue  # a row from before the cameras were saved: its figures stay
        saved = np.load(work / f"{name}.npz")
        intr = Intrinsics.from_dict({k: saved[k].item() for k in saved.files
                                     if k not in ("R", "t", "frame_indices")})
        idx = saved["frame_indices"]
        truth = [gt[i]["R"] for i in idx], [gt[i]["t"] for i in idx], intr_gt
        err = pose_errors(saved["R"], saved["t"], intr, *truth)
        err.update(surface_error(saved["R"], saved["t"], intr, *truth, *surface))
        err["held_out_px"] = row[name]["held_out_px"]
        row[name] = {k: (round(v, 4) if isinstance(v, float) else v) for k, v in err.items()}
    return row


def verdicts(row: dict, pba: str) -> dict[str, bool]:
    """Whether PBA ended worse than its start: by the truth's rotations, by the truth's
    surface (as the cameras would reconstruct it from perfect matches) and by the held-out
    tracks (the internal criterion)."""
    pba_, geo = row[pba], row["geometric"]
    return {"rotation": pba_["rotation_deg"] > geo["rotation_deg"] + WORSE_DEG,
            "surface": ("surface" in pba_
                        and pba_["surface"] > geo["surface"] * (1 + WORSE_SURFACE)),
            "held_out": pba_["held_out_px"] > geo["held_out_px"]}


def report(results: dict[str, list[dict]]) -> str:
    every = [r for rows in results.values() for r in rows]
    shown = [s for s in VARIANTS if any(s in r for r in every)]
    lines = ["# Where PBA ends worse than its start (`benchmarks/bench_pose_starts.py`)", "",
             "Per step: rotation error (median °) / principal point error (px) / the surface "
             "error (median, % of the head's size: the true surface triangulated from perfect "
             "matches with the step's cameras, aligned by a similarity) / held-out tracks' "
             "median reprojection error (px). *worse*: by the rotations (more than "
             f"{WORSE_DEG}°), *worse surface*: by the surface (more than "
             f"{WORSE_SURFACE:.0%}), both against the geometric start.", "",
             "| capture | seed | threads | geometric | " + " | ".join(
                 LABELS[s] for s in shown) + " |", "|---|---:|---:|---|" + "---|" * len(shown)]

    def cell(r, s):
        if s not in r:
            return "–"  # a row from before the variant was measured
        e = r[s]
        text = (f"{e['rotation_deg']:.3f} / {e['principal_point_px']:.1f} / "
                + (f"{e['surface_pct']:.3f} / " if "surface_pct" in e else "– / ")
                + f"{e['held_out_px']:.3f}")
        if s != "geometric":
            v = verdicts(r, s)
            text += " **worse**" * v["rotation"] + " **worse surface**" * v["surface"]
        return text

    for name, rows in results.items():
        for r in rows:
            lines.append(f"| {name} | {r['seed']} | {r['threads']} | "
                         + " | ".join(cell(r, s) for s in ("geometric", *shown)) + " |")
    lines += ["", "| PBA | ended worse (rotations) | ended worse (surface) | held-out agrees "
              "with the surface | median rotation ° | median pp px | median focal % | median "
              "surface % |", "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for s in ("geometric", *shown):
        rows = [r for r in every if s in r]
        med = [np.median([r[s][k] for r in rows if k in r[s]] or [np.nan])
               for k in ("rotation_deg", "principal_point_px", "focal_pct", "surface_pct")]
        if s == "geometric":
            lines.append("| (start: geometric) | – | – | – | "
                         + " | ".join(f"{m:.3f}" for m in med) + " |")
            continue
        v = [verdicts(r, s) for r in rows]
        judged = [x for x, r in zip(v, rows) if "surface" in r[s]]
        lines.append(f"| {LABELS[s]} | {sum(x['rotation'] for x in v)} of {len(v)} | "
                     f"{sum(x['surface'] for x in judged)} of {len(judged)} | "
                     f"{sum(x['surface'] == x['held_out'] for x in judged)} of {len(judged)} | "
                     + " | ".join(f"{m:.3f}" for m in med) + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default="out/bench_pose_starts")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    p.add_argument("--captures", nargs="+", default=DEFAULT_CAPTURES, choices=list(CAPTURES))
    p.add_argument("--variants", nargs="+", default=DEFAULT_VARIANTS, choices=list(VARIANTS))
    p.add_argument("--rescore", action="store_true",
                   help="recompute the truth's errors of the saved solutions (no solve)")
    args = p.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results_path = out / "results.json"
    results = json.loads(results_path.read_text()) if results_path.is_file() else {}
    for name in args.captures:
        if args.rescore:
            if results.get(name):
                folder = capture_folder(out, name)
                results[name] = [score(folder, out / "work" / name /
                                       f"{r['seed']}-{r['threads']}", r) for r in results[name]]
                results_path.write_text(json.dumps(results, indent=1))
            continue
        folder = capture_folder(out, name)
        keyframes = select_keyframes(folder / "video.mp4", KeyframeConfig())
        done = {(r["seed"], r["threads"]) for r in results.get(name, [])}
        for seed in args.seeds:
            for threads in args.threads:
                if (seed, threads) in done:
                    # Variants are not added to a measured row: with two threads a seed
                    # does not fix the start, so they would meet another start than its.
                    missing = [v for v in args.variants if not any(
                        v in r for r in results[name]
                        if (r["seed"], r["threads"]) == (seed, threads))]
                    if missing:
                        print(f"{name} seed {seed}, {threads} threads: measured before "
                              f"without {', '.join(missing)}, which are not added to it; "
                              "use another --out", flush=True)
                    continue
                row = run_start(folder, keyframes, seed, threads,
                                out / "work" / name / f"{seed}-{threads}", args.variants)
                results.setdefault(name, []).append(row)
                print(name, json.dumps(row), flush=True)
                results_path.write_text(json.dumps(results, indent=1))
    text = report({name: results[name] for name in args.captures if name in results})
    (out / "report.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
