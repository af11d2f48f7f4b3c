"""Geometric accuracy of a face mesh against a ground-truth scan (Agrawal et al. 2020, Table 1).

Protocol
--------
1. **Face region.** Both the reconstruction and the ground-truth scan usually hold more than
   the face (ears, neck, hair, a back of the head), and the amount differs from method to
   method. Scores are therefore taken inside one sphere defined on the *scan*, in the style
   of the NoW benchmark: its centre is the scan's nose tip (iBUG landmark 30) and its radius
   is ``radius_factor * (|L36 - L45| + |L27 - L33|) / 2`` — the mean of the outer-eye-corner
   distance and the nasion–nose-base length, times ``radius_factor`` (1.4 by default, about
   95 mm on an adult face: ear to ear across the front, forehead to chin). See
   :func:`region_sphere` and :func:`face_region`.
2. **Alignment** (:func:`align`). The reconstruction is brought into the scan's frame:

   a. if landmarks of the reconstruction are given, a Umeyama fit of its 51 inner landmarks
      (17–67; the jaw contour 0–16 is not anatomically stable) to the scan's; otherwise the
      identity (the mesh must already be roughly in the scan frame);
   b. trimmed ICP: the mesh vertices inside the face sphere (enlarged ×1.1 so that the
      boundary does not bias the fit) are matched to their closest points *on the scan
      surface* (point-to-triangle), the worst ``1 - trim`` of the matches are dropped, and the
      total transform from the original mesh coordinates to the matched points is re-solved
      (Umeyama) until it stops changing. Anderson acceleration extrapolates the transform
      from the last few steps (same fixed points, several times fewer iterations on smooth
      faces where point-to-point ICP slides slowly).

   Two protocols differ only in the transform allowed. ``"similarity"`` also fits a scale, as
   for methods whose output has no metric scale; ``"metric"`` fixes the scale to 1, so a
   wrongly-sized metric reconstruction is penalised — the point of a metric pipeline.
3. **Distances** (:func:`score`), exact point-to-triangle distances in the scan's millimetres:

   * *accuracy*: from each aligned mesh vertex inside the sphere to the scan surface;
   * *completion*: from each scan vertex inside the sphere to the aligned mesh surface.

   Each side is summarised by mean, std, median and the fractions under 1 mm and 2 mm.
   Accuracy punishes wrong geometry; completion punishes missing geometry (a mesh cropped to
   the nose and eyes can be accurate but is incomplete).

:func:`paper_table` averages per-capture scores over captures as Table 1 does (see there),
and :func:`error_heatmap` paints per-vertex errors on the mesh for a figure.

Conventions: meshes are in millimetres, the face looks towards +z, +y is up and +x is the
subject's left (the convention of facecap's data and of :func:`error_heatmap`'s views).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import open3d as o3d
from pydantic import BaseModel, ConfigDict, Field
from scipy.spatial.transform import Rotation

from facecap_core.camera import Intrinsics, look_at
from facecap_core.errors import InputError
from facecap_core.meshio import load_landmarks, load_mesh
from facecap_core.render import RaycastScene, interpolate, shade_lambert, vertex_normals

EVALUATION_JSON = "evaluation.json"

__all__ = [
    "EvaluationConfig", "Alignment", "Stats", "Score", "PROTOCOLS", "INNER_LANDMARKS",
    "umeyama", "region_sphere", "face_region", "distances", "align", "score", "score_json",
    "evaluate", "error_heatmap", "mesh_render", "paper_table",
]

Protocol = Literal["similarity", "metric"]
PROTOCOLS: tuple[str, ...] = ("similarity", "metric")

#: iBUG indices used for the landmark initialisation: brows, nose, eyes, mouth (not the jaw).
INNER_LANDMARKS = np.arange(17, 68)

#: Height in pixels of the colour-bar strip under the heat-map views.
COLORBAR_HEIGHT = 60


class EvaluationConfig(BaseModel):
    """Parameters of the evaluation protocol; the defaults reproduce facecap's reported numbers."""

    model_config = ConfigDict(extra="forbid", frozen=True, use_attribute_docstrings=True)

    radius_factor: float = Field(1.4, gt=0)
    """Face-sphere radius as a multiple of the mean of the outer-eye-corner distance and the
    nasion–nose-base length (1.4 gives about 95 mm on an adult face)."""

    trim: float = Field(0.9, gt=0, le=1)
    """Fraction of ICP matches kept each iteration, the closest ones; the rest are outliers
    (hair, holes, boundary)."""

    max_iterations: int = Field(60, ge=0)
    """Most ICP iterations; 0 keeps the landmark (or identity) alignment as it is."""

    use_landmarks: bool = True
    """Start ICP from a Umeyama fit of the mesh's landmarks when they are given; when False
    they are ignored and ICP starts from the identity."""

    icp_margin: float = Field(1.1, ge=1)
    """ICP uses mesh vertices inside the face sphere enlarged by this factor, so that vertices
    just outside the scored region still hold the fit at its boundary."""

    anderson: int = Field(5, ge=0)
    """ICP steps remembered by Anderson acceleration; 0 gives plain (slow) point-to-point ICP
    with the same result."""

    tolerance: float = Field(1e-6, gt=0)
    """ICP stops when the RMS motion of the matched vertices between two iterations falls
    below this fraction of the face-sphere radius."""


# --------------------------------------------------------------------------- transforms


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True
            ) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity (or rigid) transform with ``dst ≈ s * R @ src + t``.

    Umeyama (1991): ``R`` is always a proper rotation (det +1) — a reflection that would fit
    better is replaced by the best rotation. Returns ``(s, R, t)``; ``s`` is 1.0 when
    ``with_scale`` is False.
    """
    src = np.asarray(src, float)
    dst = np.asarray(dst, float)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ValueError(f"umeyama needs two (N>=3, 3) arrays of equal shape; got {src.shape} "
                         f"and {dst.shape}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, D, Vt = np.linalg.svd(cov)
    S = np.ones(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2] = -1.0  # flip the weakest axis: the best proper rotation, not a reflection
    R = (U * S) @ Vt
    if with_scale:
        var_s = np.sum(xs * xs) / len(src)
        s = float(np.sum(D * S) / var_s) if var_s > 0 else 1.0
    else:
        s = 1.0
    t = mu_d - s * R @ mu_s
    return s, R, t


def _matrix(s: float, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    M = np.eye(4)
    M[:3, :3] = s * R
    M[:3, 3] = t
    return M


@dataclass
class Alignment:
    """A similarity transform ``x -> s R x + t`` from mesh to scan coordinates, and its fit."""

    s: float
    R: np.ndarray
    t: np.ndarray
    iterations: int = 0  # ICP steps run (closest-point queries + Umeyama solves)
    rms: float = float("nan")  # RMS of the kept (trimmed) ICP distances at the end, mm
    matched: int = 0  # mesh vertices used by the last ICP step (after trimming)

    @property
    def matrix(self) -> np.ndarray:
        """The 4×4 homogeneous matrix of the transform."""
        return _matrix(self.s, self.R, self.t)

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Transform points (N, 3) from mesh to scan coordinates."""
        return self.s * np.asarray(points, float) @ self.R.T + self.t


# --------------------------------------------------------------------------- region


def _check_landmarks(landmarks: np.ndarray, what: str) -> np.ndarray:
    lm = np.asarray(landmarks, float)
    if lm.shape != (68, 3) or not np.all(np.isfinite(lm)):
        raise InputError(f"{what} landmarks must be 68 finite 3-D points in iBUG order; got an "
                         f"array of shape {lm.shape}")
    return lm


def region_sphere(landmarks68: np.ndarray, radius_factor: float = 1.4) -> tuple[np.ndarray, float]:
    """Centre and radius (mm) of the NoW-style face sphere from 68 iBUG landmarks.

    Centre: the nose tip (landmark 30). Radius: ``radius_factor * (|L36 - L45| + |L27 - L33|)
    / 2``, i.e. scaled from the outer-eye-corner distance and the nasion–nose-base length so
    that it adapts to face size.
    """
    lm = _check_landmarks(landmarks68, "face-region")
    eyes = np.linalg.norm(lm[36] - lm[45])
    nose = np.linalg.norm(lm[27] - lm[33])
    return lm[30].copy(), float(radius_factor * (eyes + nose) / 2.0)


def face_region(vertices: np.ndarray, landmarks68: np.ndarray, radius_factor: float = 1.4
                ) -> np.ndarray:
    """Boolean mask of the vertices inside the face sphere of :func:`region_sphere`."""
    centre, radius = region_sphere(landmarks68, radius_factor)
    return np.linalg.norm(np.asarray(vertices, float) - centre, axis=1) <= radius


# --------------------------------------------------------------------------- distances


class _Surface:
    """A triangle mesh prepared for repeated closest-point queries (open3d's BVH).

    open3d works in float32; the mesh is shifted to its own centroid first so that large
    world coordinates keep their precision, and the closest point is rebuilt in float64 from
    the returned triangle and barycentric coordinates, so it lies exactly on the triangle.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        self.vertices = np.asarray(vertices, float)
        self.faces = np.asarray(faces, np.int64)
        if self.faces.ndim != 2 or self.faces.shape[1] != 3 or len(self.faces) == 0:
            raise InputError(f"a mesh needs triangles (F, 3); got faces of shape {self.faces.shape}")
        self.origin = self.vertices.mean(0)
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(
            o3d.core.Tensor(np.ascontiguousarray(self.vertices - self.origin, dtype=np.float32)),
            o3d.core.Tensor(np.ascontiguousarray(self.faces, dtype=np.uint32)),
        )

    def closest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Closest surface points (N, 3) and distances (N,) for query points (N, 3)."""
        points = np.asarray(points, float).reshape(-1, 3)
        if len(points) == 0:
            return np.zeros((0, 3)), np.zeros(0)
        ans = self._scene.compute_closest_points(o3d.core.Tensor(
            np.ascontiguousarray(points - self.origin, dtype=np.float32)))
        prim = ans["primitive_ids"].numpy().astype(np.int64)
        if (prim >= len(self.faces)).any():  # open3d's "no triangle found"
            raise InputError("no triangle of a mesh is within reach of the points it is "
                             "compared with (degenerate triangles?); repair the mesh")
        uv = ans["primitive_uvs"].numpy().astype(float)
        tri = self.vertices[self.faces[prim]]  # (N, 3 corners, 3)
        q = ((1.0 - uv[:, :1] - uv[:, 1:]) * tri[:, 0] + uv[:, :1] * tri[:, 1]
             + uv[:, 1:] * tri[:, 2])
        return q, np.linalg.norm(points - q, axis=1)


def distances(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Exact distance (N,) from each point to the nearest point of the triangle mesh surface."""
    return _Surface(vertices, faces).closest(points)[1]


# --------------------------------------------------------------------------- alignment


MAX_LOG_SCALE = 20.0
"""Largest |log scale| an extrapolated ICP transform may have (a factor of 5e8): beyond it
the extrapolation, not the data, is speaking."""


def _params(s: float, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(log s, rotation vector, t): a flat vector in which transforms can be extrapolated."""
    return np.concatenate([[math.log(s)], Rotation.from_matrix(R).as_rotvec(), t])


def _transform(x: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    return math.exp(x[0]), Rotation.from_rotvec(x[1:4]).as_matrix(), x[4:7].copy()


def _align(mesh_vertices: np.ndarray, scan: _Surface, scan_landmarks: np.ndarray,
           mesh_landmarks: np.ndarray | None, with_scale: bool,
           config: EvaluationConfig) -> Alignment:
    mv = np.asarray(mesh_vertices, float)
    centre, radius = region_sphere(scan_landmarks, config.radius_factor)
    radius_icp = radius * config.icp_margin

    if mesh_landmarks is not None and config.use_landmarks:
        ml = _check_landmarks(mesh_landmarks, "mesh")
        s0, R0, t0 = umeyama(ml[INNER_LANDMARKS], scan_landmarks[INNER_LANDMARKS], with_scale)
    else:
        s0, R0, t0 = 1.0, np.eye(3), np.zeros(3)
    # ICP works on the mesh as placed by the initial transform, so that its own rotation
    # stays small (rotation vectors are only well-behaved away from 180 degrees); composing
    # the two at the end is exact.
    base = s0 * mv @ R0.T + t0

    def step(x):
        """One ICP step from transform x: its trimmed energy and the re-solved transform."""
        s, R, t = _transform(x)
        moved = s * base @ R.T + t
        idx = np.flatnonzero(np.linalg.norm(moved - centre, axis=1) <= radius_icp)
        if len(idx) < 3:
            raise InputError(
                f"only {len(idx)} mesh vertices lie in the scan's face region during alignment: "
                "pass mesh landmarks (--mesh-landmarks) or put the mesh in the scan's frame first")
        q, d = scan.closest(moved[idx])
        keep = np.argsort(d, kind="stable")[:max(3, math.ceil(config.trim * len(d)))]
        # The total transform from the (initially placed) mesh to its matches, not an
        # increment on the last estimate, so that rounding does not accumulate.
        s_n, R_n, t_n = umeyama(base[idx[keep]], q[keep], with_scale)
        if not s_n > 0:  # the matches collapse to a point or a line: no scale fits them
            raise InputError("the mesh cannot be aligned to the scan: its vertices in the face "
                             "region match the scan in a single point or line (a collapsed or "
                             "damaged mesh?); repair the mesh")
        after = s_n * base[idx[keep]] @ R_n.T + t_n
        change = math.sqrt(np.mean(np.sum((after - moved[idx[keep]]) ** 2, axis=1))) / radius
        energy = float(np.mean(d[keep] ** 2))
        return _params(s_n, R_n, t_n), energy, change

    # Plain point-to-point ICP crawls when the surface lets the mesh slide (smooth cheeks,
    # forehead): hundreds of iterations per degree. Anderson acceleration extrapolates the
    # next transform from the last few ICP steps; it has the same fixed points as plain ICP,
    # and a step that raises the trimmed energy is undone (Pavlov et al. 2018, Zhang et al.
    # 2021).
    g = np.zeros(7)  # max_iterations = 0: keep the initial alignment
    iterations = 0
    if config.max_iterations > 0:
        x = g
        g, energy, change = step(x)
        g_hist, f_hist = [g], [g - x]
        iterations = 1
        while change >= config.tolerance and iterations < config.max_iterations:
            accelerated = config.anderson > 0 and len(g_hist) >= 2
            if accelerated:
                dG = np.diff(np.array(g_hist), axis=0).T
                dF = np.diff(np.array(f_hist), axis=0).T
                theta = np.linalg.lstsq(dF, f_hist[-1], rcond=None)[0]
                x = g - dG @ theta
                if not (np.all(np.isfinite(x)) and abs(x[0]) < MAX_LOG_SCALE):
                    # Nearly parallel steps (a degenerate mesh) extrapolate to nonsense:
                    # take the plain ICP step instead.
                    x, accelerated = g, False
            else:
                x = g
            g_new, e_new, change = step(x)
            iterations += 1
            if accelerated and e_new > energy:
                # The extrapolation overshot: take the plain ICP step and start afresh.
                x = g
                g_new, e_new, change = step(x)
                iterations += 1
                g_hist, f_hist = [], []
            g, energy = g_new, e_new
            g_hist = (g_hist + [g])[-(config.anderson + 1):]
            f_hist = (f_hist + [g - x])[-(config.anderson + 1):]

    s1, R1, t1 = _transform(g)
    s, R, t = s1 * s0, R1 @ R0, s1 * R1 @ t0 + t1
    # Report the fit of the final transform (one more query, cheap next to ICP).
    moved = s * mv @ R.T + t
    inside = np.linalg.norm(moved - centre, axis=1) <= radius_icp
    rms, matched = float("nan"), 0
    if np.any(inside):
        d = np.sort(scan.closest(moved[inside])[1])
        d = d[:max(1, math.ceil(config.trim * len(d)))]
        rms, matched = float(np.sqrt(np.mean(d ** 2))), len(d)
    return Alignment(s=float(s), R=R, t=t, iterations=iterations,
                     rms=rms, matched=matched)


def align(mesh_vertices: np.ndarray, mesh_faces: np.ndarray, scan_vertices: np.ndarray,
          scan_faces: np.ndarray, scan_landmarks: np.ndarray,
          mesh_landmarks: np.ndarray | None = None, with_scale: bool = True,
          config: EvaluationConfig | None = None) -> Alignment:
    """Align a mesh to a scan: landmark Umeyama (if mesh landmarks) then trimmed ICP.

    ICP matches mesh vertices to the closest points on the scan *surface*; ``mesh_faces`` is
    accepted for symmetry with :func:`score` and is not needed by the fit. With ``with_scale``
    False the transform is rigid (the metric protocol). Returns an :class:`Alignment` from
    mesh to scan coordinates.
    """
    config = config or EvaluationConfig()
    scan_lm = _check_landmarks(scan_landmarks, "scan")
    return _align(mesh_vertices, _Surface(scan_vertices, scan_faces), scan_lm, mesh_landmarks,
                  with_scale, config)


# --------------------------------------------------------------------------- scoring


@dataclass
class Stats:
    """Summary of one side's distances (mm) inside the face region."""

    mean: float
    std: float
    median: float
    under_1mm: float  # fraction of distances < 1 mm
    under_2mm: float  # fraction of distances < 2 mm
    count: int

    @classmethod
    def of(cls, d: np.ndarray) -> Stats:
        """Statistics of the finite distances in ``d`` (nan everywhere when there are none)."""
        d = np.asarray(d, float)
        d = d[np.isfinite(d)]
        if len(d) == 0:
            nan = float("nan")
            return cls(nan, nan, nan, nan, nan, 0)
        return cls(float(d.mean()), float(d.std()), float(np.median(d)),
                   float(np.mean(d < 1.0)), float(np.mean(d < 2.0)), int(len(d)))

    def to_dict(self) -> dict:
        return {"mean": self.mean, "std": self.std, "median": self.median,
                "under_1mm": self.under_1mm, "under_2mm": self.under_2mm, "count": self.count}


@dataclass
class Score:
    """Result of :func:`score` for one protocol.

    ``accuracy_per_vertex`` has one entry per mesh vertex and ``completion_per_vertex`` one
    per scan vertex: the distance in mm, nan outside the face region — ready for
    :func:`error_heatmap` (accuracy on the *aligned* mesh: ``alignment.apply(vertices)``).
    """

    protocol: str
    accuracy: Stats
    completion: Stats
    scale: float
    alignment: Alignment
    accuracy_per_vertex: np.ndarray = field(repr=False)
    completion_per_vertex: np.ndarray = field(repr=False)

    @property
    def matrix(self) -> np.ndarray:
        """4×4 transform from mesh to scan coordinates."""
        return self.alignment.matrix

    def to_dict(self) -> dict:
        """JSON-ready summary (no per-vertex arrays)."""
        return {"protocol": self.protocol, "accuracy": self.accuracy.to_dict(),
                "completion": self.completion.to_dict(), "scale": self.scale,
                "matrix": self.matrix.tolist(), "icp_iterations": self.alignment.iterations,
                "icp_rms": self.alignment.rms}


def score(mesh_vertices: np.ndarray, mesh_faces: np.ndarray, scan_vertices: np.ndarray,
          scan_faces: np.ndarray, scan_landmarks: np.ndarray,
          mesh_landmarks: np.ndarray | None = None, protocol: Protocol = "similarity",
          config: EvaluationConfig | None = None) -> Score:
    """Align the mesh to the scan under ``protocol`` and measure accuracy and completion.

    ``"similarity"`` fits a scale, ``"metric"`` does not (the score's ``scale`` is then 1).
    Distances are in the scan's units (mm), inside the scan's face sphere.
    """
    config = config or EvaluationConfig()
    if protocol not in PROTOCOLS:
        raise InputError(f"unknown evaluation protocol {protocol!r}; use one of {', '.join(PROTOCOLS)}")
    scan_lm = _check_landmarks(scan_landmarks, "scan")
    scan = _Surface(scan_vertices, scan_faces)
    al = _align(mesh_vertices, scan, scan_lm, mesh_landmarks, protocol == "similarity", config)

    centre, radius = region_sphere(scan_lm, config.radius_factor)
    moved = al.apply(mesh_vertices)
    acc = np.full(len(moved), np.nan)
    in_mesh = np.linalg.norm(moved - centre, axis=1) <= radius
    acc[in_mesh] = scan.closest(moved[in_mesh])[1]

    sv = np.asarray(scan_vertices, float)
    comp = np.full(len(sv), np.nan)
    in_scan = np.linalg.norm(sv - centre, axis=1) <= radius
    comp[in_scan] = _Surface(moved, mesh_faces).closest(sv[in_scan])[1]

    return Score(protocol=protocol, accuracy=Stats.of(acc), completion=Stats.of(comp),
                 scale=al.s, alignment=al, accuracy_per_vertex=acc, completion_per_vertex=comp)


_JSON_STATS = ("mean", "std", "median", "under_1mm", "under_2mm")


def score_json(score: Score) -> dict:
    """The per-capture record used by reports and :func:`paper_table`.

    ``{"protocol", "accuracy": {mean, std, median, under_1mm, under_2mm}, "completion": {...},
    "scale"}``: distances in mm, fractions in [0, 1], ``scale`` the fitted mesh→scan scale.
    """
    def side(st: Stats) -> dict:
        return {k: float(getattr(st, k)) for k in _JSON_STATS}

    return {"protocol": score.protocol, "accuracy": side(score.accuracy),
            "completion": side(score.completion), "scale": float(score.scale)}


def evaluate(mesh_path: str | Path, scan_path: str | Path,
             scan_landmarks_path: str | Path | None = None,
             mesh_landmarks_path: str | Path | None = None,
             protocols: Sequence[str] = PROTOCOLS,
             config: EvaluationConfig | None = None) -> dict[str, Score]:
    """Score a mesh file against a scan file under each protocol; ``{protocol: Score}``.

    The scan's landmarks (68 3-D points, iBUG order, in the scan's frame) are required: they
    define the face region. The mesh's landmarks are optional and only initialise alignment.
    """
    config = config or EvaluationConfig()
    unknown = [p for p in protocols if p not in PROTOCOLS]
    if unknown or not protocols:
        raise InputError(f"unknown evaluation protocol(s) {unknown or '(none given)'}; "
                         f"use {' and/or '.join(PROTOCOLS)}")
    if scan_landmarks_path is None:
        raise InputError(f"scan {scan_path} has no landmarks: pass --scan-landmarks FILE "
                         "(68 points, iBUG order) so the face region can be cut")
    mesh = load_mesh(mesh_path, "mesh")
    scan = load_mesh(scan_path, "scan")
    scan_lm = load_landmarks(scan_landmarks_path, expected=68)
    if scan_lm.shape[1] != 3:
        raise InputError(f"scan landmark file {scan_landmarks_path} holds 2-D points; the face "
                         "region needs 3-D landmarks in the scan's frame")
    mesh_lm = None
    if mesh_landmarks_path is not None:
        mesh_lm = load_landmarks(mesh_landmarks_path, expected=68)
        if mesh_lm.shape[1] != 3:
            raise InputError(f"mesh landmark file {mesh_landmarks_path} holds 2-D points; "
                             "alignment needs 3-D landmarks in the mesh's frame")
    return {p: score(mesh.vertices, mesh.faces, scan.vertices, scan.faces, scan_lm, mesh_lm,
                     protocol=p, config=config)
            for p in dict.fromkeys(protocols)}


# --------------------------------------------------------------------------- figures

_VIEW_DIRS = {  # direction from the centre to the camera, in the data convention
    "front": np.array([0.0, 0.0, 1.0]),
    "left": np.array([1.0, 0.0, 0.0]),  # the subject's left profile
    "right": np.array([-1.0, 0.0, 0.0]),
}


_GREY = 0.62
"""Albedo of what has no colour of its own in a render (no value, no vertex colour)."""


def render_views(vertices: np.ndarray, faces: np.ndarray, albedo, framed: np.ndarray,
                 views: Sequence[str] = ("front", "left", "right"), size: int = 480,
                 centre: np.ndarray | None = None) -> np.ndarray:
    """Shaded renders of a mesh, one ``size``×``size`` pinhole view per entry of ``views``
    ("front" looks along -z at the face, "left"/"right" are the subject's profiles from
    +x/-x), side by side on white (BGR uint8).

    ``albedo(triangle, bary)`` gives the BGR colour (0..1) of each hit pixel; the views frame
    ``framed`` (the points that matter, e.g. the face) and what lies near them (the rest of a
    head, not the shoulders of a bust), around ``centre`` (default: their bounding-box
    centre, so that profiles are centred too). Lambert shading from a headlight."""
    v = np.asarray(vertices, float)
    f = np.asarray(faces, np.int64)
    unknown = [name for name in views if name not in _VIEW_DIRS]
    if unknown or not views:
        raise ValueError(f"unknown view(s) {unknown}; use {', '.join(_VIEW_DIRS)}")
    if centre is None:
        mid = (framed.min(0) + framed.max(0)) / 2.0
        reach = 1.6 * float(np.max(np.linalg.norm(framed - mid, axis=1)))
        near = v[np.linalg.norm(v - mid, axis=1) <= reach]
        centre = (near.min(0) + near.max(0)) / 2.0
    centre = np.asarray(centre, float).reshape(3)
    near = v[np.linalg.norm(v - centre, axis=1) <= 1.6 * float(
        np.max(np.linalg.norm(framed - centre, axis=1)))]
    extent = float(np.max(np.linalg.norm(near - centre, axis=1))) or 1.0
    half_fov = math.radians(15.0)
    distance = 1.1 * extent / math.sin(half_fov)  # the framed sphere fits with a margin
    focal = (size / 2.0) / math.tan(half_fov)
    intr = Intrinsics(size, size, focal, focal, (size - 1) / 2.0, (size - 1) / 2.0)

    scene = RaycastScene()
    scene.add(v, f)
    normals = vertex_normals(v, f)
    tiles = []
    for name in views:
        eye = centre + distance * _VIEW_DIRS[name]
        R, t = look_at(eye, centre, np.array([0.0, 1.0, 0.0]))
        hits = scene.cast_camera(intr, R, t)
        img = np.ones((size, size, 3))  # white background
        ok = hits.valid
        if np.any(ok):
            tri, bary = hits.triangle[ok], hits.bary[ok]
            n = interpolate(normals, f, tri, bary)
            n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
            to_cam = eye - hits.points[ok]
            to_cam /= np.maximum(np.linalg.norm(to_cam, axis=1, keepdims=True), 1e-12)
            img[ok] = shade_lambert(albedo(tri, bary), n, to_cam, [(_VIEW_DIRS[name], 0.7)],
                                    ambient=0.35)
        tiles.append(np.clip(img * 255.0, 0, 255).astype(np.uint8))
    return np.concatenate(tiles, axis=1)


def _write_png(image: np.ndarray, out_png: str | Path) -> Path:
    out = Path(out_png)
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        written = cv2.imwrite(str(out), image)
    except cv2.error:  # OpenCV knows no writer for the suffix
        written = False
    if not written:
        raise InputError(f"could not write {out} (is the folder writable, the suffix .png?)")
    return out


def error_heatmap(vertices: np.ndarray, faces: np.ndarray, per_vertex_mm: np.ndarray,
                  out_png: str | Path, max_mm: float = 5.0,
                  views: Sequence[str] = ("front", "left", "right"), size: int = 480,
                  centre: np.ndarray | None = None) -> Path:
    """Render per-vertex errors on the mesh as a turbo heat map; writes one PNG, returns it.

    The views of :func:`render_views`, framing the vertices that have a value. Errors are
    coloured 0..``max_mm`` with OpenCV's TURBO map, nan (outside the region) in grey, with a
    colour bar labelled "0 mm" / f"{max_mm} mm".
    """
    v = np.asarray(vertices, float)
    f = np.asarray(faces, np.int64)
    e = np.asarray(per_vertex_mm, float).reshape(-1)
    if len(e) != len(v):
        raise ValueError(f"per_vertex_mm has {len(e)} values for {len(v)} vertices")
    lut = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None],
                            cv2.COLORMAP_TURBO)[:, 0, :] / 255.0  # BGR
    grey = np.full(3, _GREY)

    def albedo(tri, bary):
        err = interpolate(e[:, None], f, tri, bary)[:, 0]  # nan if any corner is nan
        idx = np.clip(np.nan_to_num(err / max_mm, nan=0.0), 0.0, 1.0)
        return np.where(np.isfinite(err)[:, None], lut[np.round(idx * 255).astype(int)], grey)

    framed = v[np.isfinite(e)] if np.any(np.isfinite(e)) else v
    views_img = render_views(v, f, albedo, framed, views, size, centre)
    width = views_img.shape[1]
    bar = np.full((COLORBAR_HEIGHT, width, 3), 255, np.uint8)
    x0, x1 = 90, max(width - 110, 100)
    ramp = np.linspace(0, 255, x1 - x0).round().astype(np.uint8)[None, :]
    bar[15:35, x0:x1] = cv2.applyColorMap(np.repeat(ramp, 20, axis=0), cv2.COLORMAP_TURBO)
    font = cv2.FONT_HERSHEY_SIMPLEX
    cv2.putText(bar, "0 mm", (10, 31), font, 0.55, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(bar, f"{max_mm} mm", (x1 + 8, 31), font, 0.55, (0, 0, 0), 1, cv2.LINE_AA)
    return _write_png(np.concatenate([views_img, bar], axis=0), out_png)


def mesh_render(vertices: np.ndarray, faces: np.ndarray, out_png: str | Path,
                vertex_colours: np.ndarray | None = None,
                views: Sequence[str] = ("front", "left", "right"), size: int = 480,
                framed: np.ndarray | None = None) -> Path:
    """The mesh in its vertex colours (RGB 0..255; grey without), in the views of
    :func:`render_views` framing ``framed`` (default: every vertex); writes one PNG."""
    v = np.asarray(vertices, float)
    f = np.asarray(faces, np.int64)
    if vertex_colours is None:
        bgr = np.full((len(v), 3), _GREY)
    else:
        bgr = np.asarray(vertex_colours, float)[:, 2::-1] / 255.0
    image = render_views(v, f, lambda tri, bary: interpolate(bgr, f, tri, bary),
                         v if framed is None else framed, views, size)
    return _write_png(image, out_png)


def paper_table(rows: Sequence[tuple[str, Sequence[dict]]]) -> str:
    """A Markdown table in the layout of Agrawal et al. 2020, Table 1.

    ``rows`` are ``(method name, [per-capture record from score_json, ...])``. Per method and
    side, *mean* is the mean over captures of the per-capture mean, *std* the (population)
    standard deviation over captures of the per-capture mean (0 for one capture), and *median*
    the mean over captures of the per-capture median — the paper averages per-subject figures
    over subjects. Values in mm with two decimals; the convention is repeated as a footnote.
    """
    lines = ["| Method | Captures | Accuracy mean | std | median | Completion mean | std | median |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for name, records in rows:
        cells = [str(name).replace("|", "\\|"), str(len(records))]
        for side in ("accuracy", "completion"):
            means = np.array([r[side]["mean"] for r in records], float)
            medians = np.array([r[side]["median"] for r in records], float)
            if len(records) == 0:
                cells += ["–"] * 3
            else:
                cells += [f"{means.mean():.2f}", f"{means.std():.2f}", f"{medians.mean():.2f}"]
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "Distances in mm. Mean: mean over captures of the per-capture mean; std: "
              "standard deviation over captures of the per-capture mean (0 for one capture); "
              "median: mean over captures of the per-capture median."]
    return "\n".join(lines)


def find_file(folder: str | Path, suffixes: Sequence[str], what: str) -> Path:
    """The single file in ``folder`` with one of ``suffixes`` (an input artifact's file)."""
    found = sorted(p for p in Path(folder).iterdir()
                   if p.is_file() and p.suffix.lower() in suffixes and p.name != "manifest.json")
    if not found:
        raise InputError(f"no {what} ({'/'.join(suffixes)}) in {folder}")
    return found[0]


def evaluate_stage(mesh_dir: str | Path, scan_dir: str | Path, out_dir: str | Path,
                   scan_landmarks: str | Path | None = None,
                   config: EvaluationConfig | None = None) -> Path:
    """Score the fitting stage's ``mesh.ply`` against a scan; writes ``evaluation.json``
    (:func:`score_json` per protocol) and ``heatmap_<protocol>.png``; returns the JSON."""
    import json

    from facecap_core.fitting.run import MESH_PLY

    mesh_path = Path(mesh_dir) / MESH_PLY
    scan_path = find_file(scan_dir, (".ply", ".obj", ".stl", ".off"), "scan mesh")
    lm_path = (find_file(scan_landmarks, (".json", ".ljson", ".txt", ".pts"), "scan landmarks")
               if scan_landmarks is not None else None)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    mesh = load_mesh(mesh_path, "mesh")
    mesh_lm = Path(mesh_dir) / "landmarks.json"
    if not mesh_lm.is_file():
        # A mesh in template topology carries its landmarks: the template's landmark vertices.
        from facecap_core.meshio import save_landmarks
        from facecap_core.template import Template

        template = Template.default()
        if len(mesh.vertices) == len(template.vertices):
            mesh_lm = save_landmarks(out / "mesh_landmarks.json",
                                     mesh.vertices[template.landmarks])
    scores = evaluate(mesh_path, scan_path, lm_path, mesh_lm if mesh_lm.is_file() else None,
                      config=config)
    for name, sc in scores.items():
        error_heatmap(sc.alignment.apply(mesh.vertices), mesh.faces, sc.accuracy_per_vertex,
                      out / f"heatmap_{name}.png")
    path = out / EVALUATION_JSON
    path.write_text(json.dumps({p: score_json(s) for p, s in scores.items()}, indent=1))
    return path
