"""Camera poses against ground truth, after a similarity alignment of the camera centres."""

from __future__ import annotations

import numpy as np

from facecap_core.camera import Intrinsics, camera_center, rotation_angle_deg
from facecap_core.geometry import umeyama


def pose_errors(R_est, t_est, intr_est: Intrinsics, R_gt, t_gt, intr_gt: Intrinsics) -> dict:
    """Median rotation error (deg), median centre error (% of the mean camera distance to the
    centres' centroid), focal error (%), k1 error — estimated cameras aligned to the GT ones
    by the similarity that best maps their centres."""
    c_est = np.array([camera_center(R, t) for R, t in zip(R_est, t_est)])
    c_gt = np.array([camera_center(R, t) for R, t in zip(R_gt, t_gt)])
    s, A, b = umeyama(c_est, c_gt, with_scale=True)
    aligned = s * c_est @ A.T + b
    # World-to-camera rotations map through the alignment as R_est @ A.T.
    rot = [rotation_angle_deg(Re @ A.T, Rg) for Re, Rg in zip(R_est, R_gt)]
    spread = np.linalg.norm(c_gt - c_gt.mean(0), axis=1).mean()
    centre = np.linalg.norm(aligned - c_gt, axis=1) / spread * 100
    return {
        "images": len(R_est),
        "rotation_deg": float(np.median(rot)),
        "centre_pct": float(np.median(centre)),
        "focal_pct": float(abs(intr_est.fx / intr_gt.fx - 1) * 100),
        "principal_point_px": float(np.hypot(intr_est.cx - intr_gt.cx, intr_est.cy - intr_gt.cy)),
        "k1_error": float(intr_est.k1 - intr_gt.k1),
    }
