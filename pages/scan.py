"""The scan beside the reconstruction on the capture page: the scan a run was scored against,
moved into the mesh's frame and thinned to a page's size.

The evaluation stage keeps the transform its metric protocol brought the mesh onto the scan
with (landmarks, then trimmed ICP, rigid: the mesh keeps its own scale); the page moves the
scan by its inverse, so the scan stands where the mesh stands, seen by the same camera.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from facecap.tasks.store import open_store
from facecap_core.evaluation.alignment import Alignment
from facecap_core.evaluation.stage import find_file, read_alignment
from facecap_core.lazy import LazyModule
from facecap_core.meshio import load_mesh

o3d = LazyModule("open3d")

_log = logging.getLogger(__name__)

SCAN_FACES = 60_000
"""The scan on the page has at most this many triangles (quadric decimation): about 1.5 MB of
the page, and a scan's shape is still all there at a face's scale."""


def thinned(vertices: np.ndarray, faces: np.ndarray, max_faces: int = SCAN_FACES
            ) -> tuple[np.ndarray, np.ndarray]:
    """The mesh with at most ``max_faces`` triangles (open3d's quadric decimation)."""
    if len(faces) <= max_faces:
        return np.asarray(vertices, np.float32), np.asarray(faces, np.uint32)
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.asarray(vertices, float)),
                                     o3d.utility.Vector3iVector(np.asarray(faces, np.int32)))
    mesh = mesh.simplify_quadric_decimation(max_faces)
    mesh.remove_unreferenced_vertices()
    return (np.asarray(mesh.vertices, np.float32), np.asarray(mesh.triangles, np.uint32))


def scan_in_mesh_frame(scan_mesh: Path, alignment: Alignment) -> tuple[np.ndarray, np.ndarray]:
    """The scan's vertices (mm) moved into the mesh's frame by the inverse of ``alignment``
    (mesh to scan) and its triangles, thinned to :data:`SCAN_FACES`."""
    scan = load_mesh(scan_mesh, "scan")
    a = alignment
    # x_scan = s R x_mesh + t, so x_mesh = R^T (x_scan - t) / s (row-wise: (x - t) R / s).
    moved = (np.asarray(scan.vertices, float) - a.t) @ a.R / a.s
    return thinned(moved, np.asarray(scan.faces))


def stored_scan(report: dict) -> tuple[np.ndarray, np.ndarray] | None:
    """The scan of a scored run, in the mesh's frame (:func:`scan_in_mesh_frame`), found
    through its evaluation artifact in the run's store (``report["store"]``) and moved by the
    alignment that artifact kept; None for a run without a scan, or where the store no
    longer holds it (the page is still worth having without it)."""

    key = (report.get("stages", {}).get("evaluation") or {}).get("key")
    if not report.get("store") or not key:
        return None
    try:
        store = open_store(report["store"])
        inputs = store.manifest(key).inputs
        if "scan" not in inputs:
            return None
        return scan_in_mesh_frame(
            find_file(store.get(inputs["scan"]), (".ply", ".obj", ".stl", ".off"), "scan mesh"),
            read_alignment(store.get(key), "metric"))
    except Exception as exc:  # noqa: BLE001 - the page is made without the scan, and says so
        _log.warning("the page shows no scan: %s", str(exc).splitlines()[0] if str(exc)
                     else type(exc).__name__)
        return None
