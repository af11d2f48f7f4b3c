import numpy as np
import pytest

from facecap_core.camera import Intrinsics, camera_center, rotation_matrix
from facecap_core.config import SynthConfig
from facecap_core.keyframes import select_keyframes
from facecap_core.pose.colmap_sfm import run_sfm
from facecap_core.pose.evaluate import pose_errors
from facecap_core.synthetic import load_gt_cameras, synthesize
from facecap_core.video import read_frames


def test_pose_errors_ignore_a_similarity_of_the_world():
    rng = np.random.default_rng(0)
    R_gt = [rotation_matrix(rng.normal(size=3), rng.uniform(0, 1)) for _ in range(10)]
    t_gt = [rng.normal(size=3) * 100 for _ in range(10)]
    S = rotation_matrix([0.3, 1, 0.2], 0.7)
    s, b = 0.01, np.array([5.0, -2.0, 1.0])
    # World x' = s S x + b: cameras keep x_cam up to the scale of t.
    R_est = [R @ S.T for R in R_gt]
    t_est = [s * tg - Re @ b for Re, tg in zip(R_est, t_gt)]
    intr = Intrinsics(640, 360, 500, 500, 320, 180, 0.01, 0)
    err = pose_errors(R_est, t_est, intr, R_gt, t_gt, intr)
    assert err["rotation_deg"] < 1e-6 and err["centre_pct"] < 1e-6 and err["focal_pct"] == 0


def test_sfm_registers_every_keyframe(tmp_path, ict_model):
    cap = synthesize(SynthConfig(subject="ict:4", ict_model=ict_model, width=640, height=360,
                                 duration_s=3.0, seed=4), tmp_path / "cap", progress=False)
    kf = select_keyframes(cap.video)
    poses = run_sfm(read_frames(cap.video, kf.indices), tmp_path / "sfm", kf.video_size)
    assert poses.frame_indices == kf.indices
    intr_gt, gt = load_gt_cameras(cap.gt_cameras)
    err = pose_errors(poses.R, poses.t, poses.intrinsics, [gt[i]["R"] for i in kf.indices],
                      [gt[i]["t"] for i in kf.indices], intr_gt)
    # A geometric starting point, not the final accuracy (that is PBA's job).
    assert err["rotation_deg"] < 1.0 and err["centre_pct"] < 1.0 and err["focal_pct"] < 3.0
