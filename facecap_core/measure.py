"""Distances on the fitted face: along the straight line and along the surface, in mm, with
the metric scale's uncertainty, between two vertices or between two of the 68 landmarks.

The surface distance is the shortest path over the mesh found on a graph of its vertices and
:data:`STEINER` points on each edge, every node joined to those on the faces it touches
(Lanthier et al.'s Steiner graph), then straightened: each point of the path that lies inside
an edge slides along it to where the path is shortest (the path keeps crossing the same
edges, so it stays on the surface). The figure is the length of a path on the mesh: never
under the true geodesic, never under the straight line; on a plane it is the straight line
within 0.1 %. The results page (``pages/viewer/viewer.js``) does the same for two clicks.

The metric scale's uncertainty (``report.json`` ``figures.scale.sigma_pct``, 1σ) scales every
distance alike: a distance ``d`` is stated ``d ± d·σ``. An anatomical preset (the distance
between two of the 68 landmarks) also carries where the fit put the two landmark vertices
against the true landmarks: its ``anatomical`` figure is the mesh's distance less that
placement's bias, ± the scale's and the placement's spread in quadrature (:data:`PLACEMENT`).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra

STEINER = 3
"""Points on each edge, besides its ends, in the surface path's graph."""
RELAX_SWEEPS = 400
"""Sweeps of the straightening (each moves every inner point, odd then even ones)."""
GOLDEN_STEPS = 30
"""Golden-section steps a point takes along its edge per sweep (its place to 1e-6 of it)."""

PRESETS = (
    ("outer_eyes", "Outer eye corners", 36, 45),
    ("inner_eyes", "Inner eye corners", 39, 42),
    ("nose_width", "Nose width", 31, 35),
    ("mouth_width", "Mouth width", 48, 54),
    ("nose_length", "Nose length", 27, 33),
    ("face_height", "Face height", 27, 8),
)
"""(key, name, landmark, landmark) of the anatomical measurements: iBUG 68-point indices
(0-based): the eyes' outer and inner corners, the nostrils' wings, the mouth's corners, the
nasion to the nose's base (subnasale), the nasion to the chin."""


PLACEMENT = {
    "outer_eyes": (2.94, 4.26), "inner_eyes": (-0.72, 1.63), "nose_width": (7.75, 1.2),
    "mouth_width": (-2.27, 2.37), "nose_length": (-2.88, 1.73), "face_height": (0.45, 2.59),
}
"""Per preset, (bias, spread) in mm of the fitted mesh's distance between the two landmark
vertices at the true scale less the true landmarks' distance: its mean, and the spread of
a new capture's about it (standard deviation × sqrt(1 + 1/n)), over the n calibration
captures of ``benchmarks/bench_measure.py --calibrate`` (ICT identities 101-106: three clean
1280×720 and three phone-like 512×512 sweeps; the truth is the renderer's landmarks).
Held-out captures are reported in ``docs/results_page.md``."""


def _edges(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mesh's edges (E, 2: lower vertex id first) and each face's three edge ids
    (F, 3: the edges opposite nothing; edge k of a face joins its vertices k and k+1)."""
    pairs = np.stack([faces, np.roll(faces, -1, axis=1)], axis=2).reshape(-1, 2)
    pairs = np.sort(pairs, axis=1)
    # One integer key per edge, in the rows' lexicographic order: np.unique over rows is
    # several times slower.
    n = int(pairs.max()) + 1 if len(pairs) else 1
    keys, inverse = np.unique(pairs[:, 0] * n + pairs[:, 1], return_inverse=True)
    return np.column_stack([keys // n, keys % n]), inverse.reshape(-1, 3)


class SurfacePaths:
    """Shortest paths over one mesh's surface (vertices in mm, faces as vertex ids)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, steiner: int = STEINER):
        self.vertices = np.asarray(vertices, float)
        self.faces = np.asarray(faces, np.int64)
        self.m = steiner
        self.edges, self.face_edges = _edges(self.faces)
        a, b = self.edges.T
        lengths = np.linalg.norm(self.vertices[a] - self.vertices[b], axis=1)
        n = len(self.vertices)
        self.vertex_graph = sp.coo_matrix((np.r_[lengths, lengths], (np.r_[a, b], np.r_[b, a])),
                                          shape=(n, n)).tocsr()
        self.longest_edge = float(lengths.max()) if len(lengths) else 0.0

    # -- nodes of the Steiner graph: vertex v is node v; point k of edge e is V + e*m + k ----
    def _face_nodes(self, faces: np.ndarray) -> np.ndarray:
        """(F, 3 + 3m) node ids on each face's boundary."""
        n, m = len(self.vertices), self.m
        steiner = (n + self.face_edges[faces][:, :, None] * m + np.arange(m)).reshape(len(faces), -1)
        return np.concatenate([self.faces[faces], steiner], axis=1)

    def _node_points(self, nodes: np.ndarray) -> np.ndarray:
        n, m = len(self.vertices), self.m
        nodes = np.asarray(nodes)
        points = np.empty((len(nodes), 3))
        is_vertex = nodes < n
        points[is_vertex] = self.vertices[nodes[is_vertex]]
        e, k = np.divmod(nodes[~is_vertex] - n, m)
        t = (k + 1) / (m + 1)
        u, v = self.edges[e].T
        points[~is_vertex] = self.vertices[u] + t[:, None] * (self.vertices[v] - self.vertices[u])
        return points

    def path(self, a: int, b: int) -> tuple[float, np.ndarray]:
        """(length in mm, points of the path) along the surface from vertex ``a`` to ``b``."""
        if a == b:
            return 0.0, self.vertices[[a]]
        # The path over the edges bounds the geodesic: it lies in the ellipsoid of the points
        # whose distances to a and b sum to no more, which is the graph's region.
        bound = float(dijkstra(self.vertex_graph, indices=a)[b])
        if not math.isfinite(bound):
            return math.inf, self.vertices[[a, b]]
        reach = (np.linalg.norm(self.vertices - self.vertices[a], axis=1)
                 + np.linalg.norm(self.vertices - self.vertices[b], axis=1))
        near = reach <= bound + 2 * self.longest_edge
        faces = np.flatnonzero(near[self.faces].any(axis=1))
        nodes_of = self._face_nodes(faces)
        ids, local = np.unique(nodes_of, return_inverse=True)
        local = local.reshape(nodes_of.shape)
        points = self._node_points(ids)
        k = nodes_of.shape[1]
        i, j = np.triu_indices(k, 1)
        rows, cols = local[:, i].ravel(), local[:, j].ravel()
        # The path passes no vertex but its ends: every point inside it lies on an edge,
        # where the straightening can slide it (to the edge's end, if that is shortest).
        ends = np.isin(ids, (a, b)) | (ids >= len(self.vertices))
        keep = ends[rows] & ends[cols]
        rows, cols = rows[keep], cols[keep]
        # The pattern first (an edge two faces share appears twice), then each edge's length.
        graph = sp.coo_matrix((np.ones(2 * len(rows)), (np.r_[rows, cols], np.r_[cols, rows])),
                              shape=(len(ids), len(ids))).tocsr()
        graph.data[:] = np.linalg.norm(points[np.repeat(np.arange(len(ids)),
                                                         np.diff(graph.indptr))]
                                       - points[graph.indices], axis=1)
        start, end = int(np.searchsorted(ids, a)), int(np.searchsorted(ids, b))
        _, before = dijkstra(graph, indices=start, return_predecessors=True)
        chain = [end]
        while chain[-1] != start:
            chain.append(int(before[chain[-1]]))
        nodes = ids[np.array(chain[::-1])]
        pts = straighten(self.vertices, self.edges, nodes, len(self.vertices), self.m)
        return float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum()), pts


def straighten(vertices: np.ndarray, edges: np.ndarray, nodes: np.ndarray, n: int, m: int,
               sweeps: int = RELAX_SWEEPS) -> np.ndarray:
    """The path through ``nodes`` with each point inside an edge slid along that edge to
    where the path is shortest (vertices stay): odd points, then even ones, each by golden
    section on its edge with its neighbours held."""
    nodes = np.asarray(nodes)
    inner = nodes >= n
    e, k = np.divmod(np.where(inner, nodes - n, 0), m)
    t = np.where(inner, (k + 1) / (m + 1), 0.0)
    u = np.where(inner, edges[e, 0], nodes)
    v = np.where(inner, edges[e, 1], nodes)
    start, step = vertices[u], vertices[v] - vertices[u]
    start, step = np.ascontiguousarray(start, float), np.ascontiguousarray(step, float)
    inner = np.ascontiguousarray(inner)
    length = math.inf
    for _ in range(sweeps):
        _sweep(start, step, t, inner, GOLDEN_STEPS)
        p = start + t[:, None] * step
        shorter = float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())
        if shorter > length * (1 - 1e-7):
            break
        length = shorter
    return start + t[:, None] * step


@numba.njit(nogil=True, cache=True)
def _sweep(start, step, t, inner, golden_steps):
    """One sweep of :func:`straighten`, in place on ``t``: every inner point of odd index,
    then of even index, slid by golden section along its edge (``start + t step``) to where
    the sum of its distances to its two neighbours is least. Points of one parity do not
    neighbour each other, so each one's neighbours are those of the sweep's start or of the
    parity before. No fastmath: the figures are the float operations numpy makes, in
    numpy's order (a norm's squares summed left to right)."""
    ratio = (math.sqrt(5.0) - 1.0) / 2.0
    for first in (1, 2):
        for i in range(first, len(t) - 1, 2):
            if not inner[i]:
                continue
            prev = np.empty(3)
            nxt = np.empty(3)
            for c in range(3):
                prev[c] = start[i - 1, c] + t[i - 1] * step[i - 1, c]
                nxt[c] = start[i + 1, c] + t[i + 1] * step[i + 1, c]
            lo, hi = 0.0, 1.0
            for _ in range(golden_steps):
                d = ratio * (hi - lo)
                x1, x2 = hi - d, lo + d
                if _detour(start[i], step[i], x1, prev, nxt) < \
                        _detour(start[i], step[i], x2, prev, nxt):
                    hi = x2
                else:
                    lo = x1
            t[i] = (lo + hi) / 2


@numba.njit(nogil=True, cache=True, inline="always")
def _detour(s0, s1, x, prev, nxt):
    """|q - prev| + |q - nxt| for the point q = s0 + x s1."""
    a2 = 0.0
    b2 = 0.0
    for c in range(3):
        q = s0[c] + x * s1[c]
        a2 += (q - prev[c]) * (q - prev[c])
        b2 += (q - nxt[c]) * (q - nxt[c])
    return math.sqrt(a2) + math.sqrt(b2)


def with_sigma(mm: float, sigma_pct: float | None) -> dict:
    """``{"mm", "sigma_mm"}`` of a distance under the metric scale's 1σ (None: unknown)."""
    return {"mm": round(mm, 3),
            "sigma_mm": round(mm * sigma_pct / 100, 3) if sigma_pct is not None else None}


def measure(paths: SurfacePaths, a: int, b: int, sigma_pct: float | None) -> dict:
    """The distance from vertex ``a`` to ``b``: straight and along the surface, each with its
    1σ from the metric scale."""
    straight = float(np.linalg.norm(paths.vertices[a] - paths.vertices[b]))
    surface, _ = paths.path(a, b)
    return {"vertices": [int(a), int(b)], "straight": with_sigma(straight, sigma_pct),
            "surface": with_sigma(max(surface, straight), sigma_pct), "sigma_pct": sigma_pct}


def landmark_measurements(vertices: np.ndarray, faces: np.ndarray, landmark_ids,
                          sigma_pct: float | None) -> dict:
    """:data:`PRESETS` on a mesh whose 68 landmarks are the vertices ``landmark_ids``: key ->
    ``{"name", "landmarks", "vertices", "straight": {"mm", "sigma_mm"}, "surface": ...,
    "sigma_pct"}``."""
    paths = SurfacePaths(vertices, faces)
    ids = np.asarray(landmark_ids, np.int64)
    return {key: {"name": name, "landmarks": [i, j],
                  **measure(paths, int(ids[i]), int(ids[j]), sigma_pct)}
            for key, name, i, j in PRESETS}


def anatomical(key: str, straight_mm: float, sigma_pct: float | None) -> dict:
    """``{"mm", "sigma_mm"}`` of preset ``key``'s anatomical distance from the mesh's straight
    distance between its landmark vertices: less the placement's bias, ± the metric scale's
    1σ and the placement's spread in quadrature (:data:`PLACEMENT`; None: the scale's σ is
    unknown)."""
    bias, spread = PLACEMENT[key]
    sigma = None if sigma_pct is None else math.hypot(straight_mm * sigma_pct / 100, spread)
    return {"mm": round(straight_mm - bias, 3),
            "sigma_mm": None if sigma is None else round(sigma, 3)}


def under_scale(measurements: dict, sigma_pct: float | None) -> dict:
    """The fitting stage's ``measurements`` (made with the mesh, :func:`landmark_measurements`)
    with the metric scale's 1σ, ``sigma_pct`` (the coarse stage's), and each preset's
    :func:`anatomical` figure."""
    return {key: {**m, "sigma_pct": sigma_pct,
                  **{side: with_sigma(m[side]["mm"], sigma_pct)
                     for side in ("straight", "surface")},
                  **({"anatomical": anatomical(key, m["straight"]["mm"], sigma_pct)}
                     if key in PLACEMENT else {})}
            for key, m in measurements.items()}


def summary(measurements: dict) -> str:
    """The measurements in words: ``Outer eye corners 95.2 mm ± 5.8 mm (between its
    landmark vertices 98.1 mm straight, 104.2 mm along the surface); ...``: each preset's
    anatomical figure (1σ: the metric scale's and the landmarks' placement; no ± when the
    scale's is unknown), or its straight one ± the scale's 1σ in a report without it."""
    said = []
    for m in measurements.values():
        if not isinstance(m, dict) or not isinstance(m.get("straight"), dict):
            continue
        stated = m.get("anatomical") if isinstance(m.get("anatomical"), dict) else m["straight"]
        said.append(f"{m.get('name', '?')} {distance_text(stated)} (between its landmark "
                    f"vertices {_number(m['straight'].get('mm'))} mm straight, "
                    f"{_number(m.get('surface', {}).get('mm'))} mm along the surface)")
    return "; ".join(said)


def _number(value) -> str:
    if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value):
        return "–"
    return f"{value:.1f}"


def distance_text(d: dict, sigma_pct: float | None = None) -> str:
    """``63.2 mm ± 2.5 mm`` (``d`` as :func:`with_sigma` gives it; with ``sigma_pct``, ``(±4.0
    %, 1σ)`` after it)."""
    text = f"{_number(d.get('mm'))} mm"
    if d.get("sigma_mm") is not None:
        text += f" ± {_number(d['sigma_mm'])} mm"
        if sigma_pct is not None:
            text += f" (±{sigma_pct:.1f} %, 1σ)"
    return text
