"""Bringing a reconstruction into the scan's frame: landmark initialisation, then trimmed
point-to-surface ICP under the similarity or metric protocol."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.spatial.transform import Rotation

from facecap_core.errors import InputError
from facecap_core.evaluation.region import check_landmarks, region_sphere
from facecap_core.evaluation.settings import EvaluationConfig
from facecap_core.geometry import umeyama
from facecap_core.lazy import LazyModule
from facecap_core.template import INNER_LANDMARKS

o3d = LazyModule("open3d")

Protocol = Literal["similarity", "metric"]
PROTOCOLS: tuple[str, ...] = ("similarity", "metric")


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


class Surface:
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
    return Surface(vertices, faces).closest(points)[1]


MAX_LOG_SCALE = 20.0
"""Largest |log scale| an extrapolated ICP transform may have (a factor of 5e8): beyond it
the extrapolation, not the data, is speaking."""


def _params(s: float, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(log s, rotation vector, t): a flat vector in which transforms can be extrapolated."""
    return np.concatenate([[math.log(s)], Rotation.from_matrix(R).as_rotvec(), t])


def _transform(x: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    return math.exp(x[0]), Rotation.from_rotvec(x[1:4]).as_matrix(), x[4:7].copy()


def align_to_surface(mesh_vertices: np.ndarray, scan: Surface, scan_landmarks: np.ndarray,
           mesh_landmarks: np.ndarray | None, with_scale: bool,
           config: EvaluationConfig) -> Alignment:
    # Long on purpose: the alignment protocol step by step (landmarks, then ICP in the region), as
    # docs/evaluation.md lists it.
    mv = np.asarray(mesh_vertices, float)
    centre, radius = region_sphere(scan_landmarks, config.radius_factor)
    radius_icp = radius * config.icp_margin

    if mesh_landmarks is not None and config.use_landmarks:
        ml = check_landmarks(mesh_landmarks, "mesh")
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
    scan_lm = check_landmarks(scan_landmarks, "scan")
    return align_to_surface(mesh_vertices, Surface(scan_vertices, scan_faces), scan_lm, mesh_landmarks,
                  with_scale, config)
