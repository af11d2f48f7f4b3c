"""How well each part of the face is supported, without a reference.

Per part of the face (:data:`PARTS`, cut once on the template's face region, so they are the
same vertices on every fit): how far the fitted mesh lies from its own fused cloud (signed:
positive where the mesh stands out of the cloud), how much of the part has cloud under it,
how noisy the cloud is there, how far the part's detected 3D landmarks lie from the cloud's surface, and
how bent its edges are. A part with little cloud under it is shaped by the template and the
landmarks, not by the capture: it says so (``supported`` false).

What it is for: a reconstruction of a real face has no scan to be scored against. A part
whose mesh stands off its cloud, whose landmarks lie off the surface, or whose cloud is noisy
or missing is where to look first; the figures go to ``fit.json`` (``parts``) and
``report.json`` (``figures.parts``).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from facecap_core.lazy import LazyModule
from facecap_core.nonrigid.constraints import CloudGrid, cloud_targets
from facecap_core.nonrigid.roughness import BENT_DEG, bend_angles
from facecap_core.render import vertex_normals
from facecap_core.template import Template, head_frame

trimesh = LazyModule("trimesh")

PARTS = ("forehead", "eyes", "nose", "cheeks", "mouth", "jaw", "ears")
"""The parts of the face reported, in the order they are shown."""
LANDMARK_PARTS = {"forehead": range(17, 27), "nose": range(27, 36), "eyes": range(36, 48),
                  "mouth": range(48, 68), "jaw": range(4, 13)}
"""The landmarks each part holds (iBUG 68): a face vertex belongs to the part of its nearest
landmark (the brows' to the forehead; the jaw contour's top four on each side to the
cheeks), unless it is far from every landmark (the cheeks) or above the brows (the
forehead)."""
CHEEK_DISTANCE = 0.3
"""A face vertex farther than this × the eye-corner distance from every landmark is cheek."""
SEARCH_MM = 3.0
"""How far along a vertex's normal its cloud points are looked for (the fit's last radius)."""
LINE_MM = 1.5
"""How far from the vertex's normal line a cloud point may lie (the fit's setting)."""
MIN_SUPPORT = 0.5
"""A part with cloud under fewer than this share of its vertices is not supported."""
LANDMARK_NEIGHBOURS = 12
"""Cloud points a landmark's distance to the surface is taken over (their tangent planes)."""

__all__ = ["PARTS", "part_masks", "part_quality"]


def part_masks(template: Template) -> dict[str, np.ndarray]:
    """(n,) bool per part of :data:`PARTS`, cut on the template's own vertices."""
    V = template.vertices
    L = template.landmark_points
    face = np.asarray(template.regions["face"], bool)
    part_of = np.full(68, "cheeks", dtype=object)
    for part, members in LANDMARK_PARTS.items():
        part_of[list(members)] = part
    distance, nearest = cKDTree(L).query(V)
    eye_corners = np.linalg.norm(L[36] - L[45])
    R, _ = head_frame(L)
    above_brows = (V @ R[1]) > (L[17:27] @ R[1]).max()
    labels = np.where(distance > CHEEK_DISTANCE * eye_corners, "cheeks",
                      part_of[nearest]).astype(object)
    labels[above_brows] = "forehead"
    masks = {part: face & (labels == part) for part in PARTS if part != "ears"}
    masks["ears"] = np.asarray(template.regions["ears"], bool)
    return masks


def _landmark_surface_distance(landmarks: np.ndarray, cloud: np.ndarray,
                               normals: np.ndarray | None) -> np.ndarray:
    """(68,) distance (mm) of each landmark from the cloud's surface: the median of its
    distances to the tangent planes of its nearest cloud points (to the points themselves
    without normals); nan for a landmark that is not finite."""
    out = np.full(len(landmarks), np.nan)
    ok = np.all(np.isfinite(landmarks), axis=1)
    if not ok.any():
        return out
    k = min(LANDMARK_NEIGHBOURS, len(cloud))
    d, nearest = cKDTree(cloud).query(landmarks[ok], k=k)
    if normals is None:
        out[ok] = np.median(np.atleast_2d(d), axis=1)
        return out
    nearest = nearest.reshape(ok.sum(), k)
    offsets = landmarks[ok][:, None, :] - cloud[nearest]
    out[ok] = np.median(np.abs(np.einsum("ijk,ijk->ij", offsets, normals[nearest])), axis=1)
    return out


def _stat(values: np.ndarray, fn, digits: int = 3) -> float | None:
    values = values[np.isfinite(values)]
    return round(float(fn(values)), digits) if len(values) else None


def part_quality(vertices: np.ndarray, template: Template, cloud: np.ndarray,
                 cloud_normals: np.ndarray | None, cloud_errors: np.ndarray | None,
                 landmarks: np.ndarray) -> dict:
    """Per part of :data:`PARTS` (see the module): ``vertices``, ``supported_share`` (of its
    vertices with cloud under them), ``supported``, ``mesh_to_cloud_mm`` (median signed
    distance, positive where the mesh stands out of the cloud) and ``mesh_to_cloud_abs_mm``
    (median and 90th percentile of its size), ``cloud_noise_mm`` (the median standard error
    of the cloud points under it, None where the cloud has none), ``landmark_to_cloud_mm``
    (median over its landmarks) and ``bent_share_pct``. Also ``landmarks_to_cloud_mm``: each
    of the 68 landmarks' distance from the cloud's surface (None where not finite)."""
    V = np.asarray(vertices, float)
    faces = template.faces
    normals = vertex_normals(V, faces)
    cloud = np.asarray(cloud, float)
    grid = CloudGrid.build(cloud, cloud_normals, SEARCH_MM, cloud_errors)
    found, targets, _, point_error = cloud_targets(V, normals, grid, SEARCH_MM, LINE_MM)
    signed = np.where(found, -np.einsum("ij,ij->i", targets - V, normals), np.nan)
    point_error = np.where(found, point_error, np.nan)
    to_cloud = _landmark_surface_distance(np.asarray(landmarks, float), cloud, cloud_normals)
    # Bend per part: the edges whose two triangles have every vertex in the part.
    pairs = trimesh.Trimesh(template.vertices, faces, process=False).face_adjacency
    angles = bend_angles(V, faces, pairs)
    parts = {}
    for part, mask in part_masks(template).items():
        if not mask.any():
            continue
        share = float(found[mask].mean())
        in_part = mask[faces].all(1)
        edges = in_part[pairs].all(1)
        members = LANDMARK_PARTS.get(part, ())
        parts[part] = {
            "vertices": int(mask.sum()),
            "supported_share": round(share, 3),
            "supported": share >= MIN_SUPPORT,
            "mesh_to_cloud_mm": _stat(signed[mask], np.median),
            "mesh_to_cloud_abs_mm": _stat(np.abs(signed[mask]), np.median),
            "mesh_to_cloud_abs_p90_mm": _stat(np.abs(signed[mask]),
                                              lambda v: np.percentile(v, 90)),
            "cloud_noise_mm": _stat(point_error[mask], np.median, 4),
            "landmark_to_cloud_mm": _stat(to_cloud[list(members)], np.median)
            if len(members) else None,
            "bent_share_pct": round(float(np.mean(angles[edges] > BENT_DEG)) * 100, 2)
            if edges.any() else None,
        }
    return {"parts": parts,
            "landmarks_to_cloud_mm": [None if not np.isfinite(d) else round(float(d), 3)
                                      for d in to_cloud]}
