"""Camera poses against ground truth: after a similarity alignment of the camera centres, and
as the surface they would reconstruct."""

from __future__ import annotations

import numpy as np

from facecap_core.camera import Intrinsics, camera_center, project, rotation_angle_deg, undistort
from facecap_core.geometry import umeyama
from facecap_core.lazy import LazyModule

trimesh = LazyModule("trimesh")


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


def head_surface(mesh_path, most: int = 5000) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and vertex normals of a ground-truth head mesh, at most ``most`` of them
    picked evenly through its vertex list: the points :func:`surface_error` rebuilds."""
    mesh = trimesh.load(mesh_path, process=False)
    pick = np.linspace(0, len(mesh.vertices) - 1, min(most, len(mesh.vertices))).astype(int)
    return np.asarray(mesh.vertices)[pick], np.asarray(mesh.vertex_normals)[pick]


def surface_error(R_est, t_est, intr_est: Intrinsics, R_gt, t_gt, intr_gt: Intrinsics,
                  points: np.ndarray, normals: np.ndarray, min_angle_deg: float = 2.0) -> dict:
    """The true surface as the estimated cameras would rebuild it from perfect matches.

    Each of ``points`` (outward ``normals``, in the truth's world) is taken where the true
    cameras put it, in every view it lies in front of, faces (a back-face test: no
    occlusion test) and falls inside; seen by two views or more whose rays span
    ``min_angle_deg``, it is triangulated (linear) with the estimated cameras, and the
    triangulated points are aligned to the truth by the best similarity. Returns the median
    distance (``surface``, the truth's units; ``surface_pct``, % of the rebuilt points' mean
    distance from their centroid), the median reprojection error of the triangulated points
    (``consistency_px``) and how many points were rebuilt (``points``). A shift of the
    principal point and a turn of every camera in its own frame that reproject alike cost
    little here and much in :func:`pose_errors`' rotation error."""
    if len(R_est) != len(R_gt):
        raise ValueError(f"{len(R_est)} estimated cameras against {len(R_gt)} true ones")
    if (intr_est.width, intr_est.height) != (intr_gt.width, intr_gt.height):
        raise ValueError(f"the estimated cameras are {intr_est.width}x{intr_est.height}, the "
                         f"true {intr_gt.width}x{intr_gt.height}: scale them to one size")
    points, normals = np.asarray(points, float), np.asarray(normals, float)
    n, k = len(points), len(R_est)
    pixels = np.zeros((k, n, 2))
    seen = np.zeros((k, n), bool)
    rays = np.zeros((k, n, 3))
    for v, (Rg, tg) in enumerate(zip(R_gt, t_gt)):
        uv, z = project(points, Rg, tg, intr_gt)
        to_camera = camera_center(Rg, tg) - points
        seen[v] = (((normals * to_camera).sum(1) > 0) & (z > 0)
                   & (uv[:, 0] >= 0) & (uv[:, 0] <= intr_gt.width - 1)
                   & (uv[:, 1] >= 0) & (uv[:, 1] <= intr_gt.height - 1))
        pixels[v] = np.where(seen[v][:, None], uv, 0.0)
        rays[v] = to_camera / np.linalg.norm(to_camera, axis=1, keepdims=True)
    # The rays' spread, from below: the largest angle to the ray farthest from their mean.
    mean = (rays * seen[..., None]).sum(0)
    mean /= np.maximum(np.linalg.norm(mean, axis=1, keepdims=True), 1e-12)
    far = np.argmin(np.where(seen, np.einsum("knc,nc->kn", rays, mean), 2.0), axis=0)
    to_far = np.einsum("knc,nc->kn", rays, rays[far, np.arange(n)])
    spread = np.degrees(np.arccos(np.clip(np.where(seen, to_far, 1.0).min(0), -1, 1)))
    keep = (seen.sum(0) >= 2) & (spread >= min_angle_deg)
    pixels, seen, points = pixels[:, keep], seen[:, keep], points[keep]
    xy = undistort(np.column_stack([(pixels[..., 0].ravel() - intr_est.cx) / intr_est.fx,
                                    (pixels[..., 1].ravel() - intr_est.cy) / intr_est.fy]),
                   intr_est.k1, intr_est.k2).reshape(k, -1, 2)
    # Linear triangulation: the least eigenvector of the sum over the views that see a point
    # of a a^T, a the rows x P_3 - P_1 and y P_3 - P_2.
    M = np.zeros((len(points), 4, 4))
    for v, (Re, te) in enumerate(zip(R_est, t_est)):
        P = np.column_stack([Re, te])
        for row in (xy[v, :, :1] * P[2] - P[0], xy[v, :, 1:] * P[2] - P[1]):
            row = np.where(seen[v][:, None], row, 0.0)
            M += row[:, :, None] * row[:, None, :]
    X = np.linalg.eigh(M)[1][:, :, 0]
    X = X[:, :3] / X[:, 3:]
    if len(X) < 3 or not np.all(np.isfinite(X)):
        raise ValueError(f"{len(X)} surface points could be rebuilt with the estimated "
                         "cameras (need 3, all finite)")
    reprojection = []
    for v, (Re, te) in enumerate(zip(R_est, t_est)):
        uv, _ = project(X[seen[v]], Re, te, intr_est)
        reprojection.append(np.linalg.norm(uv - pixels[v, seen[v]], axis=1))
    s, A, b = umeyama(X, points, with_scale=True)
    distance = np.linalg.norm(s * X @ A.T + b - points, axis=1)
    size = np.linalg.norm(points - points.mean(0), axis=1).mean()
    return {"surface": float(np.median(distance)),
            "surface_pct": float(np.median(distance) / size * 100),
            "consistency_px": float(np.median(np.concatenate(reprojection))),
            "points": int(len(X))}
