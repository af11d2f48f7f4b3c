"""Camera poses against ground truth: after a similarity alignment of the camera centres, and
as the surface they would reconstruct."""

from __future__ import annotations

import numpy as np

from facecap_core.camera import Intrinsics, camera_center, project, rotation_angle_deg, undistort
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


def surface_error(R_est, t_est, intr_est: Intrinsics, R_gt, t_gt, intr_gt: Intrinsics,
                  points: np.ndarray, normals: np.ndarray) -> dict:
    """The true surface as the estimated cameras would reconstruct it from perfect matches:
    each of ``points`` (outward ``normals``, the truth's world) seen where the true cameras
    put it (in front, facing, inside the image; at least two views) is triangulated (linear)
    with the estimated cameras; then aligned to the truth by the best similarity. Returns the
    median distance (``surface`` in the truth's units, and as % of the surface's size) and
    the median reprojection error of the triangulated points (``consistency_px``). What depth
    maps see of the cameras: a shift of the principal point and a tilt of every camera that
    reproject alike cost little here and much in :func:`pose_errors`' rotation error."""
    points = np.asarray(points, float)
    n, k = len(points), len(R_est)
    pixels = np.zeros((k, n, 2))
    seen = np.zeros((k, n), bool)
    for v, (Rg, tg) in enumerate(zip(R_gt, t_gt)):
        uv, z = project(points, Rg, tg, intr_gt)
        facing = (normals * (camera_center(Rg, tg) - points)).sum(1) > 0
        seen[v] = ((z > 0) & facing & (uv[:, 0] >= 0) & (uv[:, 0] <= intr_gt.width - 1)
                   & (uv[:, 1] >= 0) & (uv[:, 1] <= intr_gt.height - 1))
        pixels[v] = uv
    keep = seen.sum(0) >= 2
    pixels, seen, points = pixels[:, keep], seen[:, keep], points[keep]
    xy = undistort(np.column_stack([(pixels[..., 0].ravel() - intr_est.cx) / intr_est.fx,
                                    (pixels[..., 1].ravel() - intr_est.cy) / intr_est.fy]),
                   intr_est.k1, intr_est.k2).reshape(k, -1, 2)
    # Linear triangulation: the least eigenvector of sum over the views of a a^T, a the rows
    # x P_3 - P_1 and y P_3 - P_2 of each view that sees the point.
    M = np.zeros((len(points), 4, 4))
    for v, (Re, te) in enumerate(zip(R_est, t_est)):
        P = np.column_stack([Re, te])
        w = seen[v][:, None]
        for row in (xy[v, :, :1] * P[2] - P[0], xy[v, :, 1:] * P[2] - P[1]):
            row = row * w
            M += row[:, :, None] * row[:, None, :]
    X = np.linalg.eigh(M)[1][:, :, 0]
    X = X[:, :3] / X[:, 3:]
    reprojection = []
    for v, (Re, te) in enumerate(zip(R_est, t_est)):
        uv, _ = project(X[seen[v]], Re, te, intr_est)
        reprojection.append(np.linalg.norm(uv - pixels[v, seen[v]], axis=1))
    s, A, b = umeyama(X, points, with_scale=True)
    distance = np.linalg.norm(s * X @ A.T + b - points, axis=1)
    size = np.linalg.norm(points - points.mean(0), axis=1).mean()
    return {"surface": float(np.median(distance)),
            "surface_pct": float(np.median(distance) / size * 100),
            "consistency_px": float(np.median(np.concatenate(reprojection)))}
