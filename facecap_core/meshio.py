"""Reading and writing meshes and landmark files, with one-line errors for bad files.

Landmarks are 68 points in the iBUG/Multi-PIE order (0–16 jaw from the subject's right,
17–21 right brow, 22–26 left brow, 27–35 nose, 36–41 right eye, 42–47 left eye, 48–67
mouth; "right" is the subject's right, i.e. image-left in a frontal photo). Accepted files:

* facecap JSON: ``{"landmarks": [[x, y, z], ...], "units": "mm", ...}``
* a plain JSON list of ``[x, y, z]`` (or ``[x, y]``) points
* menpo ``.ljson`` (LJSON v3): labelled groups are reordered into the iBUG order
* ``.npy`` / ``.txt`` arrays of shape (N, 2|3)
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from facecap_core.errors import InputError
from facecap_core.lazy import LazyModule

trimesh = LazyModule("trimesh")

MESH_SUFFIXES = {".ply", ".obj", ".stl", ".off", ".glb", ".gltf"}

# menpo label names -> slot range in the iBUG 68 order. menpo's "left" is image-left,
# which is the subject's right (iBUG 17-21, 36-41).
_LJSON_SLOTS = {
    "jaw": range(0, 17), "chin": range(0, 17),
    "left_eyebrow": range(17, 22), "leyebrow": range(17, 22),
    "right_eyebrow": range(22, 27), "reyebrow": range(22, 27),
    "nose": range(27, 36),
    "left_eye": range(36, 42), "leye": range(36, 42),
    "right_eye": range(42, 48), "reye": range(42, 48),
    "mouth": range(48, 68),
}


MAX_COORDINATE = 1e7
"""Largest vertex coordinate of a mesh read: 10 m in mm, 10 m in µm; beyond it single
precision, in which the closest-point queries work, loses the surface."""


def load_mesh(path: str | Path, what: str = "mesh", keep_vertex_order: bool = True
              ) -> trimesh.Trimesh:
    """Load a triangle mesh without merging vertices.

    ``keep_vertex_order`` keeps an OBJ's vertex numbering (needed for vertex ids); without
    it, vertices are split at texture seams so that every vertex has one UV.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{what} file not found: {path} (give the path of a .ply/.obj mesh)")
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise InputError(
            f"{what} file {path} is not a mesh (suffix {path.suffix or 'none'}; "
            f"expected one of {', '.join(sorted(MESH_SUFFIXES))})"
        )
    try:
        loaded = trimesh.load(path, process=False, maintain_order=keep_vertex_order)
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise InputError(f"{what} file {path} could not be read as a mesh ({type(exc).__name__}: "
                         f"{str(exc).splitlines()[0] if str(exc) else 'no detail'})") from exc
    if isinstance(loaded, trimesh.Scene):
        geoms = [g for g in loaded.geometry.values() if isinstance(g, trimesh.Trimesh)]
        loaded = trimesh.util.concatenate(geoms) if geoms else None
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise InputError(f"{what} file {path} holds no triangles (a point cloud or empty file?); "
                         "give a triangle mesh")
    vertices = np.asarray(loaded.vertices)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise InputError(f"{what} file {path} has vertices with {vertices.shape[-1]} coordinates, "
                         "not 3 (x y z); give a 3D triangle mesh")
    if not np.all(np.isfinite(loaded.vertices)):
        raise InputError(f"{what} file {path} has non-finite vertex coordinates; repair the mesh")
    largest = float(np.abs(loaded.vertices).max())
    if largest > MAX_COORDINATE:
        raise InputError(f"{what} file {path} has a vertex coordinate of {largest:.3g}, beyond "
                         f"±{MAX_COORDINATE:.0e} (a head in mm or µm stays well inside); repair "
                         "the mesh")
    faces = np.asarray(loaded.faces)
    if faces.min() < 0 or faces.max() >= len(loaded.vertices):
        raise InputError(f"{what} file {path} has triangles that name vertex "
                         f"{faces.min() if faces.min() < 0 else faces.max()} of "
                         f"{len(loaded.vertices)}; repair the mesh")
    return loaded


PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "<i2",
             "int16": "<i2", "ushort": "<u2", "uint16": "<u2", "int": "<i4", "int32": "<i4",
             "uint": "<u4", "uint32": "<u4", "float": "<f4", "float32": "<f4",
             "double": "<f8", "float64": "<f8"}


def ply_vertices(path: str | Path) -> np.ndarray | None:
    """The vertex element of a binary little-endian PLY whose vertices come first with
    scalar properties, x, y and z among them (what open3d and trimesh write: the cloud, the
    mesh), as a structured array by property name, read without either library; None for
    any other PLY."""
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            return None
        fields, count, element = [], None, None
        while True:
            line = f.readline()
            if not line:
                return None
            words = line.decode("ascii", "replace").split()
            if not words or words[0] in ("comment", "obj_info"):
                continue
            if words[0] == "format" and words[1:2] != ["binary_little_endian"]:
                return None
            if words[0] == "element":
                element = words[1]
                if element == "vertex":
                    count = int(words[2])
                elif count is None:  # another element before the vertices
                    return None
            if words[0] == "property" and element == "vertex":
                if words[1] not in PLY_TYPES or len(words) != 3:  # a list property
                    return None
                fields.append((words[2], PLY_TYPES[words[1]]))
            if words[0] == "end_header":
                break
        if count is None or not {"x", "y", "z"} <= {name for name, _ in fields}:
            return None
        return np.fromfile(f, dtype=np.dtype(fields), count=count)


def _ljson_points(data: dict, path: Path) -> np.ndarray:
    group = next(iter(data["groups"].values()))
    pts = np.asarray(group["landmarks"]["points"], dtype=float)
    labels = group.get("labels", [])
    slots = {name: _LJSON_SLOTS.get(lab["label"].lower()) for name, lab in
             ((lab["label"], lab) for lab in labels)}
    if len(pts) != 68 or not labels or any(s is None for s in slots.values()):
        return pts
    out = np.full((68, pts.shape[1]), np.nan)
    for lab in labels:
        target = _LJSON_SLOTS[lab["label"].lower()]
        if len(lab["mask"]) != len(target):
            raise InputError(f"landmark file {path}: group {lab['label']!r} has "
                             f"{len(lab['mask'])} points, the 68-point layout needs {len(target)}")
        out[list(target)] = pts[lab["mask"]]
    return out


def load_landmarks(path: str | Path, expected: int | None = 68) -> np.ndarray:
    """Load landmark points (N, 2|3) as float64; checks the count when ``expected`` is set."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"landmark file not found: {path} (give a JSON file of 68 points)")
    try:
        if path.suffix.lower() == ".npy":
            pts = np.load(path, allow_pickle=False)
        elif path.suffix.lower() == ".txt":
            pts = np.loadtxt(path, ndmin=2)
        else:
            data = json.loads(path.read_text())
            if isinstance(data, dict) and "groups" in data:
                pts = _ljson_points(data, path)
            elif isinstance(data, dict) and "landmarks" in data:
                pts = data["landmarks"]
            else:
                pts = data
        pts = np.asarray(pts, dtype=float)
    except InputError:
        raise
    except Exception as exc:
        raise InputError(f"landmark file {path} could not be read ({type(exc).__name__}); "
                         "expected JSON {\"landmarks\": [[x, y, z], ...]}, menpo .ljson, .npy or .txt"
                         ) from exc
    if pts.ndim != 2 or pts.shape[1] not in (2, 3):
        raise InputError(f"landmark file {path} holds an array of shape {pts.shape}; "
                         "expected N points of 2 or 3 coordinates")
    if expected is not None and len(pts) != expected:
        raise InputError(f"landmark file {path} has {len(pts)} points; expected {expected} "
                         "(iBUG 68-point order)")
    if not np.all(np.isfinite(pts)):
        raise InputError(f"landmark file {path} has missing or non-finite coordinates")
    return pts


def save_landmarks(path: str | Path, points: np.ndarray, **meta) -> Path:
    """Write landmarks as facecap JSON (units and convention recorded alongside)."""
    path = Path(path)
    doc = {"convention": "ibug68", "units": "mm", **meta,
           "landmarks": np.asarray(points, float).round(6).tolist()}
    path.write_text(json.dumps(doc, indent=1))
    return path
