"""A sweep's frames as a photo folder against its video: the two camera solves side by side.

    python benchmarks/bench_folder_video.py CAPTURE FOLDER [--out OUT]

CAPTURE is a ``facecap synth`` folder (``video.mp4`` and ``gt/cameras.json``); FOLDER holds
the same video's frames as photos (``frame_00000.jpg`` …, one per video frame, numbered as
the frames). Each goes through the keyframes and the pose stage with the defaults
(``keyframes.main``, ``estimate_poses``); printed: each solve's final cameras against the
truth (:func:`facecap_core.pose.evaluate.pose_errors`: median rotation °, principal point
px, focal %) and the folder's cameras against the video's on the video's keyframes (after a
similarity alignment of the centres). The bar of issue 48: the folder within 0.5° of the
video.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from facecap.synthetic import load_gt_cameras  # noqa: E402
from facecap_core import keyframes as keyframes_stage  # noqa: E402
from facecap_core.keyframes import load_keyframes  # noqa: E402
from facecap_core.pose.evaluate import pose_errors  # noqa: E402
from facecap_core.pose.stage import PoseConfig, estimate_poses  # noqa: E402


def final_cameras(source: Path, work: Path):
    """The pose stage's last cameras of ``source`` (a video or a photo folder)."""
    keyframes_stage.main(source, work / "keyframes")
    keyframes = load_keyframes(work / "keyframes" / "keyframes.json")
    steps, _ = estimate_poses(source, keyframes, work / "poses", PoseConfig())
    return steps.get("pba") or steps.get("geometric") or steps["sfm"]


def figures(R, t, intr, R_ref, t_ref, intr_ref) -> str:
    """Cameras (R, t, intr) against reference ones, in words."""
    e = pose_errors(R, t, intr, R_ref, t_ref, intr_ref)
    return (f"rotation {e['rotation_deg']:.3f}°, principal point "
            f"{e['principal_point_px']:.2f} px, focal {e['focal_pct']:.2f} %")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("capture", type=Path)
    ap.add_argument("folder", type=Path)
    ap.add_argument("--out", type=Path, help="keep the keyframes and solves here")
    args = ap.parse_args(argv)

    intr_gt, gt = load_gt_cameras(args.capture / "gt" / "cameras.json")
    with tempfile.TemporaryDirectory() as scratch:
        work = args.out or Path(scratch)
        solves = {name: final_cameras(source, work / name) for name, source in
                  (("folder", args.folder), ("video", args.capture / "video.mp4"))}
    for name, poses in solves.items():
        idx = poses.frame_indices
        print(f"{name}: {len(idx)} views; against the truth: "
              + figures(poses.R, poses.t, poses.intrinsics, [gt[i]["R"] for i in idx],
                        [gt[i]["t"] for i in idx], intr_gt))
    folder, video = solves["folder"], solves["video"]
    at = {i: k for k, i in enumerate(folder.frame_indices)}
    common = [(at[i], k) for k, i in enumerate(video.frame_indices) if i in at]
    f, v = [c[0] for c in common], [c[1] for c in common]
    print(f"folder against video on {len(common)} views: "
          + figures([folder.R[k] for k in f], [folder.t[k] for k in f], folder.intrinsics,
                    [video.R[k] for k in v], [video.t[k] for k in v], video.intrinsics))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
