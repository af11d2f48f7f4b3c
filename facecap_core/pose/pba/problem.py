"""What PBA solves over: its settings, the keyframes' images, the photometric points with
their initial inverse depths (the sparse points at their depths, or strong-gradient pixels
and an epipolar search), the tracked points' observations, the priors and the unknowns."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numba as nb
import numpy as np
from pydantic import Field, model_validator

from facecap_core.camera import Intrinsics, project
from facecap_core.config import KEY_NEUTRAL, StrictModel
from facecap_core.errors import FacecapError
from facecap_core.pose.pba.kernels import N_FRAME, N_INTR, PATTERN, bilinear, undistort
from facecap_core.pose.pba.normal import (
    camera_motion,
    level_intrinsics,
    relative_poses,
    track_noise_px,
)
from facecap_core.video import processing_size


class PBAConfig(StrictModel):
    """Photometric bundle adjustment (``facecap_core/pose/pba/``)."""

    cell: int = Field(12, ge=4, le=64)
    """One point per cell×cell block of each keyframe (its strongest gradient)."""
    min_gradient: float = Field(8.0, ge=0)
    """Weakest gradient (grey levels per pixel) a point may have."""
    search_level: int = Field(1, ge=0, le=5)
    """Pyramid level of the initial depth search along the epipolar lines."""
    search_samples: int = Field(96, ge=8, le=1024)
    """Inverse-depth samples of that search (log-spaced over the sparse points' range)."""
    min_search_quality: float = Field(1.5, ge=1)
    """A point is kept when its second-best match costs this many times its best."""
    neighbours: int = Field(6, ge=1, le=15)
    """Each point is compared in this many keyframes before and after its host."""
    pyramid_levels: int = Field(2, ge=1, le=6)
    """Coarse-to-fine levels (each half the size of the previous)."""
    iterations: int = Field(8, ge=1, le=200)
    """Levenberg–Marquardt iterations per pyramid level."""
    depth_only_iterations: int = Field(2, ge=0, le=200)
    """The first iterations of each level move only the inverse depths."""
    huber: float = Field(1.5, gt=0)
    """Huber threshold of the photometric residual, in units of the residuals' robust
    standard deviation (1.4826 x their median magnitude at the level's starting cameras)."""
    gradient_weight: float = Field(50.0, gt=0)
    """DSO's gradient weight c²/(c² + |∇I|²): strong edges count less (sub-pixel noise)."""
    max_residual: float = Field(3.0, gt=0)
    """A point's pattern in one target is an outlier (occluded, a highlight) when its root
    mean square residual exceeds this many robust standard deviations; it then costs a
    constant."""
    initial_lambda: float = Field(1e-3, gt=0)
    """Initial Levenberg–Marquardt damping."""
    refine_intrinsics: bool = True
    """Refine focal length, principal point and k1, k2 with the poses, when the tracked points
    are in the solve (``track_weight``): photometric residuals over neighbouring keyframes
    alone leave the principal point free against a tilt of every camera."""
    principal_point_prior_pct: float = Field(0.3, ge=0)
    """With the intrinsics refined, the principal point is held near the image centre with
    this standard deviation (% of the image's width for x, of its height for y), weighed as
    one tracked observation off by the tracks' noise: the data move it as far as they pin it
    (a tilt of every camera and a shift of the principal point reproject almost alike), and
    their biases (noise, a codec, a rolling shutter) pull it less the narrower this is. 0.3
    rather than the sensor model's spread of 1: better principal points on 11 of 12
    calibration captures and rotations on 9 (docs/poses.md). 0: free."""
    hold_principal_point: bool = Field(False, json_schema_extra={KEY_NEUTRAL: False})
    """The principal point stays where the start (the geometric refinement) put it; focal
    length and distortion are still refined. Instead of the prior above."""
    scale_prior: float = Field(1e8, gt=0)
    """Weight of the prior that fixes the length of the first baseline (the scale gauge)."""
    points_from_sparse: bool = True
    """Use the initial reconstruction's points (at their depths) instead of an epipolar
    search for strong-gradient pixels."""
    centre_prior_pct: float = Field(0.0, ge=0)
    """Camera centres are held near the start's with this standard deviation (% of the mean
    camera distance from their centroid; 0: free, the gauge is then the first keyframe and
    the first baseline's length)."""
    intrinsics_level: int = Field(0, ge=0, le=5)
    """Intrinsics are held fixed at pyramid levels coarser than this one (coarse levels bias
    the focal length)."""
    motion_blur: bool = True
    """Model each keyframe's motion blur: the streak the camera's motion (a constant velocity
    through the neighbouring keyframes) draws over the exposure. Each residual compares the
    host and the target each blurred by the other's streak. Videos only (photos have no
    times)."""
    exposure_fraction: float | None = Field(None, ge=0, le=1)
    """Exposure as a fraction of the frame interval; None: the one of
    ``exposure_candidates`` whose blur model fits the starting cameras best."""
    exposure_candidates: tuple[float, ...] = Field((0.0, 0.25, 0.5, 0.75), min_length=1)
    """Exposures (fractions of the frame interval) tried when ``exposure_fraction`` is None."""
    track_weight: float = Field(30.0, ge=0)
    """The tracked points' reprojection errors join the photometric residuals in one solve:
    one pixel of reprojection error costs as much as this many grey levels of photometric
    residual (0: photometric only)."""
    track_huber_px: float = Field(1.0, gt=0)
    """Huber threshold of the reprojection errors (pixels)."""
    rolling_shutter: bool = False
    """Model a rolling shutter: each image row exposed at its own time, the camera moving at
    a constant velocity (through the neighbouring keyframes) over the readout; with the
    readout chosen from the tracks, their adjustment under it is PBA's start. Videos only.
    Off by default: SfM and the geometric solution model no rolling shutter, and from their
    start it did not help on the benchmark's rolling-shutter capture (docs/poses.md)."""
    readout_s: float | None = Field(None, ge=0, le=0.1)
    """Readout time from the first row to the last (seconds; 0: global shutter); None: the
    one of ``readout_candidates`` whose model fits the keyframes best."""
    readout_candidates: tuple[float, ...] = Field((0.0, 0.01, 0.02, 0.03, 0.04), min_length=1)
    """Readouts (seconds) tried when ``readout_s`` is None (phones: about 10-35 ms)."""
    blur_samples: int = Field(9, ge=1, le=64)
    """Most samples along one streak (one per pixel of its length)."""
    max_width: int | None = Field(1920, ge=160, le=8192)
    """Keyframes wider than this (pixels) are adjusted at this width (area filter, aspect kept;
    the intrinsics scaled to it and the result's scaled back; poses are metric and do not
    change with it). PBA holds every keyframe with its pyramid and gradients, about 14 bytes
    a pixel: at 3840×2160 that is 116 MB a keyframe, 5 GB for 45 keyframes; at 1920×1080,
    29 MB. None: full resolution. 720p and 1080p captures are not affected."""

    @model_validator(mode="after")
    def _check_search_level(self):
        # Only the search for photometric points reads it: the sparse points replace it.
        if not self.points_from_sparse and self.search_level >= self.pyramid_levels:
            raise ValueError(f"search_level ({self.search_level}) must be a level of the "
                             f"pyramid: under pyramid_levels ({self.pyramid_levels})")
        return self


@nb.njit(cache=True)
def search_depth(host, uv, host_values, rho_lo, rho_hi, samples, neighbours, images, R_rel,
                  t_rel, intr, out_rho, out_quality):
    """Per point, the inverse depth in [rho_lo, rho_hi] (log-spaced samples) whose pattern
    matches best (SSD, mean-normalised) in the neighbouring keyframes; quality is the ratio of
    the second-best separated minimum to the best (higher = less ambiguous)."""
    f, cx, cy, k1, k2 = intr[0], intr[1], intr[2], intr[3], intr[4]
    K = len(images)
    costs = np.empty(samples)
    for p in range(host.shape[0]):
        h = host[p]
        mh = 0.0
        for q in range(8):
            mh += host_values[p, q]
        mh /= 8
        for i in range(samples):
            costs[i] = 0.0
        used = 0
        for dn in range(-neighbours, neighbours + 1):
            tg = h + dn
            if dn == 0 or tg < 0 or tg >= K:
                continue
            used += 1
            Rr = R_rel[h, tg]
            tr = t_rel[h, tg]
            for i in range(samples):
                rho = rho_lo * (rho_hi / rho_lo) ** (i / (samples - 1))
                vals = np.empty(8)
                ok = True
                for q in range(8):
                    xn, yn, _, _, _, _ = undistort((uv[p, 0] + PATTERN[q, 0] - cx) / f,
                                                    (uv[p, 1] + PATTERN[q, 1] - cy) / f, k1, k2)
                    X0 = Rr[0, 0] * xn + Rr[0, 1] * yn + Rr[0, 2] + tr[0] * rho
                    X1 = Rr[1, 0] * xn + Rr[1, 1] * yn + Rr[1, 2] + tr[1] * rho
                    X2 = Rr[2, 0] * xn + Rr[2, 1] * yn + Rr[2, 2] + tr[2] * rho
                    if X2 <= 1e-9:
                        ok = False
                        break
                    yx = X0 / X2
                    yy = X1 / X2
                    s2 = yx * yx + yy * yy
                    fac = 1 + k1 * s2 + k2 * s2 * s2
                    v = bilinear(images[tg], f * yx * fac + cx, f * yy * fac + cy)
                    if np.isnan(v):
                        ok = False
                        break
                    vals[q] = v
                if not ok:
                    costs[i] += 1e6
                    continue
                mt = vals.mean()
                c = 0.0
                for q in range(8):
                    d = (vals[q] - mt) - (host_values[p, q] - mh)
                    c += d * d
                costs[i] += c
        best = np.argmin(costs)
        out_rho[p] = rho_lo * (rho_hi / rho_lo) ** (best / (samples - 1))
        second = np.inf
        for i in range(samples):
            if abs(i - best) > 2 and costs[i] < second:
                second = costs[i]
        out_quality[p] = second / (costs[best] + 1e-6) if used > 0 else 0.0


def _pyramids(images, max_width: int | None, levels: int) -> list[np.ndarray]:
    """Every keyframe's image pyramid (float32 grey, at most ``max_width`` wide, halved by
    cv2.pyrDown), one (keyframes, h, w) array per level: the kernels index the keyframes of
    a level in one array (a numba typed list costs a second of compiling in every run)."""
    first = _processing_grey(images[0], max_width)
    stack = np.empty((len(images), *first.shape), np.float32)
    stack[0] = first
    for k in range(1, len(images)):
        stack[k] = _processing_grey(images[k], max_width)
    out = [stack]
    for _ in range(levels - 1):
        finer = out[-1]
        coarser = cv2.pyrDown(finer[0])
        stack = np.empty((len(finer), *coarser.shape), np.float32)
        stack[0] = coarser
        for k in range(1, len(finer)):
            stack[k] = cv2.pyrDown(finer[k])
        out.append(stack)
    return out


def gradients(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    return gx, gy


def sample(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    if len(uv) == 0:
        return np.zeros(0, np.float32)
    m = uv.astype(np.float32)
    return cv2.remap(img, m[None, :, 0], m[None, :, 1], cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)[0]


def _processing_grey(image: np.ndarray, max_width: int | None) -> np.ndarray:
    """A keyframe as float32 grey, at most ``max_width`` wide (area filter, aspect kept)."""

    grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
    w, h = processing_size(grey.shape[1], grey.shape[0], max_width)
    if (w, h) != (grey.shape[1], grey.shape[0]):
        grey = cv2.resize(grey, (w, h), interpolation=cv2.INTER_AREA)
    return grey.astype(np.float32)


def _at_size(intrinsics: Intrinsics, width: int, height: int) -> Intrinsics:
    """``intrinsics`` for images ``width``×``height`` (the same camera at another resolution:
    pixel-centre convention, as an area-filter resize samples)."""
    if (width, height) == (intrinsics.width, intrinsics.height):
        return intrinsics
    if abs(width / height - intrinsics.width / intrinsics.height) > 0.01:
        raise FacecapError(f"keyframes are {width}x{height} but the camera is "
                           f"{intrinsics.width}x{intrinsics.height} (aspect ratios differ)")
    return intrinsics.scaled(width, height)


def _select_points(img: np.ndarray, cell: int, min_grad: float, margin: int) -> np.ndarray:
    """The strongest-gradient pixel of each cell×cell block, if strong enough (N, 2)."""
    gx, gy = gradients(img)
    mag = np.hypot(gx, gy)
    h, w = img.shape
    hc, wc = (h - 2 * margin) // cell, (w - 2 * margin) // cell
    block = mag[margin:margin + hc * cell, margin:margin + wc * cell]
    block = block.reshape(hc, cell, wc, cell).transpose(0, 2, 1, 3).reshape(hc, wc, -1)
    arg = block.argmax(-1)
    best = np.take_along_axis(block, arg[..., None], -1)[..., 0]
    yy, xx = np.divmod(arg, cell)
    ys = margin + np.arange(hc)[:, None] * cell + yy
    xs = margin + np.arange(wc)[None, :] * cell + xx
    keep = best > min_grad
    return np.stack([xs[keep], ys[keep]], 1).astype(np.float64)


def points_from_sparse(points, hosts, R, t, intrinsics: Intrinsics, shape):
    """The initial reconstruction's points, each hosted in its given keyframe at its depth
    (no search: the geometric solution already knows where they are)."""
    h_img, w_img = shape
    margin = 8
    host, uv, rho = [], [], []
    for k in range(len(R)):
        sel = np.flatnonzero(hosts == k)
        if len(sel) == 0:
            continue
        p, z = project(points[sel], R[k], t[k], intrinsics)
        p = np.round(p)  # pattern pixels on the host's pixel grid (no host interpolation)
        ok = ((z > 0) & (p[:, 0] >= margin) & (p[:, 0] < w_img - margin)
              & (p[:, 1] >= margin) & (p[:, 1] < h_img - margin))
        if not ok.any():
            continue
        # Depth along the host ray of the rounded pixel: the camera-frame z of the point.
        host.append(np.full(ok.sum(), k))
        uv.append(p[ok])
        rho.append(1.0 / z[ok])
    if not host:
        return np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0)
    return (np.concatenate(host).astype(np.int64), np.concatenate(uv).astype(np.float64),
            np.concatenate(rho))


def _points_by_search(pyramid, R, t, intr, sparse_points, config: PBAConfig, log):
    """Strong-gradient pixels with inverse depths from an epipolar search."""
    K = len(pyramid[0])
    uvs = [_select_points(pyramid[0][k], config.cell, config.min_gradient, margin=8)
           for k in range(K)]
    host = np.concatenate([np.full(len(u), k) for k, u in enumerate(uvs)]).astype(np.int64)
    uv0 = np.concatenate(uvs)
    depths = np.concatenate([(sparse_points @ R[k].T + t[k])[:, 2] for k in range(K)])
    depths = depths[depths > 0]
    if len(host) == 0 or len(depths) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0)
    rho_lo = 1.0 / (np.percentile(depths, 99) * 1.5)
    rho_hi = 1.0 / (np.percentile(depths, 1) * 0.7)
    ss = 2.0 ** config.search_level
    uv_s = uv0 / ss
    vals_s = np.empty((len(host), 8))
    for k in range(K):
        sel = host == k
        for q, d in enumerate(PATTERN):
            vals_s[sel, q] = sample(pyramid[config.search_level][k], uv_s[sel] + d)
    R_rel, t_rel = relative_poses(R, t)
    rho = np.empty(len(host))
    quality = np.empty(len(host))
    search_depth(host, uv_s, vals_s, rho_lo, rho_hi, config.search_samples, 2,
                  pyramid[config.search_level], R_rel, t_rel,
                  level_intrinsics(intr, ss), rho, quality)
    keep = quality >= config.min_search_quality
    log.append(f"{keep.sum()} of {len(keep)} points kept after the depth search")
    return host[keep], uv0[keep], rho[keep]


@dataclass
class State:
    """The unknowns of the solve, and what the models fitted to them chose."""

    R: list[np.ndarray]
    t: list[np.ndarray]
    affine: np.ndarray  # (K, 2) brightness a, b per keyframe
    intr: np.ndarray  # f, cx, cy, k1, k2 at the processing resolution
    rho: np.ndarray  # the photometric points' inverse depths in their hosts
    X: np.ndarray  # the tracked points
    exposure_s: float
    readout_s: float
    centres0: np.ndarray  # where the centre prior holds the camera centres
    w_centre: float = 0.0  # the centre prior's weight at the current level


class Problem:
    """What the solve is over, fixed while the cameras move: the keyframes' pyramids, the
    photometric points and the keyframes each is compared in (the parameter layout: the
    intrinsics, then pose and brightness per keyframe after the first), the tracked points'
    observations, the priors (principal point, camera centres, scale) and the video's timing
    (motion blur, rolling shutter)."""

    def __init__(self, images, intrinsics: Intrinsics, R, t, sparse_points, config: PBAConfig,
                 progress, sparse_hosts, centre_prior, times, frame_interval_s, tracks):
        self.config, self.progress, self.log = config, progress, []
        self.pyramid = _pyramids(images, config.max_width, config.pyramid_levels)
        self.K = K = len(self.pyramid[0])
        self.shape = self.pyramid[0].shape[1:]
        self.full = intrinsics
        self.intrinsics = _at_size(intrinsics, self.shape[1], self.shape[0])
        R = [np.asarray(r, float) for r in R]
        t = [np.asarray(x, float) for x in t]
        self.baseline_ref = np.linalg.norm(R[1].T @ t[1] - R[0].T @ t[0])
        centres0 = np.array([-r.T @ x for r, x in zip(R, t)])
        spread = np.linalg.norm(centres0 - centres0.mean(0), axis=1).mean()
        # One standard deviation of a centre costs as much as one residual at the Huber
        # threshold.
        self.w_centre_unit = (1 / (config.centre_prior_pct / 100 * spread) ** 2
                              if centre_prior and config.centre_prior_pct > 0 else 0.0)
        self._principal_point_prior(tracks, R, t)
        intr = np.array([self.intrinsics.fx, self.intrinsics.cx, self.intrinsics.cy,
                         self.intrinsics.k1, self.intrinsics.k2])
        if config.points_from_sparse and sparse_hosts is not None:
            self.host, self.uv0, rho = points_from_sparse(sparse_points, sparse_hosts, R, t,
                                                           self.intrinsics, self.shape)
            self.log.append(f"{len(self.host)} points from the initial reconstruction")
        else:
            self.host, self.uv0, rho = _points_by_search(self.pyramid, R, t, intr,
                                                         sparse_points, config, self.log)
        if len(self.host) == 0:
            raise FacecapError("photometric bundle adjustment found no usable points: the "
                               "keyframes have no texture")
        tgt = [[k for k in range(max(0, h - config.neighbours),
                                 min(K, h + config.neighbours + 1)) if k != h]
               for h in self.host]
        self.target_start = np.concatenate([[0], np.cumsum([len(x) for x in tgt])]
                                           ).astype(np.int64)
        self.targets = np.fromiter((k for x in tgt for k in x), np.int64)
        self.n_cam = N_INTR + N_FRAME * (K - 1)
        self.max_local = N_INTR + N_FRAME * (2 * config.neighbours + 1)
        self.video = times is not None and bool(frame_interval_s)
        self.blur = config.motion_blur and self.video
        self.shutter = config.rolling_shutter and self.video
        self.key_times = np.asarray(times if times is not None else np.zeros(K), float)
        self.frame_interval_s = frame_interval_s
        X = self._tracks(tracks)
        # Without the tracks the intrinsics stay put: the photometric residuals over
        # neighbouring keyframes leave the principal point free against a tilt of every
        # camera.
        self.free_intrinsics = config.refine_intrinsics and len(X) > 0
        self.start = State(
            R, t, np.zeros((K, 2)), intr, rho, X,
            exposure_s=((config.exposure_fraction or 0.0) * (frame_interval_s or 0.0)
                        if self.blur else 0.0),
            readout_s=(config.readout_s or 0.0) if self.shutter else 0.0, centres0=centres0)

    def _principal_point_prior(self, tracks, R, t) -> None:
        """The principal point's prior: a deviation of one standard deviation (processing
        pixels) costs as much as one tracked observation off by the tracks' noise, so that
        it weighs as a prior should against the data whatever their noise (exact tracks:
        nothing)."""
        config, intrinsics = self.config, self.intrinsics
        self.pp0 = intrinsics.image_centre
        pp_sigma = config.principal_point_prior_pct / 100 * np.array([intrinsics.width,
                                                                      intrinsics.height])
        self.w_pp = np.zeros(2)
        if config.hold_principal_point:
            self.pp0 = np.array([intrinsics.cx, intrinsics.cy])
            self.w_pp = np.full(2, 1e12)
            self.log.append("principal point held at the start's")
        elif config.principal_point_prior_pct > 0 and tracks is not None and len(tracks[0]):
            noise = track_noise_px(tracks, R, t, intrinsics, self.full)
            self.w_pp = config.track_weight ** 2 * noise ** 2 / pp_sigma ** 2
            self.log.append(f"principal point prior: ±{config.principal_point_prior_pct:g} % "
                            f"of the image, the tracks' noise {noise:.2f} px")

    def _tracks(self, tracks) -> np.ndarray:
        """The tracked points (the geometric solution's, with their observations) in the
        same solve: long tracks pin what the photometric residuals over neighbouring
        keyframes leave loose (the principal point against a tilt of every camera, the chain
        of centres). Sets their observations; returns the points."""
        if tracks is None or self.config.track_weight <= 0:
            self.obs_start = np.zeros(1, np.int64)
            self.obs_frame = np.zeros(0, np.int64)
            self.obs_xy = np.zeros((0, 2))
            self.track_w = 0.0
            return np.zeros((0, 3))
        X = np.asarray(tracks[0], float).copy()
        obs = np.asarray(tracks[1], float)
        obs = obs[np.argsort(obs[:, 0], kind="stable")]
        pid = obs[:, 0].astype(np.int64)
        self.obs_start = np.searchsorted(pid, np.arange(len(X) + 1)).astype(np.int64)
        self.obs_frame = obs[:, 1].astype(np.int64)
        scale_px = np.array([self.intrinsics.width / self.full.width,
                             self.intrinsics.height / self.full.height])
        self.obs_xy = (obs[:, 2:4] + 0.5) * scale_px - 0.5
        self.track_w = self.config.track_weight ** 2
        return X

    def velocity(self, R, t) -> np.ndarray:
        return camera_motion(R, t, self.key_times, 1.0) if self.video else np.zeros((self.K, 6))

    def prior_cost(self, st: State, R, t, intr) -> float:
        cost = float(np.sum(self.w_pp * (intr[1:3] - self.pp0) ** 2))
        if st.w_centre == 0:
            return cost
        c = np.array([-r.T @ x for r, x in zip(R, t)])
        return cost + st.w_centre * float(np.sum((c - st.centres0) ** 2))

    def say(self, line: str) -> None:
        self.log.append(line)
        if self.progress:
            print(line)
