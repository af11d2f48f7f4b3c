"""Entry point of the fitting stage: inputs in, ``mesh.ply`` / ``mesh.obj`` (+ colours) out.

:func:`main` loads what it is given (arrays or files), fits the template (:func:`fit`),
colours it from the keyframes (:func:`facecap_core.texture.vertex_colours`) and writes

    mesh.ply     fitted mesh in template topology, mm, per-vertex RGB
    mesh.obj     the same, vertex colours as ``v x y z r g b``; with the default template
                 also its UVs (``vt``, ``f v/vt``) and ``mtllib mesh.mtl``
    mesh.mtl, texture.png  the UV texture atlas baked from the keyframes
                 (:func:`facecap_core.texture.bake_texture`), default template only
    mesh.glb     binary glTF split at the UV seams, the atlas as baseColorTexture
    landmarks.json  the fitted mesh's 68 landmark points
    fit.json     schedule, per-step log, timing (wall and CPU seconds)
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from facecap_core.errors import InputError
from facecap_core.fitting.quality import part_quality
from facecap_core.fitting.sanity import MeshSanity, check_mesh, relax_folds
from facecap_core.fitting.settings import FittingConfig
from facecap_core.landmarks.ears import EAR_VERTEX_IDS
from facecap_core.lazy import LazyModule
from facecap_core.measure import landmark_measurements
from facecap_core.meshio import load_landmarks, save_landmarks
from facecap_core.nonrigid.constraints import Keyframe
from facecap_core.nonrigid.nicp import FitResult, fit
from facecap_core.nonrigid.photometric import refine
from facecap_core.nonrigid.roughness import face_edges, roughness
from facecap_core.template import Template
from facecap_core.texture import (
    MESH_GLB,
    MESH_MTL,
    TEXTURE_PNG,
    UVLayout,
    bake_texture,
    glb_bytes,
    mtl_text,
    obj_text,
    png_bytes,
    template_uv,
    vertex_colours,
)
from facecap_core.video import read_frames

o3d = LazyModule("open3d")
trimesh = LazyModule("trimesh")

MESH_PLY = "mesh.ply"
MESH_OBJ = "mesh.obj"
MESH_LANDMARKS = "landmarks.json"
FIT_JSON = "fit.json"

__all__ = ["fit_and_write", "write_mesh", "load_cloud", "keyframes_from_video"]

log = logging.getLogger(__name__)


def load_cloud(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Points (N, 3) and normals (or None) from a PLY/PCD/XYZ point cloud or an ``.npz``
    with ``points`` (and ``normals``)."""
    points, normals, _ = load_cloud_errors(path)
    return points, normals


def load_cloud_errors(path: str | Path
                      ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Points, normals (or None) and each point's standard error in mm (or None), from the
    fusion stage's ``spread`` and ``views`` PLY properties (spread / sqrt(views)), or an
    ``.npz``'s ``errors``."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"point cloud file not found: {path}")
    if path.suffix.lower() == ".npz":
        with np.load(path) as z:
            if "points" not in z:
                raise InputError(f"point cloud {path} has no 'points' array")
            return (z["points"].astype(float),
                    z["normals"].astype(float) if "normals" in z else None,
                    z["errors"].astype(float).ravel() if "errors" in z else None)
    pc = o3d.t.io.read_point_cloud(str(path))
    if "positions" not in pc.point or len(pc.point.positions) == 0:
        raise InputError(f"point cloud {path} is empty or unreadable (expected PLY/PCD/XYZ)")
    pts = pc.point.positions.numpy().astype(float)
    normals = pc.point.normals.numpy().astype(float) if "normals" in pc.point else None
    errors = None
    if "spread" in pc.point and "views" in pc.point:
        errors = (pc.point.spread.numpy().astype(float).ravel()
                  / np.sqrt(np.maximum(pc.point.views.numpy().astype(float).ravel(), 1.0)))
    return pts, normals, errors


def keyframes_from_video(video: str | Path, intrinsics, poses: list[dict],
                         indices: list[int], width: int | None = None) -> list[Keyframe]:
    """Keyframes (RGB images + cameras) for the frame ``indices`` of a video; ``poses`` are
    per-frame dicts with ``index``, ``R``, ``t`` (world-to-camera)."""

    images = read_frames(video, indices, width=width)
    by_index = {p["index"]: p for p in poses}
    return [Keyframe(images[i], intrinsics, by_index[i]["R"], by_index[i]["t"])
            for i in indices if i in images]


def write_mesh(folder: str | Path, vertices: np.ndarray, faces: np.ndarray,
               colours: np.ndarray | None = None,
               texture: tuple[UVLayout, np.ndarray] | None = None) -> tuple[Path, Path]:
    """Write ``mesh.ply`` and ``mesh.obj`` (vertex order and faces exactly as given); with
    ``texture`` (the UV layout and its atlas) also ``mesh.mtl``, ``texture.png`` and
    ``mesh.glb``, and the OBJ carries the UVs."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    mesh = trimesh.Trimesh(np.asarray(vertices, float), np.asarray(faces, np.int64),
                           process=False)
    if colours is not None:
        rgba = np.c_[np.asarray(colours, np.uint8), np.full(len(vertices), 255, np.uint8)]
        mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=rgba)
    ply, obj = folder / MESH_PLY, folder / MESH_OBJ
    files = {ply: _export(mesh, "ply", {"encoding": "binary"})}
    if texture is None:
        files[obj] = _export(mesh, "obj", {"include_color": True, "include_normals": False,
                                           "include_texture": False})
    else:
        layout, atlas = texture
        # The OBJ last: its material and image are in place when it appears.
        files = {folder / TEXTURE_PNG: png_bytes(atlas), folder / MESH_MTL: mtl_text().encode(),
                 folder / MESH_GLB: glb_bytes(vertices, faces, layout, atlas), **files,
                 obj: obj_text(vertices, faces, colours, layout).encode()}
    for path, data in files.items():
        tmp = path.with_name(path.name + ".part")
        tmp.write_bytes(data)
        tmp.replace(path)
    return ply, obj


def _export(mesh: trimesh.Trimesh, kind: str, kwargs: dict) -> bytes:
    data = trimesh.exchange.export.export_mesh(mesh, None, file_type=kind, **kwargs)
    return data if isinstance(data, bytes) else data.encode()


EAR_OFF_CLOUD_MM = 8.0
"""A side's ear points whose median distance to the cloud exceeds this are not used: twice
the error of a triangulated ear point along a profile view (about 4 mm, docs/ears.md), while
ears 20 % too far apart lie some 15 mm out in the air beside the head."""
EAR_CLOUD_COVER = 200
"""Cloud points within 30 mm of an ear's points needed to judge it (a cloud with a hole
there, hair or a side never seen, says nothing about the ear)."""


def ears_off_the_cloud(ear_points, cloud: np.ndarray) -> tuple[tuple | None, dict]:
    """``ear_points`` (ids, points[, weights]) without the sides (by
    :data:`~facecap_core.landmarks.ears.EAR_VERTEX_IDS`) that lie off the fused ``cloud``, and
    per side judged: the median distance (mm), the cloud points near it, ``used``."""


    if ear_points is None or not len(ear_points[0]) or len(cloud) < EAR_CLOUD_COVER:
        return ear_points, {}
    ids, pts = np.asarray(ear_points[0]), np.asarray(ear_points[1], float)
    tree = cKDTree(np.asarray(cloud, float))
    keep, report = np.ones(len(ids), bool), {}
    for side, side_ids in EAR_VERTEX_IDS.items():
        mine = np.isin(ids, side_ids)
        if not mine.any():
            continue
        near = len(tree.query_ball_point(pts[mine].mean(0), 30.0))
        d = float(np.median(tree.query(pts[mine])[0]))
        used = near < EAR_CLOUD_COVER or d <= EAR_OFF_CLOUD_MM
        report[side] = {"median_cloud_distance_mm": round(d, 2), "cloud_points_near": near,
                        "used": used}
        if not used:
            keep[mine] = False
            report[side]["reason"] = (f"its points lie {d:.0f} mm from the reconstructed "
                                      f"surface (bound {EAR_OFF_CLOUD_MM:g} mm)")
            log.info("%s ear not fitted: %s", side, report[side]["reason"])
    return tuple(np.asarray(a)[keep] for a in ear_points), report


def fit_and_write(cloud, landmarks, out_dir: str | Path, template: Template | None = None,
         keyframes: list[Keyframe] | tuple = (), ear_points=None, cloud_normals=None,
         config: FittingConfig | None = None, cloud_errors=None) -> Path:
    """Fit and write the mesh; returns the path of ``mesh.ply``.

    ``cloud``: (N, 3) array or a point-cloud file; ``landmarks``: (68, 3) array or a
    landmark file; ``template``: default :meth:`Template.default`.
    """
    config = config or FittingConfig()
    if isinstance(cloud, (str, Path)):
        cloud, file_normals, file_errors = load_cloud_errors(cloud)
        cloud_normals = cloud_normals if cloud_normals is not None else file_normals
        cloud_errors = cloud_errors if cloud_errors is not None else file_errors
    if isinstance(landmarks, (str, Path)):
        landmarks = load_landmarks(landmarks)
    template = template or Template.default()
    ears_report = {}
    if config.use_cloud and config.use_ear_landmarks:
        ear_points, ears_report = ears_off_the_cloud(ear_points, cloud)
    result = fit(template, cloud, landmarks, keyframes, ear_points, cloud_normals, config,
                 cloud_errors)
    photometric = {}
    if config.photometric.rounds and len(keyframes):
        vertices, photometric = refine(result.vertices, result.faces, keyframes,
                                       config.photometric)
        result.template = result.template.with_vertices(vertices)
    sanity, relaxed = check_mesh(result.vertices, result.faces, template.vertices), None
    if not sanity.ok and config.relax_folds:
        found = sanity.to_json()
        vertices, relaxed = relax_folds(result.vertices, result.faces, template.vertices)
        result.template = result.template.with_vertices(vertices)
        sanity = check_mesh(result.vertices, result.faces, template.vertices)
        relaxed["before"] = found
        log.info("folds relaxed over %d vertices: %d flipped, %d stretched, %d intersecting "
                 "before; %d, %d, %d after", relaxed["relaxed_vertices"], found["flipped"],
                 found["stretched_edges"], found["self_intersecting_pairs"], sanity.flipped,
                 sanity.stretched_edges, sanity.self_intersecting_pairs)
    if not sanity.ok:
        log.warning("the fitted mesh keeps %d flipped triangles, %d stretched edges and %d "
                    "self-intersecting triangle pairs (fit.json: sanity)", sanity.flipped,
                    sanity.stretched_edges, sanity.self_intersecting_pairs)
    colours, texture, texture_info = None, None, {}
    if config.texture and len(keyframes):
        colours, _ = vertex_colours(result.vertices, result.faces, keyframes,
                                    config.texture_min_cos)
        layout = template_uv(result.faces)
        if layout is not None:
            atlas, texture_info = bake_texture(result.vertices, result.faces, keyframes, layout,
                                               min_cos=config.texture_min_cos,
                                               fill_colours=colours)
            texture = (layout, atlas)
    out = Path(out_dir)
    ply, _ = write_mesh(out, result.vertices, result.faces, colours, texture)
    save_landmarks(out / MESH_LANDMARKS, result.template.landmark_points,
                   template=template.name)
    rough = roughness(result.vertices, result.faces,
                      face_edges(template.vertices, template.faces, template.landmarks))
    parts = (part_quality(result.vertices, template, cloud, cloud_normals, cloud_errors,
                          landmarks) if config.use_cloud else None)
    # The anatomical distances on the mesh, for a dataset to compare (the metric scale's
    # uncertainty is the coarse stage's, added where the report is made).
    measurements = landmark_measurements(result.vertices, result.faces, template.landmarks,
                                         None)
    write_report(out / FIT_JSON, result, config, sanity, relaxed, ears_report, rough,
                 {**(parts or {}), "measurements": measurements, "photometric": photometric,
                  **({"texture": texture_info} if texture_info else {})})
    last = result.log[-1] if result.log else {}
    log.info("fitted %d vertices in %d steps (%.1f s): landmark RMS %.2f mm, %d cloud targets, "
             "last step moved %.3f mm; %.1f %% of the face's edges bent over %g°",
             len(result.vertices), result.iterations, result.wall_s,
             last.get("landmark_rms_mm", float("nan")), last.get("cloud_targets", 0),
             last.get("max_move_mm", float("nan")), rough["bent_share_pct"] or 0.0,
             rough["bent_deg"])
    return ply


def _rounded(value: float | None, digits: int) -> float | None:
    """A figure for JSON: rounded, None where unknown (strict JSON has no nan)."""
    return None if value is None or not np.isfinite(value) else round(float(value), digits)


def write_report(path: Path, result: FitResult, config: FittingConfig,
                 sanity: MeshSanity | None = None, relaxed: dict | None = None,
                 ears: dict | None = None, rough: dict | None = None,
                 more: dict | None = None) -> Path:
    doc = {"config": config.model_dump(mode="json"), "timing": result.timing(),
           "vertices": len(result.vertices), "faces": len(result.faces), "steps": result.log,
           "sanity": sanity.to_json() if sanity is not None else None, "relaxed": relaxed,
           "ears_on_cloud": ears or {}, "roughness": rough,
           "cloud_noise": {"noise_mm": _rounded(result.cloud_noise_mm, 4),
                           "reference_mm": config.cloud_noise_mm,
                           "weight": _rounded(result.cloud_weight, 4)},
           **(more or {})}
    path.write_text(json.dumps(doc, indent=1))
    return path
