"""Checks that a fitted mesh is a sane deformation of its template.

A fit shares the template's topology, so each triangle and each edge can be compared with
its own template counterpart once the template is moved onto the fit by a similarity
(least squares over all vertices):

- **flipped**: a triangle whose normal points against its template triangle's normal (the
  surface folded over itself there);
- **stretched**: an edge longer than ``max_stretch`` times its template length (a spike);
- **self-intersections**: pairs of triangles that cut through each other (an edge of one
  crosses the other) and do not in the template.
"""

from __future__ import annotations

import threading
from dataclasses import asdict, dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from facecap_core.geometry import umeyama
from facecap_core.lazy import LazyModule
from facecap_core.nonrigid.solver import edges_of

o3d = LazyModule("open3d")

MAX_EDGE_STRETCH = 3.0
"""An edge beyond this many times its (similarity-scaled) template length counts as
stretched: the fit's smooth deformations (landmark pulls, cloud attraction) change edge
lengths by tens of percent, a torn region by many times."""
INTERSECTION_ROUNDS = 8
"""Self-intersections are relaxed over a neighbourhood 2 rings wider each round: lips
pressed into each other need about 8 rings (4 rounds) on the demo capture."""


@dataclass
class MeshSanity:
    triangles: int
    flipped: int
    degenerate: int  # triangles of (near) zero area in the fit
    stretched_edges: int
    max_edge_stretch: float
    self_intersecting_pairs: int

    @property
    def ok(self) -> bool:
        return not (self.flipped or self.stretched_edges or self.self_intersecting_pairs)

    def to_json(self) -> dict:
        return {**asdict(self), "max_edge_stretch": round(self.max_edge_stretch, 3),
                "stretch_bound": MAX_EDGE_STRETCH, "ok": self.ok}


def _normals(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    v = vertices[faces]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    area2 = np.linalg.norm(n, axis=1)
    return n / np.maximum(area2, 1e-300)[:, None], area2


def self_intersecting_pairs(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(P, 2) indices (sorted, unique) of the triangle pairs that cut through each other
    (sharing a vertex or an edge is not an intersection); read-only.

    The last meshes' answers are kept: the fit's check after the relaxation asks again
    about the mesh the relaxation's last check found sound.
    """
    v = np.asarray(vertices, float)
    f = np.asarray(faces, np.int64)
    # The layout is part of the key: the centroid's sum runs in memory order.
    key = (v.shape, v.strides, v.tobytes(order="A"), f.shape, f.tobytes())
    with _PAIRS_LOCK:
        found = _PAIRS.get(key)
    if found is None:
        found = _self_intersecting_pairs(v, f)
        with _PAIRS_LOCK:  # fits in threads of one process share the answers
            _PAIRS[key] = found
            while len(_PAIRS) > PAIRS_KEPT:
                del _PAIRS[next(iter(_PAIRS))]
    return found


PAIRS_KEPT = 2
"""Meshes whose self-intersecting pairs :func:`self_intersecting_pairs` keeps."""
_PAIRS: dict[tuple, np.ndarray] = {}
_PAIRS_LOCK = threading.Lock()


def _self_intersecting_pairs(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """:func:`self_intersecting_pairs`, worked out.

    Two triangles in general position intersect when an edge of one crosses the other: every
    edge is cast as a segment through a bounding-volume hierarchy of the triangles (open3d's
    ray casting, float32 about the centroid: 1e-5 mm on a head), and each crossing pairs the
    crossed triangle with the triangles that hold the edge. Coplanar overlaps are not seen.
    """
    centre = v.mean(0)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor((v - centre).astype(np.float32)),
                        o3d.core.Tensor(f.astype(np.uint32)))
    edges = edges_of(f)
    start, end = v[edges[:, 0]] - centre, v[edges[:, 1]] - centre
    hits = scene.list_intersections(o3d.core.Tensor(
        np.concatenate([start, end - start], 1).astype(np.float32)))
    t_hit = hits["t_hit"].numpy()
    inside = (t_hit > 1e-6) & (t_hit < 1 - 1e-6)  # not at the edge's own end points
    edge = edges[hits["ray_ids"].numpy()[inside]]
    crossed = hits["primitive_ids"].numpy()[inside].astype(np.int64)
    # The triangles that hold each crossing edge (one or two).
    corner_edges = np.sort(f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    keys = corner_edges[:, 0] * len(v) + corner_edges[:, 1]
    order = np.argsort(keys)
    keys, holder = keys[order], np.repeat(np.arange(len(f)), 3)[order]
    query = edge[:, 0] * len(v) + edge[:, 1]
    lo, hi = np.searchsorted(keys, query, "left"), np.searchsorted(keys, query, "right")
    count = hi - lo
    rows = np.repeat(np.arange(len(edge)), count)
    # lo[r], lo[r] + 1, ..., hi[r] - 1 for each crossing r in turn.
    held = holder[np.arange(len(rows)) - np.repeat(np.cumsum(count) - count - lo, count)]
    pairs = np.sort(np.column_stack([held, crossed[rows]]), axis=1)
    shared = (f[pairs[:, 0]][:, :, None] == f[pairs[:, 1]][:, None, :]).any(axis=(1, 2))
    found = np.unique(pairs[~shared], axis=0).reshape(-1, 2)
    found.flags.writeable = False  # shared by every caller
    return found


def new_intersecting_pairs(vertices: np.ndarray, faces: np.ndarray,
                           template_vertices: np.ndarray) -> np.ndarray:
    """The intersecting triangle pairs of the fit that do not intersect in the template (a
    template may intersect itself by design, e.g. where the lips or an ear fold meet)."""
    pairs = self_intersecting_pairs(vertices, faces)
    if not len(pairs):
        return pairs
    # Test the template only on the triangles involved: a few, not the whole mesh.
    involved = np.unique(pairs)
    local = self_intersecting_pairs(template_vertices, faces[involved])
    in_template = {tuple(p) for p in np.sort(involved[local], axis=1).tolist()}
    return pairs[np.array([tuple(p) not in in_template for p in pairs.tolist()], bool)]


@dataclass
class _Comparison:
    """A fit's triangles and edges against the similarity-moved template's."""

    flipped: np.ndarray  # per triangle
    degenerate: np.ndarray  # per triangle
    stretch: np.ndarray  # per edge of the reference: fit length / template length


@dataclass
class _Reference:
    """The similarity-moved template's triangles and edges, which every comparison of a fit
    with it reads (computed once per move, not once per comparison)."""

    faces: np.ndarray
    edges: np.ndarray  # (E, 2)
    normals: np.ndarray  # per triangle, unit
    area_bound: float  # a triangle of at most this (doubled) area is degenerate
    valid: np.ndarray  # per triangle: the template's is not degenerate
    lengths: np.ndarray  # per edge, at least 1e-12


def _reference(moved: np.ndarray, faces: np.ndarray, edges: np.ndarray) -> _Reference:
    normals, area = _normals(moved, faces)
    bound = 1e-9 * np.median(area)
    lengths = np.linalg.norm(moved[edges[:, 0]] - moved[edges[:, 1]], axis=1)
    return _Reference(faces, edges, normals, bound, area > bound, np.maximum(lengths, 1e-12))


def _compare(vertices: np.ndarray, ref: _Reference) -> _Comparison:
    n_fit, area_fit = _normals(vertices, ref.faces)
    degenerate = area_fit <= ref.area_bound
    flipped = ~degenerate & ref.valid & (np.einsum("ij,ij->i", n_fit, ref.normals) < 0)
    edges = ref.edges
    len_fit = np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1)
    return _Comparison(flipped, degenerate, len_fit / ref.lengths)


def _moved_template(template: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    s, R, t = umeyama(template, vertices, with_scale=True)
    return s * template @ R.T + t


def check_mesh(vertices: np.ndarray, faces: np.ndarray, template_vertices: np.ndarray,
               max_stretch: float = MAX_EDGE_STRETCH) -> MeshSanity:
    """Sanity figures of a fit (``vertices``) against its template (same ``faces``)."""
    vertices = np.asarray(vertices, float)
    template = np.asarray(template_vertices, float)
    faces = np.asarray(faces, np.int64)
    c = _compare(vertices, _reference(_moved_template(template, vertices), faces,
                                      edges_of(faces)))
    return MeshSanity(triangles=len(faces), flipped=int(c.flipped.sum()),
                      degenerate=int(c.degenerate.sum()),
                      stretched_edges=int((c.stretch > max_stretch).sum()),
                      max_edge_stretch=float(c.stretch.max()) if len(c.stretch) else 0.0,
                      self_intersecting_pairs=len(new_intersecting_pairs(vertices, faces,
                                                                         template)))


def _adjacency(faces: np.ndarray, n: int):
    """Row-normalised vertex adjacency (sparse): A @ x averages x over each one-ring."""

    e = edges_of(faces)
    A = sp.coo_matrix((np.ones(2 * len(e)), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])),
                      shape=(n, n)).tocsr()
    degree = np.asarray(A.sum(1)).ravel()
    return sp.diags(1.0 / np.maximum(degree, 1)) @ A


def _bad_faces(vertices, ref: _Reference, max_stretch) -> np.ndarray:
    """Triangles that are flipped or degenerate, or touch a stretched edge."""
    c = _compare(vertices, ref)
    stretched = np.zeros(len(vertices), bool)
    stretched[ref.edges[c.stretch > max_stretch].ravel()] = True
    return c.flipped | c.degenerate | stretched[ref.faces].any(1)


def relax_folds(vertices: np.ndarray, faces: np.ndarray, template_vertices: np.ndarray,
                max_stretch: float = MAX_EDGE_STRETCH, rounds: int = 16,
                check_intersections: bool = True) -> tuple[np.ndarray, dict]:
    """Undo folds, spikes and self-intersections of a fit where they are: around each bad
    triangle the deformation (fit minus the similarity-moved template) is replaced by a
    membrane (each vertex's deformation the mean of its neighbours', the vertices around
    held), over a neighbourhood that widens by a ring each round the triangle stays bad; a
    sliver still folded after that is moved with its template triangle. Elsewhere the fit
    is untouched. Returns the vertices and what was done."""

    V = np.asarray(vertices, float).copy()
    T = np.asarray(template_vertices, float)
    faces = np.asarray(faces, np.int64)
    moved = _moved_template(T, V)
    A = _adjacency(faces, len(V))
    edges = edges_of(faces)
    ref = _reference(moved, faces, edges)
    region = np.zeros(len(V), bool)

    def relax(bad_faces: np.ndarray, rings: int) -> None:
        nonlocal region
        seed = np.zeros(len(V), bool)
        seed[faces[bad_faces].ravel()] = True
        for _ in range(rings):
            seed |= (A @ seed.astype(float)) > 0
        region |= seed
        inside, outside = np.flatnonzero(region), np.flatnonzero(~region)
        D = V - moved
        L = sp.identity(len(inside), format="csc") - A[inside][:, inside].tocsc()
        V[inside] = moved[inside] + spla.splu(L).solve(A[inside][:, outside] @ D[outside])

    def snap() -> int:
        """A sliver that the membrane still folds (its height a tenth of a millimetre) gets
        one deformation for its three corners, their mean: it is then its template triangle
        moved, never flipped."""
        count = 0
        for _ in range(4):
            c = _compare(V, ref)
            bad = np.flatnonzero(c.flipped | c.degenerate)
            if not len(bad):
                break
            for f in faces[bad]:
                V[f] = moved[f] + (V[f] - moved[f]).mean(0)
            count += len(bad)
        return count

    steps = snapped = 0
    last = INTERSECTION_ROUNDS if check_intersections else 0
    for sweep in range(3):
        if sweep:
            # The template's similarity onto the relaxed fit has moved a little, so an edge
            # relaxed to just under the bound may be just over it now: another sweep.
            moved = _moved_template(T, V)
            ref = _reference(moved, faces, edges)
            if not _bad_faces(V, ref, max_stretch).any():
                break
        for attempt in range(last + 1):
            for r in range(rounds):
                bad = _bad_faces(V, ref, max_stretch)
                if not bad.any():
                    break
                relax(bad, min(r + 1, 12))
                steps += 1
            snapped += snap()
            if attempt == last:
                break
            pairs = new_intersecting_pairs(V, faces, T)
            if not len(pairs):
                break
            bad = np.zeros(len(faces), bool)
            bad[np.unique(pairs)] = True
            relax(bad, 2 + 2 * attempt)
            steps += 1
    return V, {"relaxed_vertices": int(region.sum()), "relax_steps": steps,
               "snapped_triangles": snapped}
