"""How crinkled a fitted face is, without a reference: the bend across its edges.

Skin is smooth at the 1–2 mm scale of the template's triangles, so the angle between the
normals of two triangles that share an edge is small on a face mesh (the default template
itself: a median 1.2°, 2 % of its face edges over 20°). A mesh that carries reconstruction
noise bends at many edges: real-skin MVS noise shows as a millimetre network of ridges, with
a fifth of the face's edges bent over 20°.

The measure is taken over the face: the template's vertices within ``FACE_RADIUS_MM`` ×
(its eye-corner distance L36–L45 / ``EYE_CORNERS_MM``) of the centroid of its landmarks
17–67, and the edges both of whose triangles lie wholly inside. The region is the
template's, so it is the same set of edges on every fit of it (:func:`face_vertices` is
also the region that ``benchmarks/bench_real.py --split-half`` measures).
"""

from __future__ import annotations

import numpy as np

from facecap_core.lazy import LazyModule

trimesh = LazyModule("trimesh")

FACE_RADIUS_MM = 70.0
"""Radius of the face region on a face whose outer eye corners are ``EYE_CORNERS_MM`` apart
(forehead to chin, cheek to cheek; the ears and the neck are outside)."""
EYE_CORNERS_MM = 90.0
BENT_DEG = 20.0
"""An edge counts as bent when its two triangles' normals differ by more than this."""

__all__ = ["face_vertices", "face_edges", "bend_angles", "roughness"]


def face_vertices(vertices: np.ndarray, landmarks: np.ndarray) -> np.ndarray:
    """(n,) bool: the template's vertices in its face region (its 68 landmark vertex ids)."""
    V = np.asarray(vertices, float)
    ids = np.asarray(landmarks, np.int64)
    centre = V[ids[17:68]].mean(0)
    radius = FACE_RADIUS_MM * np.linalg.norm(V[ids[36]] - V[ids[45]]) / EYE_CORNERS_MM
    return np.linalg.norm(V - centre, axis=1) <= radius


def face_edges(vertices: np.ndarray, faces: np.ndarray, landmarks: np.ndarray) -> np.ndarray:
    """(E, 2) triangle-index pairs of the interior edges of the face region of a template
    (``vertices``, ``faces`` and its 68 landmark vertex ids)."""
    tri_inside = face_vertices(vertices, landmarks)[np.asarray(faces, np.int64)].all(1)
    # Pairs of triangles that share an edge (manifold edges: exactly two triangles).
    pairs = trimesh.Trimesh(vertices, faces, process=False).face_adjacency
    return pairs[tri_inside[pairs].all(1)]


def bend_angles(vertices: np.ndarray, faces: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Angle (degrees) between the normals of each edge's two triangles (``edges`` from
    :func:`face_edges`); a degenerate triangle's edges bend 180°."""
    v = np.asarray(vertices, float)[np.asarray(faces, np.int64)]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    norm = np.linalg.norm(n, axis=1)
    n = n / np.maximum(norm, 1e-300)[:, None]
    cos = np.einsum("ij,ij->i", n[edges[:, 0]], n[edges[:, 1]])
    cos = np.where((norm[edges[:, 0]] > 0) & (norm[edges[:, 1]] > 0), cos, -1.0)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def roughness(vertices: np.ndarray, faces: np.ndarray, edges: np.ndarray) -> dict:
    """The bend distribution over the face: share of edges bent over ``BENT_DEG`` (%), median
    and 90th percentile (degrees), and how many edges were measured."""
    angles = bend_angles(vertices, faces, edges)
    if len(angles) == 0:
        return {"edges": 0, "bent_share_pct": None, "median_bend_deg": None,
                "p90_bend_deg": None, "bent_deg": BENT_DEG}
    return {"edges": int(len(angles)),
            "bent_share_pct": round(float(np.mean(angles > BENT_DEG)) * 100, 2),
            "median_bend_deg": round(float(np.median(angles)), 2),
            "p90_bend_deg": round(float(np.percentile(angles, 90)), 2),
            "bent_deg": BENT_DEG}
