"""The normal equations of PBA and their steps.

The photometric kernel summed over runs of points on threads, the tracked points' own
kernel, the Schur complement's back-substitution, the scale gauge, the pose increments, the
camera velocities (motion blur, rolling shutter) and the adjustment to the tracks alone
(the rolling shutter's readout from the tracks).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import cv2
import numba as nb
import numpy as np

from facecap_core.camera import Intrinsics, project, rotation_matrix
from facecap_core.pose.pba.kernels import (
    N_FRAME,
    N_INTR,
    accumulate,
    distortion_terms,
    moved,
    point_gradient,
)

ACCUMULATE_CHUNKS = 2
"""The photometric normal equations are summed over this many fixed runs of points, each
on its own thread (the kernel releases the GIL), and added in this order: the same sums,
so the same cameras, on one core or many; two use both cores of the machine the pipeline
is sized for (PBA runs alone in the pipeline)."""


def accumulate_in_chunks(host, uv, rho, target_start, targets, images, grad_x, grad_y,
                          host_weights, motion, max_samples, velocity, readout, rows, R_rel,
                          t_rel, affine, intr, huber, max_residual, with_cameras, H, b, Hpp,
                          bpp, Hcp_store, idx_store, stats, res_out,
                          chunks: int = ACCUMULATE_CHUNKS, jacobians: bool = True):
    """:func:`accumulate` over ``chunks`` runs of points at once: per-point outputs are
    written in place (the runs are disjoint), the camera system and the cost summed in
    order, the residual magnitudes gathered at the front of ``res_out`` (stats[2] of them)."""
    cuts = np.linspace(0, len(host), chunks + 1).astype(np.int64)
    runs = []
    for a, z in zip(cuts[:-1], cuts[1:]):
        out = res_out[8 * target_start[a]:8 * target_start[z]] if len(res_out) else res_out
        runs.append((a, z, np.zeros_like(H), np.zeros_like(b), np.zeros(3), out))

    def run(part):
        a, z, H_, b_, stats_, out = part
        accumulate(host[a:z], uv[a:z], rho[a:z], target_start[a:z + 1], targets, images,
                    grad_x, grad_y, host_weights[a:z], motion, max_samples, velocity, readout,
                    rows, R_rel, t_rel, affine, intr, huber, max_residual, with_cameras,
                    jacobians, H_,
                    b_, Hpp[a:z], bpp[a:z], Hcp_store[a:z], idx_store[a:z], stats_, out)

    if chunks == 1:
        run(runs[0])
    else:
        with ThreadPoolExecutor(chunks) as pool:
            list(pool.map(run, runs))
    stats[0] = stats[1] = 0.0
    written = int(stats[2])
    for _, _, H_, b_, stats_, out in runs:
        H += H_
        b += b_
        stats[0] += stats_[0]
        stats[1] += stats_[1]
        n = int(stats_[2])
        if n:  # each run's magnitudes start its own slice, at or after the gathered ones
            res_out[written:written + n] = out[:n].copy()
            written += n
    stats[2] = written


@nb.njit(cache=True)
def accumulate_tracks(X, obs_start, obs_frame, obs_xy, R, t, intr, weight, huber_px,
                       velocity, readout, rows, with_cameras, H, b, Hpp, bpp, Hpc, stats):
    """Reprojection residuals of the tracked points (world points X, 3 unknowns each, their
    observations in CSR order) added to the same normal equations as the photometric ones,
    the points eliminated by their own 3x3 Schur blocks. ``weight`` is the cost of one pixel
    in squared grey levels; Huber beyond ``huber_px``. Keyframe 0 is fixed (the gauge).
    ``Hpc`` keeps each observation's 3x6 pose block and each point's 3x5 intrinsics block
    (stored after the observations) for the back-substitution. With a rolling shutter
    (``readout`` > 0) each observation is of the camera moved for its row's time offset.
    """
    # Long on purpose: a numba kernel, one pass over the observations as in accumulate.
    f, cx, cy, k1, k2 = intr[0], intr[1], intr[2], intr[3], intr[4]
    n_obs_total = obs_frame.shape[0]
    cost = 0.0
    e = np.empty(2)
    J = np.empty(N_INTR + 6)  # one residual's columns: intrinsics, then its keyframe's pose
    jp = np.empty(3)
    cols = np.empty(N_INTR + 6, np.int64)
    for c in range(N_INTR):
        cols[c] = c
    for p in range(X.shape[0]):
        o0 = obs_start[p]
        o1 = obs_start[p + 1]
        n = o1 - o0
        # local unknowns: intrinsics (5), then 6 pose unknowns per observation
        n_loc = N_INTR + 6 * n
        m = n_loc if with_cameras else 0  # a long track's camera block is large: only if used
        Hcc = np.zeros((m, m))
        Wc = np.zeros((3, m))
        bc = np.zeros(m)
        Hp = np.zeros((3, 3))
        bp = np.zeros(3)
        for o in range(o0, o1):
            k = obs_frame[o]
            Rk = R[k]
            Xc0 = Rk[0, 0] * X[p, 0] + Rk[0, 1] * X[p, 1] + Rk[0, 2] * X[p, 2] + t[k, 0]
            Xc1 = Rk[1, 0] * X[p, 0] + Rk[1, 1] * X[p, 1] + Rk[1, 2] * X[p, 2] + t[k, 1]
            Xc2 = Rk[2, 0] * X[p, 0] + Rk[2, 1] * X[p, 1] + Rk[2, 2] * X[p, 2] + t[k, 2]
            if readout != 0.0:
                Xc0, Xc1, Xc2 = moved(Xc0, Xc1, Xc2, velocity[k],
                                       readout * (obs_xy[o, 1] / rows - 0.5))
            if Xc2 <= 1e-9:
                continue
            yx, yy, s2, fac, dfac = distortion_terms(Xc0, Xc1, Xc2, k1, k2)
            e[0] = f * yx * fac + cx - obs_xy[o, 0]
            e[1] = f * yy * fac + cy - obs_xy[o, 1]
            norm = np.sqrt(e[0] * e[0] + e[1] * e[1])
            w = weight if norm <= huber_px else weight * huber_px / norm
            cost += (weight * norm * norm if norm <= huber_px
                     else weight * (2 * huber_px * norm - huber_px * huber_px))
            stats[1] += 1
            slot = N_INTR + 6 * (o - o0)
            for c in range(6):
                cols[N_INTR + c] = slot + c
            for row in range(2):
                gx = 1.0 if row == 0 else 0.0
                gy = 1.0 - gx
                dX0, dX1, dX2 = point_gradient(gx, gy, Xc0, Xc1, Xc2, f, yx, yy, fac, dfac)
                y = yx if row == 0 else yy
                J[0] = y * fac
                J[1] = gx
                J[2] = gy
                J[3] = f * y * s2
                J[4] = f * y * s2 * s2
                J[5] = dX0
                J[6] = dX1
                J[7] = dX2
                J[8] = Xc1 * dX2 - Xc2 * dX1
                J[9] = Xc2 * dX0 - Xc0 * dX2
                J[10] = Xc0 * dX1 - Xc1 * dX0
                for c in range(3):
                    jp[c] = dX0 * Rk[0, c] + dX1 * Rk[1, c] + dX2 * Rk[2, c]
                r = e[row]
                for c1 in range(3):
                    bp[c1] += w * jp[c1] * r
                    for c2 in range(3):
                        Hp[c1, c2] += w * jp[c1] * jp[c2]
                if not with_cameras:
                    continue
                for i1 in range(N_INTR + 6):
                    c1 = cols[i1]
                    bc[c1] += w * J[i1] * r
                    for c in range(3):
                        Wc[c, c1] += w * J[i1] * jp[c]
                    for i2 in range(N_INTR + 6):
                        Hcc[c1, cols[i2]] += w * J[i1] * J[i2]
        Hpp[p] = Hp
        bpp[p] = bp
        if not with_cameras:
            continue
        det = np.linalg.det(Hp)
        if abs(det) < 1e-18:
            continue
        inv = np.linalg.inv(Hp)
        # global columns of the local unknowns (-1: keyframe 0, fixed)
        glob = np.empty(n_loc, np.int64)
        for c in range(N_INTR):
            glob[c] = c
        for o in range(o0, o1):
            k = obs_frame[o]
            for c in range(6):
                glob[N_INTR + 6 * (o - o0) + c] = -1 if k == 0 else N_INTR + N_FRAME * (k - 1) + c
            for c in range(3):
                for c2 in range(6):
                    Hpc[o, c, c2] = Wc[c, N_INTR + 6 * (o - o0) + c2]
        for c in range(3):
            for c2 in range(N_INTR):
                Hpc[n_obs_total + p, c, c2] = Wc[c, c2]
        IW = inv @ Wc
        for c1 in range(n_loc):
            g1 = glob[c1]
            if g1 < 0:
                continue
            b[g1] += bc[c1] - (Wc[0, c1] * (inv[0, 0] * bp[0] + inv[0, 1] * bp[1] + inv[0, 2] * bp[2])
                               + Wc[1, c1] * (inv[1, 0] * bp[0] + inv[1, 1] * bp[1] + inv[1, 2] * bp[2])
                               + Wc[2, c1] * (inv[2, 0] * bp[0] + inv[2, 1] * bp[1] + inv[2, 2] * bp[2]))
            for c2 in range(n_loc):
                g2 = glob[c2]
                if g2 < 0:
                    continue
                H[g1, g2] += Hcc[c1, c2] - (Wc[0, c1] * IW[0, c2] + Wc[1, c1] * IW[1, c2]
                                            + Wc[2, c1] * IW[2, c2])
    stats[0] += cost


class Normal:
    """The normal equations of one evaluation: the Schur-reduced camera system, and what
    the back-substitution of the photometric inverse depths and the tracked points needs."""

    def __init__(self, n_cam: int, n_points: int, max_local: int, n_tracks: int,
                 n_obs: int):
        self.H = np.zeros((n_cam, n_cam))
        self.b = np.zeros(n_cam)
        self.Hpp, self.bpp = np.zeros(n_points), np.zeros(n_points)
        self.Hcp = np.zeros((n_points, max_local))
        self.idx = np.full((n_points, max_local), -1, np.int64)
        self.Hpp3, self.bpp3 = np.zeros((n_tracks, 3, 3)), np.zeros((n_tracks, 3))
        self.Hpc = np.zeros((n_obs + n_tracks, 3, 6))
        self.stats = np.zeros(3)


def track_steps(e: Normal, dc: np.ndarray, obs_start, obs_frame, lam: float) -> np.ndarray:
    """The tracked points' steps for the camera step ``dc`` (back-substitution)."""
    n = len(e.bpp3)
    if n == 0:
        return np.zeros((0, 3))
    n_obs = len(obs_frame)
    pose = np.zeros((n_obs, 6))
    moving = obs_frame > 0
    cols = N_INTR + N_FRAME * (obs_frame[moving] - 1)
    pose[moving] = dc[cols[:, None] + np.arange(6)]
    rhs = e.bpp3 + np.einsum("ncj,j->nc", e.Hpc[n_obs:, :, :N_INTR], dc[:N_INTR])
    per_obs = np.einsum("ocj,oj->oc", e.Hpc[:n_obs], pose)
    point = np.repeat(np.arange(n), np.diff(obs_start))
    np.add.at(rhs, point, per_obs)
    Hd = e.Hpp3 + lam * np.einsum("nii->ni", e.Hpp3)[:, :, None] * np.eye(3)[None]
    ok = np.abs(np.linalg.det(Hd)) > 1e-18
    step = np.zeros((n, 3))
    step[ok] = -np.linalg.solve(Hd[ok], rhs[ok][:, :, None])[:, :, 0]
    return step


def hold_baseline(H, b, R, t, length, weight):
    """Add the scale gauge to the camera system: a prior holding the first baseline at
    ``length`` (keyframe 1's centre moves by -R_1^T v_1 under its increment)."""
    c0, c1 = -R[0].T @ t[0], -R[1].T @ t[1]
    n = (c1 - c0) / np.linalg.norm(c1 - c0)
    a = -R[1] @ n
    sl = slice(N_INTR, N_INTR + 3)
    H[sl, sl] += weight * np.outer(a, a)
    b[sl] += weight * a * (np.linalg.norm(c1 - c0) - length)


def update_frames(R, t, affine, delta):
    """Left-multiplied pose increments (v, w) and brightness increments for keyframes 1..K-1."""
    R, t, affine = [r.copy() for r in R], [x.copy() for x in t], affine.copy()
    for k in range(1, len(R)):
        d = delta[N_FRAME * (k - 1): N_FRAME * k]
        angle = np.linalg.norm(d[3:6])
        dR = np.eye(3) if angle < 1e-15 else rotation_matrix(d[3:6] / angle, angle)
        R[k] = dR @ R[k]
        t[k] = dR @ t[k] + d[:3]
        affine[k] += d[6:8]
    return R, t, affine


def relative_poses(R, t):
    """Every pair's relative pose: R_rel[h, k] = R_k R_hᵀ, t_rel[h, k] = t_k - R_rel[h, k] t_h."""
    R, t = np.asarray(R, float), np.asarray(t, float)
    R_rel = np.matmul(R[None], np.swapaxes(R, 1, 2)[:, None])
    t_rel = t[None] - np.matmul(R_rel, t[:, None, :, None])[..., 0]
    return R_rel, t_rel


def camera_motion(R: list[np.ndarray], t: list[np.ndarray], times: np.ndarray,
                  seconds: float) -> np.ndarray:
    """Per keyframe, the camera's displacement over ``seconds`` centred on its time, as
    (w, v) in its own frame (a point X of the camera frame moves by w x X + v), from the
    velocity of a constant-velocity model through its neighbouring keyframes (K, 6)."""
    K = len(R)
    out = np.zeros((K, 6))
    if K < 2 or seconds <= 0:
        return out
    for k in range(K):
        rates = []
        for j in (k - 1, k + 1):
            if not 0 <= j < K or times[j] == times[k]:
                continue
            # Camera k's frame to j's: X_j = R_kj X_k + t_kj = X_k + phi x X_k + t_kj (small).
            R_kj = R[j] @ R[k].T
            phi = cv2.Rodrigues(R_kj)[0][:, 0]
            t_kj = t[j] - R_kj @ t[k]
            rates.append(np.r_[phi, t_kj] / (times[j] - times[k]))
        if rates:
            out[k] = np.mean(rates, 0) * seconds
    return out


def level_intrinsics(x: np.ndarray, s: float) -> np.ndarray:
    """(f, cx, cy, k1, k2) at a pyramid level ``s`` times smaller.

    cv2.pyrDown centres coarse pixel i on fine pixel s*i, so pixel coordinates simply scale
    by 1/s (not (u + 0.5)/s - 0.5, which would shift every sample by half a pixel less one
    coarse half pixel and bias the focal length at the coarse levels).
    """
    return np.array([x[0] / s, x[1] / s, x[2] / s, x[3], x[4]])


def full_intrinsics(x: np.ndarray, s: float) -> np.ndarray:
    return np.array([x[0] * s, x[1] * s, x[2] * s, x[3], x[4]])


def adjust_to_tracks(R, t, intr, X, obs_start, obs_frame, obs_xy, rows, velocity, readout,
                      huber_px, iterations, free_intrinsics=True, pp_prior=None):
    """Cameras, intrinsics (``free_intrinsics``) and points adjusted to the tracked points
    alone under a given rolling-shutter readout (Levenberg-Marquardt; the gauge: keyframe 0
    and the first baseline's length), and the reprojection cost left: how well that readout
    explains the tracks. ``pp_prior``: (centre, weight per pixel² of x and y) of the principal
    point's prior. Returns (cost, R, t, intr, X)."""
    pp0, w_pp = pp_prior if pp_prior is not None else (np.zeros(2), np.zeros(2))

    def prior(intr_):
        return float(np.sum(w_pp * (intr_[1:3] - pp0) ** 2))

    K = len(R)
    n_cam = N_INTR + N_FRAME * (K - 1)
    R, t, intr, X = list(R), list(t), intr.copy(), X.copy()
    lam = 1e-3
    baseline = np.linalg.norm(R[1].T @ t[1] - R[0].T @ t[0])

    def run(R_, t_, intr_, X_, with_cameras):
        e = Normal(n_cam, 0, 1, len(X_), len(obs_frame))
        accumulate_tracks(X_, obs_start, obs_frame, obs_xy, np.asarray(R_), np.asarray(t_),
                           intr_, 1.0, huber_px, velocity(R_, t_), readout, rows,
                           with_cameras, e.H, e.b, e.Hpp3, e.bpp3, e.Hpc, e.stats)
        return e

    e = run(R, t, intr, X, True)
    for _ in range(iterations):
        H, b = e.H.copy(), e.b.copy()
        hold_baseline(H, b, R, t, baseline, 1e8)
        if not free_intrinsics:
            H[:N_INTR, :N_INTR] += 1e12 * np.eye(N_INTR)
        else:
            H[1:3, 1:3] += np.diag(w_pp)
            b[1:3] += w_pp * (intr[1:3] - pp0)
        dc = -np.linalg.solve(H + lam * np.diag(np.diag(H)) + 1e-9 * np.eye(n_cam), b)
        R2, t2, _ = update_frames(R, t, np.zeros((K, 2)), dc[N_INTR:])
        intr2 = intr + dc[:N_INTR]
        X2 = X + track_steps(e, dc, obs_start, obs_frame, lam)
        e2 = run(R2, t2, intr2, X2, True)
        if e2.stats[0] + prior(intr2) < e.stats[0] + prior(intr):
            R, t, intr, X, e = R2, t2, intr2, X2, e2
            lam = max(lam / 4, 1e-7)
        else:
            lam *= 4
    return float(e.stats[0]) + prior(intr), R, t, intr, X


def track_noise_px(tracks: tuple[np.ndarray, np.ndarray], R, t, intrinsics: Intrinsics,
                    full: Intrinsics) -> float:
    """The tracked observations' noise at the start (robust standard deviation of their
    reprojection errors, pixels of ``intrinsics``; the start is a bundle adjustment's, so
    what is left is their noise)."""
    points, obs = np.asarray(tracks[0], float), np.asarray(tracks[1], float)
    scale = intrinsics.width / full.width
    errors = np.empty(len(obs))
    for k in np.unique(obs[:, 1]).astype(int):
        sel = obs[:, 1] == k
        uv, _ = project(points[obs[sel, 0].astype(int)], R[k], t[k], intrinsics)
        errors[sel] = np.linalg.norm(uv - ((obs[sel, 2:4] + 0.5) * scale - 0.5), axis=1)
    # The median length of a 2D Gaussian error is 1.1774 of its standard deviation.
    return float(np.median(errors) / 1.1774)
