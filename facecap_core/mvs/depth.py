"""One keyframe's depth map: the coarse mesh's prior, PatchMatch and the per-map filter
(the MVS stage's fan-out unit, one artifact per reference keyframe).

    main(index, frames, cameras.json, views.json, coarse.ply, out) -> depth_<index>.npz
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import replace
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from facecap_core.camera import CAMERAS_JSON, Intrinsics
from facecap_core.coarse import COARSE_PLY
from facecap_core.config import StrictModel
from facecap_core.errors import InputError
from facecap_core.meshio import load_mesh
from facecap_core.mvs.filtering import filter_with_prior
from facecap_core.mvs.images import MVSView, downscale_view, load_view, metric_cameras
from facecap_core.mvs.patchmatch import (
    DepthMap,
    neighbour_pattern,
    patchmatch_depth,
    presmoothed,
)
from facecap_core.mvs.prior import CoarsePrior, coarse_prior
from facecap_core.mvs.sweep import smooth_normals, sweep_depth
from facecap_core.mvs.views import VIEWS, read_views
from facecap_core.render import RaycastScene
from facecap_core.stage import Folders, Stage


class DepthMapConfig(StrictModel):
    """One keyframe's depth map: the search range from the coarse mesh, PatchMatch, and the
    per-map filter (``mvs.depth``)."""

    processing_width: int = Field(640, ge=64, le=4096)
    """Width (px) the keyframes are resized to before undistortion and matching."""
    depth_margin_mm: float = Field(8.0, gt=0, le=100)
    """Half-width of the depth search range around the coarse mesh."""
    head_dilation_px: int = Field(6, ge=0, le=100)
    """Pixels the coarse mesh's silhouette is grown by to form the computed region."""
    method: Literal["patchmatch", "sweep"] = "patchmatch"
    """How the depths are searched: ``patchmatch`` (the paper's: slanted planes, sparse
    bilateral window, ``patchmatch.py``) or ``sweep`` (fronto-parallel planes every
    ``sweep_step_mm`` around the coarse depth, dense box window, ``sweep.py``): a fifth of
    the depth stage's time, as accurate or more on rendered faces, less consistent on real
    photos and on the real head scan (docs/mvs.md, "Which depth search"). Both use the
    window radius, the best-views aggregation and the filter below; the PatchMatch fields
    only PatchMatch."""
    sweep_step_mm: float = Field(0.5, gt=0, le=10)
    """Spacing of the sweep's planes (a parabola through the best one and its neighbours
    gives the depth between them)."""
    start: Literal["random", "sweep"] = "random"
    """Where PatchMatch's planes start. ``random``: random planes in the coarse mesh's range,
    then ``iterations`` (the paper's). ``sweep``: the plane sweep's depths over PatchMatch's
    pre-blurred images (``sweep_step_mm`` apart; 1 mm measured) with the normals of the
    planes fitted to its depths over ``start_normal_sigma_px``, then ``sweep_iterations`` of
    PatchMatch from them: with 1 mm, the depth maps in 0.65 of the time, as good or better on the real scan
    and the real photo set (smoother), but the phone-like ICT renders' ears 10-34 % worse, so
    not the default (docs/mvs.md, "PatchMatch from the sweep"). One level only
    (``levels: 1``)."""
    sweep_iterations: int = Field(2, ge=1, le=8)
    """PatchMatch iterations after the sweep's start (``start: sweep``), with ``neighbours``
    and refinement steps from a quarter of the first ones; one cost the calibration render's
    ears 6-8 % (its maps) to 13-26 % (its mesh, with four neighbours)."""
    start_normal_sigma_px: float = Field(6.0, gt=0, le=50)
    """Gaussian (px) weighting the sweep's depths each pixel's starting plane is fitted to
    (``start: sweep``): the slant over a window, not a pixel's sub-step noise (4 and 10 px
    were as good on the calibration render's maps)."""
    init_from_coarse: bool = True
    """Also test the coarse mesh's plane at initialisation (the paper initialises with it)."""

    iterations: int = Field(4, ge=1, le=32)
    """Red–black PatchMatch iterations (each updates both colours once). Four: as accurate
    as five on the real-skin calibration captures (ICT 11 `clean` and `phone_512`), three
    and two were worse on `phone_512` (docs/mvs.md, "How many iterations")."""
    levels: int = Field(1, ge=1, le=2)
    """PatchMatch's pyramid. 1: every iteration at ``processing_width``. 2: the
    ``iterations`` at half that width (a quarter of the pixels), then ``fine_iterations`` at
    full width starting from the half-width planes: the depth maps in 0.58-0.74 of the
    time, but meshes up to 11 % less accurate on the ICT renders (the clean render's mouth
    and completion, the ears on phone-like video), so not the default (docs/mvs.md, "Coarse
    to fine"). ``method: sweep`` has one level whatever this says."""
    fine_iterations: int = Field(2, ge=1, le=8)
    """Iterations at full width after the half-width level (``levels: 2``), propagating from
    the four nearest neighbours (whatever ``neighbours`` says), with refinement steps a
    quarter of the first level's."""
    neighbours: str = Field("fast", pattern="^(fast|full)$")
    """Gipuma's propagation pattern: 8 ('fast': ±1, ±5 on both axes) or 20 ('full')."""
    refine_trials: int = Field(3, ge=0, le=10)
    """Random refinements per pixel and iteration (depth, normal, both perturbed)."""
    normal_perturbation_deg: float = Field(30.0, gt=0, le=90)
    """Largest normal perturbation; the depth and normal steps halve every iteration."""
    window_radius: int = Field(5, ge=1, le=15)
    """Half-size (px) of the matching window. 3 (with ``window_step`` 2: every second pixel
    over ±2 px): the depth maps in about half the time and 10-13 % better faces on clean
    captures, but a sparser cloud on real skin, worse faces on the noisy calibration renders
    (ICT 11, ICT 104) and worse ears on the real scan, so not the default (docs/mvs.md, "The
    matching window")."""
    window_step: int = Field(2, ge=1, le=5)
    """Sample every ``window_step``-th pixel of the window (sparse window)."""
    presmooth_sigma: float = Field(0.8, ge=0, le=5)
    """Gaussian blur (px) of the grey images before matching (noise vs. sparse sampling)."""
    sigma_color: float = Field(0.2, gt=0)
    """Bilateral weight's intensity spread (intensities in [0, 1])."""
    sigma_spatial: float | None = Field(None, gt=0)
    """Bilateral weight's spatial spread in px; default: the window radius."""
    num_best_views: int = Field(8, ge=1, le=64)
    """A hypothesis' cost is the mean of its best this-many per-view costs (occlusion)."""
    pixel_views: int = Field(0, ge=0, le=64)
    """From the second iteration on, each pixel is matched only against the this-many
    sources that fit its current plane best, chosen again every iteration (0, or a single
    iteration: against all sources). At least ``num_best_views``; equal to it, a
    hypothesis' cost is the mean over the pixel's views. 8: 14 % less time per map and
    more consistent meshes on the real photo set and the phone-like renders, but worse
    ears on the phone-like calibration render, so not the default (docs/mvs.md, "Which
    views per pixel")."""
    seed: int = Field(0, ge=0, le=2**32 - 1)
    """Seed of the random hypotheses (results are reproducible per keyframe)."""

    max_cost: float = Field(0.5, gt=0, le=2)
    """Depths whose aggregated cost (1 - NCC) exceeds this are rejected."""
    coarse_max_distance_mm: float = Field(6.0, gt=0)
    """Depths farther than this from the coarse mesh (along the ray) are rejected."""

    @model_validator(mode="after")
    def _check_start(self):
        if self.start == "sweep" and self.levels != 1:
            raise ValueError("start: sweep is a one-level search; set levels: 1")
        return self

    @model_validator(mode="after")
    def _check_pixel_views(self):
        if 0 < self.pixel_views < self.num_best_views:
            raise ValueError(f"pixel_views ({self.pixel_views}) must be 0 or at least "
                             f"num_best_views ({self.num_best_views})")
        return self


log = logging.getLogger(__name__)


def depth_map_name(index: int) -> str:
    """File of one keyframe's depth map (:func:`save_depth_map`)."""
    return f"depth_{int(index):05d}.npz"


def compute_depth_map(ref: MVSView, sources: list[MVSView], coarse_vertices: np.ndarray,
                      coarse_faces: np.ndarray, config: DepthMapConfig
                      ) -> tuple[DepthMap, DepthMap]:
    """One keyframe's depth map: coarse prior, PatchMatch or the plane sweep
    (``config.method``), coarse-mesh filter.

    Returns (raw, filtered); both carry depth, camera-frame normal and cost maps.
    """
    scene = RaycastScene()
    scene.add(coarse_vertices, coarse_faces)
    prior = coarse_prior(ref, coarse_vertices, coarse_faces, config.depth_margin_mm,
                         config.head_dilation_px, scene)
    if config.method == "sweep":
        raw = sweep_depth(ref, sources, prior, config.depth_margin_mm, config.sweep_step_mm,
                          config.window_radius, config.num_best_views)
    elif config.start == "sweep":
        raw = patchmatch_from_sweep(ref, sources, prior, config)
    else:
        raw = patchmatch_pyramid(ref, sources, prior, coarse_vertices, coarse_faces, scene,
                                 config)
    filtered = filter_with_prior(raw, prior, config.max_cost, config.coarse_max_distance_mm,
                                 config.depth_margin_mm)
    return raw, filtered


FINE_FIRST_STEP = 2
"""The full-width level's refinement steps start at 0.5 ** this of the first level's: its
planes are already within a few tenths of a mm (a half was worse on the calibration render's
depth maps: 0.324 against 0.315 mm, docs/experiments/2026-11-28-coarse-to-fine-patchmatch.md)."""


def patchmatch_from_sweep(ref: MVSView, sources: list[MVSView], prior: CoarsePrior,
                          config: DepthMapConfig) -> DepthMap:
    """The plane sweep's depths, with the slant of the planes fitted to them, as the planes
    PatchMatch starts from, then ``config.sweep_iterations`` of PatchMatch: the sweep finds
    the depth along each ray at a fraction of PatchMatch's cost, PatchMatch tilts and
    refines the planes."""
    start, cpu = time.perf_counter(), time.thread_time()
    # The sweep matches the images PatchMatch will (pre-blurred against the sensor's noise):
    # unblurred, the phone-like calibration render's face median was 2 % worse.
    blurred = [replace(v, grey=presmoothed(v.grey, config.presmooth_sigma))
               for v in (ref, *sources)]
    planes = sweep_depth(blurred[0], blurred[1:], prior, config.depth_margin_mm,
                         config.sweep_step_mm, config.window_radius, config.num_best_views)
    planes.normal = smooth_normals(planes.depth, ref.intr, config.start_normal_sigma_px)
    # Gipuma's pattern, not the four nearest a pyramid's finer level uses: the sweep's
    # planes are right per pixel but not yet per surface, and the ears need the far
    # neighbours (docs/experiments/2026-11-29-patchmatch-from-the-sweep.md).
    planes = patchmatch_depth(ref, sources, prior, config, planes, config.sweep_iterations,
                              FINE_FIRST_STEP, neighbours=neighbour_pattern(config.neighbours))
    planes.seconds = time.perf_counter() - start
    planes.cpu_seconds = time.thread_time() - cpu
    return planes


def patchmatch_pyramid(ref: MVSView, sources: list[MVSView], prior: CoarsePrior,
                       coarse_vertices: np.ndarray, coarse_faces: np.ndarray,
                       scene: RaycastScene, config: DepthMapConfig) -> DepthMap:
    """PatchMatch over ``config.levels`` pyramid levels, coarsest first: the coarsest runs
    every iteration from random planes; each finer one starts from the planes of the level
    below and refines them (``scene``: the coarse mesh's, for each level's prior)."""
    start, cpu = time.perf_counter(), time.thread_time()
    planes = None
    for level in range(config.levels - 1, -1, -1):
        if level == 0:
            view, views, level_prior = ref, sources, prior
        else:
            factor = 0.5 ** level
            view = downscale_view(ref, factor)
            views = [downscale_view(s, factor) for s in sources]
            level_prior = coarse_prior(view, coarse_vertices, coarse_faces, config.depth_margin_mm,
                                       max(1, round(config.head_dilation_px * factor)), scene)
        if planes is None:
            planes = patchmatch_depth(view, views, level_prior, config)
        else:
            planes = patchmatch_depth(view, views, level_prior, config, planes,
                                      config.fine_iterations, FINE_FIRST_STEP)
    planes.seconds = time.perf_counter() - start
    planes.cpu_seconds = time.thread_time() - cpu
    return planes


def save_depth_map(depth: DepthMap, folder: str | Path) -> Path:
    """``depth_<index>.npz`` (depth, normal, cost, K, size, R, t, sources)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / depth_map_name(depth.index)
    tmp = folder / f".{path.stem}.part.npz"
    np.savez_compressed(tmp, depth=depth.depth, normal=depth.normal, cost=depth.cost,
                        K=depth.intr.K, size=np.array([depth.intr.width, depth.intr.height]),
                        R=depth.R, t=depth.t,
                        sources=np.asarray(depth.sources if depth.sources is not None else []))
    tmp.replace(path)
    return path


def load_depth_map(path: str | Path) -> DepthMap:
    """A depth map written by :func:`save_depth_map`."""
    with np.load(path) as z:
        w, h = (int(v) for v in z["size"])
        K = z["K"]
        intr = Intrinsics(w, h, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
        index = int(Path(path).stem.split("_")[-1])
        return DepthMap(index, z["depth"], z["normal"], z["cost"], intr, z["R"], z["t"],
                        z["sources"])


def main(index: int, frames_dir: str | Path, cameras_json: str | Path,
               views_json: str | Path, coarse_ply: str | Path, out_dir: str | Path,
               config: DepthMapConfig | None = None) -> Path:
    """One keyframe's filtered depth map; writes ``depth_<index>.npz`` and returns it."""
    config = config or DepthMapConfig()
    cams = metric_cameras(cameras_json)
    sources = read_views(views_json)
    if int(index) not in sources:
        raise InputError(f"keyframe {index} is not in {views_json}")
    coarse = load_mesh(coarse_ply, "coarse mesh")
    ref = load_view(frames_dir, cams, index, config.processing_width)
    srcs = [load_view(frames_dir, cams, j, config.processing_width) for j in sources[int(index)]]
    _, filtered = compute_depth_map(ref, srcs, coarse.vertices, coarse.faces, config)
    path = save_depth_map(filtered, out_dir)
    meta = {"index": int(index), "seconds": round(filtered.seconds, 3),
            "cpu_seconds": round(filtered.cpu_seconds, 3),
            "valid_pixels": int(filtered.valid.sum())}
    path.with_suffix(".json").write_text(json.dumps(meta))
    log.info("depth map of keyframe %d: %d valid pixels (%.0f %%) from %d source views in "
             "%.1f s", int(index), meta["valid_pixels"], 100.0 * filtered.valid.mean(),
             len(srcs), filtered.seconds)
    return path


def run(inputs: Folders, out: Path, config: DepthMapConfig, params: dict) -> None:
    main(params["index"], inputs["frames"], inputs["coarse"] / CAMERAS_JSON,
         inputs["views"] / VIEWS, inputs["coarse"] / COARSE_PLY, out, config)


def reference_keyframes(inputs: Folders) -> list[int]:
    """The keyframes that get a depth map: those the view selection chose."""
    return sorted(read_views(inputs["views"] / VIEWS))


STAGE = Stage("depth", version="3", inputs=("frames", "coarse", "views"),
              work_seconds=135.0,
              section="mvs.depth", run=run,
              outputs=("depth_{index:05d}.npz", "depth_{index:05d}.json"),
              per_keyframe=reference_keyframes)
