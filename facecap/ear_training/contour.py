"""The ear contour on the template and its transfer to the training heads."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from facecap.ear_training.config import EarTrainingConfig
from facecap.synthetic import ict_subject
from facecap.synthetic.cloud import mvs_like_cloud
from facecap_core.errors import InputError
from facecap_core.fitting import fit
from facecap_core.landmarks.ears import CONTOUR_FILE, DETECTOR_FILE, PREDICTOR_FILE
from facecap_core.nonrigid.nicp import NicpConfig
from facecap_core.template import Template, head_frame

SIDES = ("left", "right")
SIDE_SIGN = {"left": 1.0, "right": -1.0}  # head frame +x is the subject's left
MODEL_FILES = (DETECTOR_FILE, PREDICTOR_FILE, CONTOUR_FILE)


# -- the ear contour on the template ---------------------------------------------------------


def template_ear_contour(template: Template, side: str, count: int = 12,
                         arc_deg: tuple[float, float] = (130.0, -115.0)) -> np.ndarray:
    """Ordered vertex ids of one ear's outer contour (helix root -> top -> back -> lobe).

    In the head frame's side plane (a = backwards, b = up), around the centre of the ear
    region's bounding box, the outline is the farthest ear vertex per 3-degree sector, swept
    clockwise from ``arc_deg[0]`` (0 = straight back, 90 = up) to ``arc_deg[1]``; ``count``
    points are then taken at equal arc length along it.
    """
    if side not in SIDES:
        raise InputError(f"ear side {side!r}: expected 'left' or 'right'")
    R, origin = head_frame(template.landmark_points)
    P = (template.vertices - origin) @ R.T
    ids = np.flatnonzero(template.regions["ears"] & (np.sign(P[:, 0]) == SIDE_SIGN[side]))
    if len(ids) < 3 * count:
        raise InputError(f"template {template.name} has {len(ids)} {side} ear vertices; "
                         f"the ear contour needs a template with ears")
    Q = P[ids]
    ab = np.stack([-Q[:, 2], Q[:, 1]], 1)
    centre = (ab.min(0) + ab.max(0)) / 2
    d = ab - centre
    angle = np.degrees(np.arctan2(d[:, 1], d[:, 0]))
    radius = np.hypot(d[:, 0], d[:, 1])
    lateral = np.abs(Q[:, 0])
    outline = []
    for hi in np.arange(arc_deg[0], arc_deg[1], -3.0):
        sel = np.flatnonzero((angle <= hi) & (angle > hi - 3.0))
        if not len(sel):
            continue
        # Of the vertices on the outline (within 0.5 mm of the farthest), the most lateral
        # one is the rim's outer edge rather than its inner fold.
        near = sel[radius[sel] >= radius[sel].max() - 0.5]
        outline.append(near[np.argmax(lateral[near])])
    outline = np.array(outline)
    # Arc length in the side plane: the outline's lateral zigzag is not part of its length.
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(ab[outline], axis=0), axis=1))])
    picks = [outline[np.argmin(np.abs(arc - s))] for s in np.linspace(0, arc[-1], count)]
    out = ids[np.array(picks)]
    if len(np.unique(out)) != count:
        raise InputError(f"template {template.name}: the {side} ear outline is too coarse "
                         f"for {count} contour points")
    return out


# -- correspondence to other heads -----------------------------------------------------------


@dataclass
class SurfacePoints:
    """Points on a mesh as triangle corner vertex ids (K, 3) and barycentrics (K, 3)."""

    corners: np.ndarray
    bary: np.ndarray

    def on(self, vertices: np.ndarray) -> np.ndarray:
        """The points on a mesh of the same topology with these vertex positions."""
        return np.einsum("kc,kcd->kd", self.bary, np.asarray(vertices, float)[self.corners])

    def to_dict(self) -> dict:
        return {"corners": self.corners.tolist(), "bary": self.bary.round(6).tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> SurfacePoints:
        return cls(np.asarray(d["corners"], np.int64), np.asarray(d["bary"], float))


def snap_to_surface(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray
                    ) -> tuple[SurfacePoints, np.ndarray]:
    """Nearest surface points of a mesh to ``points`` and their distances."""

    mesh = trimesh.Trimesh(np.asarray(vertices, float), np.asarray(faces, np.int64),
                           process=False)
    closest, dist, tri = trimesh.proximity.closest_point(mesh, np.asarray(points, float))
    corners = mesh.faces[tri]
    bary = trimesh.triangles.points_to_barycentric(mesh.vertices[corners], closest)
    return SurfacePoints(corners.astype(np.int64), np.clip(bary, 0.0, 1.0)), dist


def fit_template_to_head(template: Template, vertices: np.ndarray, faces: np.ndarray,
                         landmarks: np.ndarray) -> np.ndarray:
    """Template vertices fitted (NICP, dense surface samples + 68 landmarks) to a head mesh."""

    cloud, normals = mvs_like_cloud(vertices, faces, density=2.0, noise_mm=0.0, holes=0.0,
                                    outliers=0.0, normal_jitter_deg=0.0)
    result = fit(template, cloud, landmarks, cloud_normals=normals,
                 config=NicpConfig(use_edges=False))
    return result.vertices


def fitted_ear_contour(template: Template, contour_ids: dict[str, np.ndarray],
                       vertices: np.ndarray, faces: np.ndarray, landmarks: np.ndarray
                       ) -> dict[str, tuple[SurfacePoints, np.ndarray]]:
    """Per side: the contour as surface points of the head mesh, and the snap distances (mm)."""
    fitted = fit_template_to_head(template, vertices, faces, landmarks)
    return {side: snap_to_surface(vertices, faces, fitted[ids])
            for side, ids in contour_ids.items()}


def ict_contour_transfer(template: Template, contour_ids: dict[str, np.ndarray],
                         ict_model: str | Path) -> dict:
    """The contour on the ICT topology (via a fit to the ICT mean head), as JSON-ready data."""

    mean = ict_subject(ict_model, None)
    skin = mean.faces[mean.gt_faces]
    snapped = fitted_ear_contour(template, contour_ids, mean.vertices, skin, mean.landmarks)
    return {side: {**sp.to_dict(), "snap_mm": dist.round(3).tolist()}
            for side, (sp, dist) in snapped.items()}


def write_contour_file(path: str | Path, config: EarTrainingConfig, ict_model: str | Path,
                       template: Template | None = None) -> dict:
    """Compute the template contour ids and their ICT transfer; write ``ear_contour.json``."""
    template = template or Template.default()
    ids = {side: template_ear_contour(template, side, config.contour_points,
                                      config.contour_arc_deg) for side in SIDES}
    doc = {"template": template.name, "template_vertices": len(template.vertices),
           "order": "helix root (top front) -> top -> back -> lobe",
           "vertex_ids": {s: v.tolist() for s, v in ids.items()},
           "ict": ict_contour_transfer(template, ids, ict_model)}
    Path(path).write_text(json.dumps(doc, indent=1))
    return doc


def load_contour_file(path: str | Path) -> dict:
    doc = json.loads(Path(path).read_text())
    return {"vertex_ids": {s: np.asarray(doc["vertex_ids"][s], np.int64) for s in SIDES},
            "ict": {s: SurfacePoints.from_dict(doc["ict"][s]) for s in SIDES},
            "template": doc.get("template")}


# -- rendering ----------------------------------------------------------------------------------
