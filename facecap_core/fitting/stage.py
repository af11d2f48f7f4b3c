"""The fitting stage on the files of the stages before it.

Reads the fused ``cloud.ply``, the coarse stage's folder (metric ``cameras.json``,
``landmarks3d.json`` with all 68 points in mm, ``ears3d.json``) and the keyframe PNGs, and
writes what :func:`facecap_core.fitting.run.fit_and_write` writes (``mesh.ply``, ``mesh.obj``,
``landmarks.json``, ``fit.json``; with the default template's UVs ``mesh.mtl``,
``texture.png`` and the textured ``mesh.glb``).
"""

from __future__ import annotations

import json
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np

from facecap_core.camera import CAMERAS_JSON
from facecap_core.errors import InputError
from facecap_core.fitting.run import FIT_JSON, MESH_LANDMARKS, MESH_OBJ, MESH_PLY, fit_and_write
from facecap_core.fitting.settings import FittingConfig
from facecap_core.frames import load_frame
from facecap_core.landmarks.stage import EARS_3D, LANDMARKS_3D
from facecap_core.meshio import load_landmarks
from facecap_core.mvs.fusion import CLOUD
from facecap_core.nonrigid.constraints import FIT_THREADS, Keyframe
from facecap_core.pose.cameras_json import read_cameras_json
from facecap_core.stage import Folders, Stage
from facecap_core.template import Template
from facecap_core.texture import MESH_GLB, MESH_MTL, TEXTURE_PNG


def read_ear_points(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """``(vertex ids, points, weights)`` from an ``ears3d.json`` (weights 1 where it has
    none), or None if it holds none."""
    path = Path(path)
    if not path.is_file():
        return None
    doc = json.loads(path.read_text())
    ids = np.asarray(doc.get("vertex_ids", []), np.int64)
    if len(ids) == 0:
        return None
    weights = np.asarray(doc.get("weights") or np.ones(len(ids)), float)
    if weights.shape != ids.shape:
        raise InputError(f"{path}: {len(weights)} weights for {len(ids)} ear points: recompute "
                         "the coarse stage")
    return ids, np.asarray(doc["points"], float).reshape(-1, 3), weights


def load_keyframes(frames_dir: str | Path, cams, frame_width: int | None = 960
                   ) -> list[Keyframe]:
    """The keyframe PNGs of ``cams`` (a :func:`read_cameras_json` result) with their
    cameras, at most ``frame_width`` pixels wide."""
    def keyframe(i, R, t):
        image = load_frame(frames_dir, i)
        if frame_width and image.shape[1] > frame_width:
            h = int(round(image.shape[0] * frame_width / image.shape[1]))
            image = cv2.resize(image, (frame_width, h), interpolation=cv2.INTER_AREA)
        return Keyframe(image, cams.intrinsics, R, t)

    with ThreadPoolExecutor(FIT_THREADS) as pool:  # decoding lets go of the GIL
        return list(pool.map(keyframe, cams.frame_indices, cams.R, cams.t))


def main(cloud_ply: str | Path | None, coarse_dir: str | Path, frames_dir: str | Path,
         out_dir: str | Path, config: FittingConfig | None = None,
         template: Template | None = None, frame_width: int | None = 960) -> Path:
    """Fit the template; returns ``mesh.ply``. ``cloud_ply`` None: landmarks only."""
    config = config or FittingConfig()
    coarse = Path(coarse_dir)
    cams = read_cameras_json(coarse / CAMERAS_JSON)
    keyframes = []
    if config.use_edges or config.texture or config.photometric.rounds:
        keyframes = load_keyframes(frames_dir, cams, frame_width)
    if cloud_ply is None:
        config = config.model_copy(update={"use_cloud": False})
    landmarks = load_landmarks(coarse / LANDMARKS_3D)
    return fit_and_write(cloud_ply if cloud_ply is not None else np.zeros((0, 3)), landmarks,
                    out_dir, template, keyframes, read_ear_points(coarse / EARS_3D),
                    config=config)


def figures(folder: str | Path) -> dict:
    """Headline figures of a fitting artifact: its time, the mesh checks, the face's
    roughness, each part's support by the cloud (:mod:`facecap_core.fitting.quality`) and
    the anatomical distances on the mesh (:mod:`facecap_core.measure`, without the scale's
    uncertainty, which the capture flow adds)."""
    if not (Path(folder) / FIT_JSON).is_file():
        return {}
    fit = json.loads((Path(folder) / FIT_JSON).read_text())
    # The registration's seconds and the photometric refinement's after it.
    fig = {"fit_seconds": round(fit["timing"].get("wall_s", 0.0)
                                + (fit.get("photometric") or {}).get("seconds", 0.0), 2)}
    if fit.get("sanity"):
        fig["mesh_sanity"] = fit["sanity"]
    if fit.get("roughness"):
        fig["roughness"] = fit["roughness"]
    if fit.get("cloud_noise"):
        fig["cloud_noise"] = fit["cloud_noise"]
    if fit.get("parts"):
        fig["parts"] = fit["parts"]
        fig["landmarks_to_cloud_mm"] = fit.get("landmarks_to_cloud_mm")
    if fit.get("measurements"):
        fig["measurements"] = fit["measurements"]
    return fig


def run(inputs: Folders, out: Path, config: FittingConfig, params: dict) -> None:
    main(inputs["fusion"] / CLOUD, inputs["coarse"], inputs["frames"], out, config)


STAGE = Stage("fitting", version="9", inputs=("fusion", "coarse", "frames"),
              work_seconds=45.0,
              section="fitting", run=run,
              outputs=(MESH_PLY, MESH_OBJ, MESH_LANDMARKS, FIT_JSON),
              # The UV atlas: the default template's topology and the texture on.
              optional_outputs=(MESH_MTL, TEXTURE_PNG, MESH_GLB),
              exported=(MESH_PLY, MESH_OBJ, MESH_MTL, TEXTURE_PNG, FIT_JSON), figures=figures)
