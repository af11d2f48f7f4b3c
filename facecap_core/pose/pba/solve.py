"""PBA's solve: one :class:`_Level` of the image pyramid at a time (its images, the normal
equations at a :class:`State`, the models' choice, the Levenberg-Marquardt iterations), and
:func:`photometric_bundle_adjustment`, which runs the levels coarse to fine."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from facecap_core.camera import Intrinsics
from facecap_core.pose.pba.kernels import N_FRAME, N_INTR, PATTERN
from facecap_core.pose.pba.normal import (
    Normal,
    accumulate_in_chunks,
    accumulate_tracks,
    adjust_to_tracks,
    full_intrinsics,
    hold_baseline,
    level_intrinsics,
    relative_poses,
    track_steps,
    update_frames,
)
from facecap_core.pose.pba.problem import PBAConfig, Problem, State, gradients, sample


@dataclass
class PBAResult:
    intrinsics: Intrinsics
    R: list[np.ndarray]
    t: list[np.ndarray]
    affine: np.ndarray  # (K, 2) brightness a, b per keyframe
    points: int
    residuals: int
    rms_before: float
    rms_after: float
    seconds: float
    log: list[str]
    exposure_fraction: float | None = None  # the exposure the blur model used (of a frame)
    readout_s: float | None = None  # the rolling shutter's readout the model used


class _Level:
    """One level of the image pyramid: its images, gradients and the points' pattern
    weights; the residuals and normal equations at a state, the robust scale, the models'
    choice (exposure, readout) and the Levenberg-Marquardt iterations."""

    def __init__(self, problem: Problem, level: int):
        p = self.p = problem
        self.level, self.s = level, 2.0 ** level
        self.frozen_velocity = None
        self.huber = self.max_residual = 1e9
        # (keyframes, h, w) each, as the kernel indexes them.
        self.imgs = p.pyramid[level]
        self.gxs, self.gys = np.empty_like(self.imgs), np.empty_like(self.imgs)
        for k in range(p.K):
            self.gxs[k], self.gys[k] = gradients(self.imgs[k])
        self.uv = p.uv0 / self.s
        self.host_weights = np.empty((len(p.host), 8))
        c2 = p.config.gradient_weight ** 2
        for k in range(p.K):
            sel = p.host == k
            for q, d in enumerate(PATTERN):
                # DSO's weight from the host's gradient: fixed while the poses move, so the
                # cost cannot fall by sliding residuals onto strong edges.
                g2 = (sample(self.gxs[k], self.uv[sel] + d) ** 2
                      + sample(self.gys[k], self.uv[sel] + d) ** 2)
                self.host_weights[sel, q] = c2 / (c2 + g2)

    def evaluate(self, st: State, R, t, affine, intr, rho, X, with_cameras: bool,
                 with_tracks: bool = True, residuals=None, jacobians: bool = True) -> Normal:
        """The cost and normal equations at cameras ``R, t, affine, intr`` and points
        ``rho, X`` (the exposure and readout of ``st``); without ``jacobians`` only the
        cost: the photometric residuals' Jacobians are skipped (a step's test, a model's
        choice)."""
        p = self.p
        R_rel, t_rel = relative_poses(R, t)
        e = Normal(p.n_cam, len(p.host), p.max_local, len(X), len(p.obs_frame))
        intr_l = level_intrinsics(intr, self.s)
        vel = self.frozen_velocity if self.frozen_velocity is not None else p.velocity(R, t)
        rows = self.imgs[0].shape[0]
        accumulate_in_chunks(p.host, self.uv, rho, p.target_start, p.targets, self.imgs,
                              self.gxs, self.gys, self.host_weights,
                              vel * (st.exposure_s / 2), p.config.blur_samples, vel,
                              st.readout_s, rows, R_rel, t_rel, affine, intr_l, self.huber,
                              self.max_residual, with_cameras,
                              e.H, e.b, e.Hpp, e.bpp, e.Hcp, e.idx, e.stats,
                              residuals if residuals is not None else np.zeros(0),
                              jacobians=jacobians)
        if with_tracks and len(X):
            accumulate_tracks(X, p.obs_start, p.obs_frame, p.obs_xy / self.s, np.asarray(R),
                               np.asarray(t), intr_l, p.track_w * self.s * self.s,
                               p.config.track_huber_px / self.s, vel, st.readout_s, rows,
                               with_cameras, e.H, e.b, e.Hpp3, e.bpp3, e.Hpc, e.stats)
        e.cost, e.count = float(e.stats[0]), int(e.stats[1])
        return e

    def at(self, st: State, with_cameras: bool = False, **kwargs) -> Normal:
        """:meth:`evaluate` at the state."""
        return self.evaluate(st, st.R, st.t, st.affine, st.intr, st.rho, st.X, with_cameras,
                             **kwargs)

    def magnitudes(self, st: State) -> tuple[Normal, np.ndarray]:
        """The photometric cost at the state and every residual's magnitude."""
        buf = np.empty(8 * len(self.p.targets))
        e = self.at(st, with_tracks=False, residuals=buf, jacobians=False)
        return e, buf[:int(e.stats[2])]

    def robust_scale(self, st: State, magnitudes: np.ndarray | None = None) -> float:
        """1.4826 x the median residual magnitude at the current cameras (grey levels): the
        residuals' standard deviation, whatever the outliers. ``magnitudes``: those of the
        state, when an evaluation already gave them (they do not depend on the loss)."""
        buf = self.magnitudes(st)[1] if magnitudes is None else magnitudes
        n = len(buf)
        # At least the noise of 8-bit quantisation (1/sqrt(12) grey levels): exact renders
        # would otherwise make every residual an outlier.
        return max(1.4826 * float(np.median(buf[:n])) if n else 1.0, 12 ** -0.5)

    def set_robust_loss(self, st: State, magnitudes: np.ndarray | None = None) -> float:
        """The robust loss in units of the residuals' own spread (noise, codec, blur differ
        from capture to capture): Huber, and the outlier bound of a pattern in one target.
        Returns the spread. ``magnitudes``: as :meth:`robust_scale` takes them."""
        sigma = self.robust_scale(st, magnitudes)
        self.huber = self.p.config.huber * sigma
        self.max_residual = self.p.config.max_residual * sigma
        return sigma

    def choose(self, st: State, candidates, field: str, scale: float | None, name: str,
               unit: str) -> np.ndarray:
        """Sets ``st.<field>`` to the candidate (times ``scale``) whose model makes the
        residuals smallest; returns their magnitudes under it (the robust scale's)."""
        costs, magnitudes = [], []
        for value in candidates:
            setattr(st, field, value if scale is None else value * scale)
            e, buf = self.magnitudes(st)
            costs.append(e.cost / max(e.count, 1))
            magnitudes.append(buf)
        best = candidates[int(np.argmin(costs))]
        setattr(st, field, best if scale is None else best * scale)
        self.p.say(f"{name} " + ", ".join(f"{v:g}: rms {np.sqrt(c):.3f}"
                                          for v, c in zip(candidates, costs))
                   + f"; chose {best:g} {unit} at level {self.level}")
        return magnitudes[int(np.argmin(costs))]

    def readout_from_tracks(self, st: State) -> None:
        """The readout from the tracks, each candidate after its own adjustment of the
        cameras: the start absorbed the shutter's distortion into its cameras (a tilt, a
        principal point), so at the start every readout but 0 looks worse. The chosen
        readout's adjustment is the start: SfM and the geometric solution model no rolling
        shutter. The track cost's unit is one observation (track_w in the joint solve)."""
        p, config = self.p, self.p.config
        pp_prior = (p.pp0, p.w_pp / max(config.track_weight ** 2, 1e-12))
        adjusted = [adjust_to_tracks(
            st.R, st.t, st.intr, st.X, p.obs_start, p.obs_frame, p.obs_xy, p.shape[0],
            p.velocity, value, config.track_huber_px, 15, p.free_intrinsics, pp_prior)
            for value in config.readout_candidates]
        costs = [a[0] for a in adjusted]
        best = int(np.argmin(costs))
        st.readout_s = config.readout_candidates[best]
        if st.readout_s > 0:
            st.R, st.t, st.intr, st.X = adjust_to_tracks(
                *adjusted[best][1:], p.obs_start, p.obs_frame, p.obs_xy,
                p.shape[0], p.velocity, st.readout_s, config.track_huber_px, 35,
                p.free_intrinsics, pp_prior)[1:]
            st.centres0 = np.array([-r.T @ x for r, x in zip(st.R, st.t)])
        p.say("readout " + ", ".join(f"{v:g}: cost {c:.4g}"
                                     for v, c in zip(config.readout_candidates, costs))
              + f"; chose {st.readout_s:g} s from the tracks")

    def prepare(self, st: State) -> None:
        """The level's robust loss; the exposure and the readout where they are not given.
        They are rarely known for a video: the candidates whose model makes the residuals
        smallest (an over- or under-estimate leaves the two sides of every residual
        differently blurred, or their rows at the wrong times). Again at each level:
        misaligned cameras favour a longer exposure (blurring both sides hides
        misalignment), the finer level starts from better ones."""
        p, config = self.p, self.p.config
        sigma = self.set_robust_loss(st)
        choose_readout = p.shutter and config.readout_s is None
        choose_exposure = p.blur and config.exposure_fraction is None
        # The residuals under the last choice, which left the state as it is now.
        magnitudes = None
        if choose_readout and self.level == config.pyramid_levels - 1:
            if len(st.X):
                self.readout_from_tracks(st)
            else:
                magnitudes = self.choose(st, config.readout_candidates, "readout_s", None,
                                         "readout", "s")
        if choose_exposure:
            magnitudes = self.choose(st, config.exposure_candidates, "exposure_s",
                                     p.frame_interval_s, "exposure", "of a frame")
        if choose_readout or choose_exposure:
            sigma = self.set_robust_loss(st, magnitudes)
        p.log.append(f"level {self.level}: residual scale {sigma:.2f} grey levels")
        if p.w_centre_unit:
            st.w_centre = self.huber ** 2 * p.w_centre_unit

    def normal_step(self, st: State, e: Normal, lam: float):
        """The Levenberg-Marquardt step of the cameras, intrinsics and points from the
        normal equations ``e`` with the gauge and the priors; returns the moved
        ``(R, t, affine, intr, rho step, X)``."""
        p, config, s = self.p, self.p.config, self.s
        H, b = e.H, e.b
        hold_baseline(H, b, st.R, st.t, p.baseline_ref, config.scale_prior)
        if st.w_centre > 0:
            # Centre c = -R^T t moves by -R^T v under the increment (v, w).
            for k in range(1, p.K):
                sl = slice(N_INTR + N_FRAME * (k - 1), N_INTR + N_FRAME * (k - 1) + 3)
                c = -st.R[k].T @ st.t[k]
                H[sl, sl] += st.w_centre * np.eye(3)
                b[sl] += -st.w_centre * st.R[k] @ (c - st.centres0[k])
        if not p.free_intrinsics or self.level > config.intrinsics_level:
            H[:N_INTR, :N_INTR] += 1e12 * np.eye(N_INTR)
        else:
            # The prior in the level's pixels (cx_l = cx / s): cost w s² (cx_l - c0 / s)².
            H[1:3, 1:3] += np.diag(p.w_pp * s * s)
            b[1:3] += p.w_pp * s * (st.intr[1:3] - p.pp0)
        dc = -np.linalg.solve(H + lam * np.diag(np.diag(H) + 1e-9), b)
        dcl = np.where(e.idx >= 0, dc[np.maximum(e.idx, 0)], 0.0)
        drho = -(e.bpp + np.sum(e.Hcp * dcl, 1)) / (e.Hpp * (1 + lam) + 1e-12)
        R2, t2, aff2 = update_frames(st.R, st.t, st.affine, dc[N_INTR:])
        intr2 = full_intrinsics(level_intrinsics(st.intr, s) + dc[:N_INTR], s)
        X2 = st.X + track_steps(e, dc, p.obs_start, p.obs_frame, lam)
        return R2, t2, aff2, intr2, drho, X2

    def iterate(self, st: State) -> float | None:
        """The level's Levenberg-Marquardt iterations (inverse depths alone for the first
        ``depth_only_iterations``, then jointly with the cameras); returns the rms of the
        first residuals (None without iterations)."""
        p, config = self.p, self.p.config
        lam, rms_first = config.initial_lambda, None
        for it in range(config.iterations):
            # The camera velocities (blur, rolling shutter) are those of the iteration's
            # start for its step and the step's test: the Jacobians hold them fixed.
            self.frozen_velocity = p.velocity(st.R, st.t)
            cams = it >= config.depth_only_iterations
            e = self.at(st, cams)
            cost, count = e.cost, e.count
            cost_prior = p.prior_cost(st, st.R, st.t, st.intr)
            if rms_first is None:
                rms_first = np.sqrt(cost / max(count, 1))
            if cams:
                R2, t2, aff2, intr2, drho, X2 = self.normal_step(st, e, lam)
            else:
                drho = -e.bpp / (e.Hpp * (1 + lam) + 1e-12)
                R2, t2, aff2, intr2, X2 = st.R, st.t, st.affine, st.intr, st.X
            rho2 = np.clip(st.rho + drho, st.rho * 0.5, st.rho * 2.0)
            e2 = self.evaluate(st, R2, t2, aff2, intr2, rho2, X2, False, jacobians=False)
            accept = e2.cost + p.prior_cost(st, R2, t2, intr2) <= cost + cost_prior
            if accept:
                st.R, st.t, st.affine, st.intr, st.rho, st.X = R2, t2, aff2, intr2, rho2, X2
                lam = max(lam / 4, 1e-7)
            else:
                lam *= 4
            p.say(f"level {self.level} it {it:2d} {'joint' if cams else 'depth'}: rms "
                  f"{np.sqrt(cost / max(count, 1)):.3f} -> "
                  f"{np.sqrt(e2.cost / max(e2.count, 1)):.3f}, {e2.count} residuals, "
                  f"{'accepted' if accept else 'rejected'}, f {st.intr[0]:.2f}, "
                  f"lambda {lam:.1e}, |drho|/rho {np.median(np.abs(drho) / st.rho):.1e}")
        return rms_first


def photometric_bundle_adjustment(images: list[np.ndarray], intrinsics: Intrinsics,
                                  R: list[np.ndarray], t: list[np.ndarray],
                                  sparse_points: np.ndarray, config: PBAConfig | None = None,
                                  progress: bool = False,
                                  sparse_hosts: np.ndarray | None = None,
                                  centre_prior: bool = False,
                                  times: list[float] | None = None,
                                  frame_interval_s: float | None = None,
                                  tracks: tuple[np.ndarray, np.ndarray] | None = None
                                  ) -> PBAResult:
    """Refine keyframe poses, intrinsics and distortion photometrically.

    ``images``: the keyframes (grey or RGB) in video order, at the intrinsics' resolution or
    any other of the same aspect ratio; those wider than ``config.max_width`` are adjusted at
    that width, and the returned intrinsics are at the resolution of ``intrinsics``;
    ``R``, ``t``: their initial world-to-camera poses; ``sparse_points``: 3D points of the
    initial reconstruction. With ``sparse_hosts`` (a host keyframe per sparse point, -1 for
    none) and ``config.points_from_sparse``, the photometric points are those sparse points,
    hosted there at their initial depths; otherwise strong-gradient pixels get their initial
    inverse depth by a search along the epipolar lines within the sparse points' depth range.
    With ``centre_prior`` and ``config.centre_prior_pct`` > 0 the camera centres are held
    near their initial positions (that % of the mean camera distance from their centroid).

    ``tracks``: world points and their observations (rows: point, keyframe, x, y in pixels of
    ``intrinsics``), whose reprojection errors join the photometric residuals in one solve
    (``config.track_weight``); only with them are the intrinsics refined.
    ``times`` (seconds, one per keyframe) and ``frame_interval_s`` (1 / fps) make it a video:
    motion blur (``config.motion_blur``) and the rolling shutter (``config.rolling_shutter``)
    are modelled from the camera's velocity through the neighbouring keyframes.
    """
    config = config or PBAConfig()
    start = time.perf_counter()
    problem = Problem(images, intrinsics, R, t, sparse_points, config, progress,
                       sparse_hosts, centre_prior, times, frame_interval_s, tracks)
    st = problem.start
    rms_first = None
    for level in reversed(range(config.pyramid_levels)):
        finest = _Level(problem, level)
        finest.prepare(st)
        first = finest.iterate(st)
        rms_first = first if rms_first is None else rms_first
    finest.frozen_velocity = None
    e = finest.at(st, jacobians=False)
    full, processed = problem.full, problem.intrinsics
    out = Intrinsics(processed.width, processed.height, float(st.intr[0]), float(st.intr[0]),
                     float(st.intr[1]), float(st.intr[2]), float(st.intr[3]),
                     float(st.intr[4]))
    if (out.width, out.height) != (full.width, full.height):
        out = out.scaled(full.width, full.height)
    return PBAResult(out, st.R, st.t, st.affine, len(problem.host), e.count, float(rms_first),
                     float(np.sqrt(e.cost / max(e.count, 1))),
                     time.perf_counter() - start, problem.log,
                     st.exposure_s / frame_interval_s if problem.blur else None,
                     st.readout_s if problem.shutter else None)
