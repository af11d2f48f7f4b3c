"""Metric scale and the coarse template: the template placed and bent onto the 3D landmarks.

A monocular reconstruction knows its cameras only up to scale. facecap reports millimetres
by a **size prior** (see docs/landmarks.md, "Metric scale"):

* the robust similarity from the template's inner landmark vertices (and ear vertices, when
  ear points exist) to the triangulated landmarks has a scale ``lambda`` (camera units per
  template millimetre);
* an average face's landmark configuration is ``landmark_size`` times the template's (a
  population mean measured once, with the detector's convention: see
  :class:`~facecap_core.coarse.CoarseConfig`);
* so one camera unit is ``landmark_size / lambda`` millimetres.

The error of such a prior is the spread of face sizes around the mean (≈ 5 % for the
landmark configuration over ICT identities). A measured cue narrows it: the subject's
interpupillary distance (``ipd_mm``) against the distance between the triangulated eye
centres (≈ 2 %), or better between the triangulated pupils (≈ 0.6 %). With no measured cue,
the irises still give one: an adult's horizontal visible iris diameter is 11.7 ± 0.5 mm (≈ 4 %,
tighter than the face's size), measured at the triangulated pupils' depth (≈ 6.5 % with the
measurement); the spreads are ``CoarseConfig``'s ``*_spread`` fields. The cues are
combined by their stated spreads (an inverse-variance mean of log scales); one that
disagrees with the others beyond ``cue_agreement_sigmas`` is dropped and reported. The
ear-to-ear width is a cue only when ``ear_width_cue`` is on (not calibrated).
``scale_method: fixed`` takes a known scale as it is.

The **coarse mesh**: the template, placed by the robust similarity (in mm), then bent by a
smooth landmark-driven deformation — a Gaussian radial-basis displacement field of the
landmark residuals (``rbf``, stiff and fast) or the landmarks-only optimal-step NICP
(``nicp``). It initialises and bounds the depth search of MVS.

:func:`main` writes ``coarse.ply``, ``cameras.json`` (t in mm), ``landmarks3d.json`` (68
points in mm, the jaw contour from the coarse mesh), ``ears3d.json`` (mm) and
``coarse.json``.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field

from facecap_core.camera import CAMERAS_JSON
from facecap_core.config import MAX_LEVELS, StrictModel
from facecap_core.errors import InputError
from facecap_core.geometry import robust_similarity
from facecap_core.landmarks.ear_check import reliability
from facecap_core.landmarks.landmarks3d_json import load_landmarks3d
from facecap_core.landmarks.stage import (
    EAR_TEMPLATE,
    EARS_3D,
    LANDMARKS_3D,
    load_ears3d,
)
from facecap_core.lazy import LazyModule
from facecap_core.nonrigid.nicp import NicpConfig, fit
from facecap_core.pose.cameras_json import Cameras, keyframe_poses
from facecap_core.stage import Folders, Stage
from facecap_core.template import INNER_LANDMARKS, Template

trimesh = LazyModule("trimesh")


class CoarseConfig(StrictModel):
    """Metric scale and the coarse template fitted to the 3D landmarks
    (``facecap_core/coarse.py``)."""

    scale_method: Literal["template", "fixed"] = "template"
    """How millimetres are obtained: ``template``: the scale that makes the 3D landmarks
    (and ear points) match the template's landmarks at the template's physical size (a
    population-mean prior); ``fixed``: ``fixed_scale`` (e.g. from a known distance)."""
    fixed_scale: float = Field(1.0, gt=0)
    """Millimetres per camera unit with ``scale_method: fixed``."""
    landmark_size: float = Field(1.0858, gt=0.5, lt=2)
    """Size of an average face's inner-landmark configuration relative to the template's
    landmark vertices (robust similarity scale, template mm to mm): the mean over 200 random
    ICT identities (``benchmarks/bench_landmarks.py --calibrate`` prints it)."""
    scale_cauchy_mm: float = Field(10.0, gt=0)
    """Cauchy scale of the robust similarity that measures the landmark configuration's size
    (template mm; wide: every landmark counts, a stray one does not)."""
    landmark_size_spread: float = Field(0.05, gt=0, lt=1)
    """Relative spread (1σ) of that size over faces: the landmark cue's uncertainty (5.8 %
    RMS measured over 30 held-out ICT identities, 0.7 % on the james scan; ``tests/
    test_coarse.py``)."""
    ipd_mm: float | None = Field(None, ge=40, le=90)
    """The subject's interpupillary distance in mm as an optician measures it ("far PD"),
    when known: the scale then comes mainly from the distance between the triangulated eye
    centres (``--ipd-mm`` on the command line)."""
    ipd_ratio: float = Field(0.9800, gt=0.5, lt=1.5)
    """Pupil distance over the distance between the triangulated centres of the two eyes'
    six landmarks: the mean over the captures of ICT identities 1000-1007 (the rendered
    pupils against the landmark stage's output with exact cameras; ``benchmarks/
    bench_scale.py --calibrate``). Used for ``ipd_mm`` when the pupils were not measured."""
    ipd_spread: float = Field(0.02, gt=0, lt=1)
    """Relative 1σ of the IPD cue against the eye landmarks: the spread of that ratio over
    the calibration captures (1.1 % over 8, rounded up: a spread from 8 faces is itself
    uncertain by a quarter)."""
    pupil_ratio: float = Field(1.0055, gt=0.5, lt=1.5)
    """Pupil distance over the distance between the pupils as the landmark stage triangulates
    them: the mean over the captures of ICT identities 1000-1007 (``benchmarks/
    bench_scale.py --calibrate``). With pupils, ``ipd_mm`` uses them instead of the eye
    landmarks."""
    pupil_ipd_spread: float = Field(0.006, gt=0, lt=1)
    """Relative 1σ of the IPD cue from the triangulated pupils: the spread of ``pupil_ratio``
    over the calibration captures (0.22 % over 8), widened to 0.6 %: a spread from 8 faces is
    itself uncertain by a quarter, rendered pupils are sharper than real ones, and a subject
    who fixates a near point while the camera moves converges the eyes (a far gaze, or eyes
    that follow the camera, give the far PD)."""
    iris_cue: bool = True
    """Use the iris size as a scale cue when the landmark stage measured the irises: an
    adult's horizontal visible iris diameter is ``iris_diameter_mm`` give or take 4 %, a
    tighter prior than the face's size."""
    iris_diameter_mm: float = Field(11.7, gt=8, lt=16)
    """Mean horizontal visible iris diameter of adults (11.7 ± 0.5 mm, 1σ)."""
    iris_ratio: float = Field(0.9838, gt=0.5, lt=1.5)
    """True iris diameter over the landmark stage's measurement (MediaPipe's iris edges at
    the pupils' depth): the mean over the captures of ICT identities 1000-1007, whose renders
    paint each subject's own iris diameter (``benchmarks/bench_scale.py --calibrate``)."""
    iris_spread: float = Field(0.065, gt=0, lt=1)
    """Relative 1σ of the iris cue: the population's 4.3 % (0.5 / 11.7) and the measurement's
    3.7 % (the spread of ``iris_ratio`` over the calibration captures, 640x360 renders with
    irises ~12 px wide; 4.5 % before the face mesh gave the 68 points too), added in
    quadrature (5.5 %) and rounded up to the earlier 6.5 %."""
    ear_width_cue: bool = False
    """Use the ear-to-ear width as a scale cue. Off: it is not calibrated (``ear_width_size``
    is the template's own width) and real-skin ear points can be far off."""
    ear_width_size: float = Field(1.0, gt=0.5, lt=2)
    """Ear-to-ear width of an average head relative to the template's."""
    ear_width_spread: float = Field(0.05, gt=0, lt=1)
    """Relative spread of the ear-to-ear width over heads (weights the ear estimate)."""
    ear_weight: float = Field(1.0, ge=0)
    """Weight of one ear point against one face landmark in the similarity fit of the coarse
    mesh (0 ignores ears)."""
    cue_agreement_sigmas: float = Field(3.0, gt=0)
    """A scale cue further than this many combined standard deviations from the others'
    estimate is dropped (and reported), not averaged in."""
    robust_iterations: int = Field(5, ge=0, le=50)
    """Reweighting rounds of the robust (Cauchy) similarity fit."""
    robust_scale_mm: float = Field(3.0, gt=0)
    """Cauchy scale of the robust similarity fit, in template millimetres."""
    deformation: Literal["rbf", "nicp", "none"] = "rbf"
    """Landmark-driven deformation after the similarity: a smooth radial-basis displacement
    field (``rbf``), the landmarks-only optimal-step NICP (``nicp``), or none."""
    rbf_kernel_mm: float = Field(60.0, gt=0)
    """Width of the Gaussian displacement kernel of ``rbf`` (large: stiff, global bends)."""
    rbf_smoothing: float = Field(0.3, ge=0)
    """Regularisation of ``rbf`` (0: the landmarks are met exactly; larger: stiffer)."""
    nicp_stiffness: list[float] = Field(default_factory=lambda: [10.0, 5.0, 2.0], min_length=1,
                                        max_length=MAX_LEVELS)
    """Stiffness levels of ``nicp`` (high: the coarse mesh stays smooth); each level's
    landmark weight equals its stiffness, as in the fitting stage's schedule."""


COARSE_PLY = "coarse.ply"
COARSE_JSON = "coarse.json"

__all__ = ["main", "metric_scale", "combine_cues",
           "eye_distance", "rbf_deform", "coarse_mesh"]


# --------------------------------------------------------------------------- similarity


# --------------------------------------------------------------------------- scale


def _ear_width(points: np.ndarray, sides: np.ndarray) -> float:
    return float(np.linalg.norm(points[sides == "left"].mean(0) - points[sides == "right"].mean(0)))


def eye_distance(landmarks: np.ndarray) -> float:
    """Distance between the centres of the two eyes' six landmarks (ibug 36-41, 42-47); nan
    when an eye is missing."""
    right, left = landmarks[36:42], landmarks[42:48]
    if not (np.all(np.isfinite(right)) and np.all(np.isfinite(left))):
        return float("nan")
    return float(np.linalg.norm(left.mean(0) - right.mean(0)))


def _log_mean(cues: list[dict]) -> tuple[float, float]:
    """Inverse-variance mean of the cues' log scales and its relative 1σ."""
    w = np.array([1 / c["sigma"] ** 2 for c in cues])
    return float(np.sum(w * np.log([c["mm_per_unit"] for c in cues])) / w.sum()), \
        float(1 / np.sqrt(w.sum()))


def combine_cues(cues: list[dict], agreement_sigmas: float) -> tuple[float, float, list[dict]]:
    """Inverse-variance mean of the cues' log scales: ``(mm per unit, relative 1σ, dropped)``.

    Each cue is ``{"name", "mm_per_unit", "sigma"}`` (relative 1σ). A cue whose estimate
    lies more than ``agreement_sigmas`` combined standard deviations from the others' mean
    is dropped — the worst first, one at a time — as long as two or more cues remain."""
    kept, dropped = list(cues), []
    while len(kept) >= 2:
        worst, worst_z = None, agreement_sigmas
        for cue in kept:
            mean, sigma = _log_mean([c for c in kept if c is not cue])
            z = abs(np.log(cue["mm_per_unit"]) - mean) / np.hypot(cue["sigma"], sigma)
            if z > worst_z:
                worst, worst_z = cue, z
        if worst is None:
            break
        if len(kept) == 2:
            # Two cues that disagree: keep the one with the smaller stated spread.
            worst = max(kept, key=lambda c: c["sigma"])
        kept.remove(worst)
        dropped.append({**worst, "disagreement_sigmas": round(float(worst_z), 2),
                        "reason": "disagrees with the other cues"})
    log_scale, sigma = _log_mean(kept)
    return float(np.exp(log_scale)), sigma, dropped


def metric_scale(template: Template, landmarks: np.ndarray, ear_ids: np.ndarray,
                 ear_points: np.ndarray, ear_sides: np.ndarray, config: CoarseConfig,
                 irises: dict | None = None) -> dict:
    """Millimetres per camera unit, each cue's estimate, the combined 1σ uncertainty and the
    cues dropped for disagreeing or unusable (a JSON-ready dict). ``irises`` is the landmark
    stage's iris measurement (``landmarks3d.json``: ``irises``): triangulated pupils and the
    iris diameter in camera units; without it (None) there is no iris cue and none is
    reported missing."""
    if config.scale_method == "fixed":
        return {"metric_scale": config.fixed_scale, "method": "fixed", "sigma_pct": None,
                "cues": [], "dropped": [], "how": "given (CoarseConfig.fixed_scale)"}
    inner = INNER_LANDMARKS
    ok = np.all(np.isfinite(landmarks[inner]), axis=1)
    src = template.vertices[template.landmarks[inner]][ok]
    s, _, _, _ = robust_similarity(src, landmarks[inner][ok], None, config.robust_iterations,
                                   config.scale_cauchy_mm)
    cues = [{"name": "landmarks", "mm_per_unit": config.landmark_size / s,
             "sigma": config.landmark_size_spread,
             "how": "size prior: the landmark configuration of an average face"}]
    eyes = eye_distance(landmarks)
    irises = irises or {}
    pupils = irises.get("pupil_distance")
    iris_units = irises.get("iris_diameter")
    unusable = []
    if config.ipd_mm is not None and pupils:
        cues.append({"name": "ipd", "mm_per_unit": config.ipd_mm / (config.pupil_ratio * pupils),
                     "sigma": config.pupil_ipd_spread,
                     "how": f"given interpupillary distance {config.ipd_mm:g} mm against the "
                            "triangulated pupils"})
    elif config.ipd_mm is not None and np.isfinite(eyes) and eyes > 0:
        cues.append({"name": "ipd", "mm_per_unit": config.ipd_mm / (config.ipd_ratio * eyes),
                     "sigma": config.ipd_spread,
                     "how": f"given interpupillary distance {config.ipd_mm:g} mm against the "
                            "eye-landmark centres"})
    elif config.ipd_mm is not None:
        unusable.append({"name": "ipd", "reason": "an eye's landmarks were not triangulated"})
    if config.iris_cue and iris_units:
        cues.append({"name": "iris", "mm_per_unit": config.iris_diameter_mm
                     / (config.iris_ratio * iris_units), "sigma": config.iris_spread,
                     "how": f"size prior: an adult's iris is {config.iris_diameter_mm:g} mm "
                            f"across (median of {len(irises.get('iris_diameter_views', []))} "
                            "eye views)"})
    elif config.iris_cue and irises:
        unusable.append({"name": "iris", "reason": irises.get("reason")
                         or "the irises were not measured"})
    both = len(ear_ids) and {"left", "right"} <= set(ear_sides.tolist())
    if config.ear_width_cue and both:
        measured = _ear_width(ear_points, ear_sides)
        reference = _ear_width(template.vertices[ear_ids], ear_sides)
        cues.append({"name": "ear_width", "mm_per_unit": config.ear_width_size * reference
                     / measured, "sigma": config.ear_width_spread,
                     "how": "size prior: the ear-to-ear width of an average head"})
    scale, sigma, dropped = combine_cues(cues, config.cue_agreement_sigmas)
    names = [c["name"] for c in cues if c["name"] not in {d["name"] for d in dropped}]
    dropped += unusable
    return {"method": "cues", "metric_scale": scale, "sigma_pct": round(100 * sigma, 2),
            "cues": cues, "dropped": dropped, "used": names,
            "landmark_similarity_scale": s, "landmarks_used": int(ok.sum()),
            "eye_distance_units": eyes if np.isfinite(eyes) else None,
            "pupil_distance_units": pupils, "iris_diameter_units": iris_units,
            "how": " + ".join(names) + "".join(f"; {d['name']} dropped: {d['reason']}"
                                               for d in dropped)}


# --------------------------------------------------------------------------- deformation


def rbf_deform(vertices: np.ndarray, anchors: np.ndarray, displacements: np.ndarray,
               kernel_mm: float, smoothing: float, weights: np.ndarray | None = None
               ) -> np.ndarray:
    """Displace ``vertices`` by a Gaussian radial-basis field through ``anchors`` (k, 3)
    with values ``displacements`` (k, 3); ``smoothing`` regularises (0: exact), larger for
    anchors of small ``weights``."""
    d2 = np.sum((anchors[:, None] - anchors[None]) ** 2, axis=-1)
    K = np.exp(-d2 / (2 * kernel_mm ** 2))
    w = np.ones(len(anchors)) if weights is None else np.maximum(np.asarray(weights), 1e-6)
    coef = np.linalg.solve(K + np.diag(smoothing / w), displacements)
    out = np.array(vertices, float)
    for start in range(0, len(out), 20000):  # bounded memory: 20k × k kernel blocks
        v = out[start:start + 20000]
        kv = np.exp(-np.sum((v[:, None] - anchors[None]) ** 2, axis=-1) / (2 * kernel_mm ** 2))
        out[start:start + 20000] = v + kv @ coef
    return out


def coarse_mesh(template: Template, landmarks_mm: np.ndarray, ear_ids: np.ndarray,
                ear_points_mm: np.ndarray, config: CoarseConfig,
                ear_weights: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """Coarse vertices (template topology, mm) and a report of the fit. ``ear_weights``
    (k,): each ear point's reliability (1 when None)."""
    inner = INNER_LANDMARKS
    ok = np.all(np.isfinite(landmarks_mm[inner]), axis=1)
    ids = np.r_[template.landmarks[inner][ok], ear_ids].astype(np.int64)
    targets = np.r_[landmarks_mm[inner][ok], ear_points_mm]
    ear_w = np.ones(len(ear_ids)) if ear_weights is None else np.asarray(ear_weights, float)
    base_w = np.r_[np.ones(int(ok.sum())), config.ear_weight * ear_w]
    src = template.vertices[ids]
    s, R, t, w = robust_similarity(src, targets, base_w, config.robust_iterations,
                                   config.robust_scale_mm)
    placed = s * template.vertices @ R.T + t
    before = np.linalg.norm(placed[ids] - targets, axis=1)
    if config.deformation == "rbf":
        V = rbf_deform(placed, placed[ids], targets - placed[ids], config.rbf_kernel_mm,
                       config.rbf_smoothing, w / np.maximum(base_w, 1e-12))
    elif config.deformation == "nicp":
        V = _nicp(template.with_vertices(placed), landmarks_mm, ear_ids, ear_points_mm, config,
                  ear_w)
    else:
        V = placed
    after = np.linalg.norm(V[ids] - targets, axis=1)
    report = {"similarity_scale": s, "deformation": config.deformation,
              "residual_mm_before": _stats(before), "residual_mm_after": _stats(after),
              "robust_weights_below_half": int(np.sum(w / np.maximum(base_w, 1e-12) < 0.5))}
    return V, report


def _nicp(placed: Template, landmarks_mm, ear_ids, ear_points_mm, config: CoarseConfig,
          ear_weights):
    L = np.array(landmarks_mm, float)
    L[:17] = placed.landmark_points[:17]  # unused by the fit; keeps the input finite
    L[~np.all(np.isfinite(L), axis=1)] = placed.landmark_points[~np.all(np.isfinite(L), axis=1)]
    fit_config = NicpConfig(stiffness=list(config.nicp_stiffness),
                            landmark_weight=list(config.nicp_stiffness),
                            use_cloud=False, use_edges=False, initial_similarity=False)
    ears = (ear_ids, ear_points_mm, ear_weights) if len(ear_ids) else None
    return fit(placed, None, L, ear_points=ears, config=fit_config).vertices


def _stats(d: np.ndarray) -> dict:
    d = np.asarray(d, float)
    if not d.size:
        return {}
    return {"mean": float(d.mean()), "median": float(np.median(d)), "max": float(d.max())}


# --------------------------------------------------------------------------- main


def main(landmarks_dir: str | Path, cameras_json: str | Path, out_dir: str | Path,
         template: Template | None = None, config: CoarseConfig | None = None) -> Path:
    """Metric scale + coarse template. Reads ``landmarks3d.json`` (and ``ears3d.json``) from
    ``landmarks_dir``; writes ``coarse.ply``, ``cameras.json``, ``landmarks3d.json``,
    ``ears3d.json`` and ``coarse.json`` into ``out_dir``; returns the path of
    ``coarse.ply``."""

    config = config or CoarseConfig()
    t_wall, t_cpu = time.perf_counter(), time.process_time()
    landmarks_dir = Path(landmarks_dir)
    L, landmarks_doc = load_landmarks3d(landmarks_dir / LANDMARKS_3D)
    if np.sum(np.all(np.isfinite(L[INNER_LANDMARKS]), axis=1)) < 6:
        raise InputError(f"{landmarks_dir / 'landmarks3d.json'} has fewer than 6 inner "
                         "landmarks in 3D: the coarse template needs the face's landmarks")
    ear_ids, ear_pts, ear_doc = load_ears3d(landmarks_dir / EARS_3D)
    ear_sides = np.asarray(ear_doc.get("sides", []), dtype=object).astype(str)
    template = template or Template.default()
    ears_ignored = False
    if len(ear_ids) and ear_doc.get("template", EAR_TEMPLATE) != template.name:
        # Ear vertex ids belong to one template's topology.
        ear_ids, ear_pts, ear_sides, ears_ignored = (np.zeros(0, np.int64), np.zeros((0, 3)),
                                                     np.zeros(0, str), True)
        ear_doc = {**ear_doc, "sigma": []}
    if len(ear_ids) and ear_ids.max() >= len(template.vertices):
        raise InputError(f"ears3d.json names vertex {ear_ids.max()} of a "
                         f"{len(template.vertices)}-vertex template")
    cameras = Cameras.read(cameras_json)
    cams = cameras.camera_set()

    scale_doc = metric_scale(template, L, ear_ids, ear_pts, ear_sides, config,
                             landmarks_doc.irises.model_dump())
    m = float(scale_doc["metric_scale"])
    L_mm, ears_mm = L * m, ear_pts * m
    # Ear points of a document without uncertainties (written by hand) weigh as landmarks.
    sigma = np.asarray(ear_doc.get("sigma", np.zeros(len(ear_ids))), float).reshape(-1)
    if len(sigma) != len(ear_ids):
        raise InputError(f"{landmarks_dir / EARS_3D} holds {len(sigma)} sigmas for "
                         f"{len(ear_ids)} ear points: recompute the landmark stage")
    ear_w = reliability(sigma * m)
    V, fit_doc = coarse_mesh(template, L_mm, ear_ids, ears_mm, config, ear_w)
    L_out = L_mm.copy()
    missing = ~np.all(np.isfinite(L_out), axis=1)
    L_out[missing] = V[template.landmarks[missing]]  # the jaw contour from the coarse mesh

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ply = out / COARSE_PLY
    tmp = out / "coarse.ply.part"
    tmp.write_bytes(trimesh.exchange.ply.export_ply(
        trimesh.Trimesh(V, template.faces, process=False), encoding="binary"))
    tmp.replace(ply)
    cameras.model_copy(update={
        "units": "mm", "metric_scale": m,
        "keyframes": keyframe_poses(cams.frame_indices, cams.R, cams.t * m)}).write(
        out / CAMERAS_JSON)
    _write(out / LANDMARKS_3D, {
        "convention": "ibug68", "units": "mm", "template": template.name,
        "from_coarse_mesh": np.flatnonzero(missing).tolist(),
        "coverage": landmarks_doc.coverage.model_dump(),
        "landmarks": np.round(L_out, 6).tolist()})
    _write(out / EARS_3D, {"template": template.name, "units": "mm",
                                 "vertex_ids": ear_ids.tolist(),
                                 "points": np.round(ears_mm, 6).tolist(),
                                 "sides": ear_sides.tolist(),
                                 "weights": np.round(ear_w, 4).tolist(),
                                 "checks": ear_doc.get("checks", {})})
    _write(out / COARSE_JSON, {
        "scale": scale_doc, "fit": fit_doc, "ears_used": int(len(ear_ids)),
        "ears": ear_doc.get("checks", {}),
        "ears_ignored_other_template": ears_ignored, "template": template.name,
        "config": config.model_dump(mode="json"),
        "seconds": {"wall": round(time.perf_counter() - t_wall, 3),
                    "cpu": round(time.process_time() - t_cpu, 3)}})
    return ply


def _write(path: Path, doc: dict) -> Path:
    tmp = path.with_name(path.name + ".part")
    tmp.write_text(json.dumps(doc, indent=1))
    tmp.replace(path)
    return path


def ears_summary(checks: dict) -> str:
    """One line on the ear points the scale and the fit used: per side, its points or why
    it was dropped."""
    return "; ".join(f"{side} {c['points']} points" if c["used"] else
                     f"{side} dropped: {c['reason']}" for side, c in checks.items())


def scale_summary(scale: dict) -> str:
    """One line on the metric scale's uncertainty and its cues (``scale`` as
    :func:`figures` gives it): ``±4.0 % (1σ) from landmarks + iris; ears dropped (...)``."""
    return (f"±{scale['sigma_pct']:.1f} % (1σ) from {' + '.join(scale['used'])}"
            + "".join(f"; {d['name']} dropped ({d['reason']})" for d in scale["dropped"]))


def figures(folder: str | Path) -> dict:
    """Headline figures of a coarse artifact: the metric scale, its cues and uncertainty,
    and the angular coverage of the landmarks."""
    folder, fig = Path(folder), {}
    if (folder / CAMERAS_JSON).is_file():
        fig["metric_scale"] = Cameras.read(folder / CAMERAS_JSON).metric_scale
    if (folder / COARSE_JSON).is_file():
        doc = json.loads((folder / COARSE_JSON).read_text())
        scale = doc["scale"]
        fig["scale"] = {k: scale.get(k) for k in ("metric_scale", "sigma_pct", "used", "cues",
                                                   "dropped", "how")}
        if doc.get("ears"):
            fig["ears"] = doc["ears"]
    if (folder / LANDMARKS_3D).is_file():
        coverage = json.loads((folder / LANDMARKS_3D).read_text()).get("coverage")
        if coverage:
            fig["coverage"] = coverage
    return fig


def headline(folder: str | Path) -> str:
    """The coarse task's log line's figure: ``: metric scale 90.9 mm per camera unit, ±4.0 %
    (1σ) from landmarks + iris`` ("" without a metric scale)."""
    scale = figures(folder).get("scale") or {}
    if scale.get("metric_scale") is None:
        return ""
    sigma = f", {scale_summary(scale)}" if scale.get("sigma_pct") is not None else ""
    return f": metric scale {scale['metric_scale']:.4g} mm per camera unit{sigma}"


def run(inputs: Folders, out: Path, config: CoarseConfig, params: dict) -> None:
    main(inputs["landmarks"], inputs["poses"] / CAMERAS_JSON, out, config=config)


STAGE = Stage("coarse", version="5", inputs=("landmarks", "poses"), work_seconds=1.0,
              section="coarse", run=run,
              outputs=(CAMERAS_JSON, LANDMARKS_3D, EARS_3D, COARSE_PLY, COARSE_JSON),
              exported=(CAMERAS_JSON, LANDMARKS_3D, EARS_3D, COARSE_PLY, COARSE_JSON),
              figures=figures, headline=headline)
