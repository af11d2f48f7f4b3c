"""Mean-template baseline on synthetic subjects, and the renderer's speed.

    python benchmarks/bench_baseline.py [--subjects ict:0 ict:1 james] [--width 1280 --height 720]

Synthesizes one capture per subject (a full ear-to-ear sweep), prints render seconds per
frame, then scores the default template against each subject's ground-truth mesh under the
similarity and metric protocols, as the first row of the paper's Table 1.
"""

from __future__ import annotations

import argparse
import os
import resource
import time
from pathlib import Path

from facecap.synthetic import synthesize
from facecap.synthetic.config import SynthConfig
from facecap_core.baselines import mean_template
from facecap_core.evaluation import paper_table, score_json
from facecap_core.template import Template

PAPER_MEAN_BASEL = "paper, Mean Basel (10 real subjects): accuracy 3.09 / 1.24 / 2.62, completion 3.02 / 1.25 / 2.76 mm"


def landmark_agreement(capture, max_yaw_deg: float = 12.0) -> tuple[float, int]:
    """Median distance (px) between the detector's inner 51 landmarks and the projected ground truth
    on the near-frontal frames, and the number of frames where a face was found."""
    import av
    import numpy as np

    from facecap.synthetic import load_gt_cameras
    from facecap_core.camera import camera_center, project
    from facecap_core.face import detect
    from facecap_core.meshio import load_landmarks

    intr, poses = load_gt_cameras(capture.gt_cameras)
    landmarks = load_landmarks(capture.gt_landmarks)
    errors, found = [], 0
    with av.open(str(capture.video)) as video:
        for frame, pose in zip(video.decode(video=0), poses):
            c = camera_center(pose["R"], pose["t"])
            if abs(np.degrees(np.arctan2(c[0], c[2]))) > max_yaw_deg:
                continue
            det = detect(frame.to_ndarray(format="rgb24"))
            if det is None:
                continue
            found += 1
            uv, _ = project(landmarks, pose["R"], pose["t"], intr)
            errors.append(np.linalg.norm(det.points[17:] - uv[17:], axis=1))
    return (float(np.median(np.concatenate(errors))) if errors else float("nan")), found


def run_baseline(subjects: list[str], out: Path, width: int = 1280, height: int = 720,
                 fps: float = 30.0, seconds: float = 6.0, ict_model: str | None = None,
                 progress: bool = True) -> str:
    """Render the captures, score the mean template; returns the report (Markdown)."""
    template = Template.default()
    rows = {p: [] for p in ("similarity", "metric")}
    lines = []
    for subject in subjects:
        folder = out / subject.replace(":", "_")
        config = SynthConfig(subject=subject, width=width, height=height, fps=fps,
                             duration_s=seconds,
                             ict_model=ict_model or os.environ.get("FACECAP_ICT_MODEL"))
        start = time.perf_counter()
        capture = synthesize(config, folder, progress=progress)
        per_frame = (time.perf_counter() - start) / capture.frames
        scores = mean_template(template, capture.gt_mesh, capture.gt_landmarks,
                               heatmap_dir=folder)
        for p, s in scores.items():
            rows[p].append(score_json(s))
        sim, met = scores["similarity"], scores["metric"]
        lm_px, lm_frames = landmark_agreement(capture)
        lines.append(f"- {subject}: {capture.frames} frames at {width}x{height}, "
                     f"{per_frame:.2f} s/frame; mean template similarity accuracy median "
                     f"{sim.accuracy.median:.2f} mm (scale {sim.scale:.3f}), metric "
                     f"{met.accuracy.median:.2f} mm; dlib vs projected GT landmarks (inner 51, "
                     f"{lm_frames} frontal frames) median {lm_px:.2f} px; heat maps in {folder}")
    table = paper_table([(f"Mean template ({p})", r) for p, r in rows.items()])
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return "\n".join(lines + ["", table, "", PAPER_MEAN_BASEL,
                              f"peak memory {peak_mb:.0f} MB"])


def main() -> Path:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--subjects", nargs="+", default=["ict:0", "ict:1", "james"])
    ap.add_argument("--out", default="out/bench_baseline")
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--height", type=int, default=720)
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--seconds", type=float, default=6.0)
    ap.add_argument("--ict-model")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    report = run_baseline(args.subjects, out, args.width, args.height, args.fps, args.seconds,
                          args.ict_model)
    print(report)
    (out / "report.md").write_text(report + "\n")
    return out / "report.md"


if __name__ == "__main__":
    main()
