"""The face template: a mesh, its 68 landmark vertices and its region masks.

A :class:`Template` fixes the output topology: vertex i means the same point on every face
fitted to it. Regions (boolean masks over vertices) are derived reproducibly from the
landmarks in a head frame, so any template gets them (see :func:`region_masks`):

* ``ears``: lateral to and behind the top of the jaw contour (landmarks 0/16), within the
  ear's height band;
* ``scalp_neck``: behind the ear-front plane (not ears), above the hairline height or below
  the chin;
* ``face``: everything else.

Sources: PLY/OBJ + landmark JSON (vertex ids or points), the default template (menpo3d's
Basel-topology face-and-ears template, µm converted to mm), or an ICT Face Model ``.npz``
(skin only: face + head-and-neck, cm converted to mm).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from facecap_core import assets
from facecap_core.errors import InputError
from facecap_core.lazy import LazyModule
from facecap_core.meshio import load_landmarks, load_mesh
from facecap_core.render import RaycastScene, vertex_normals

trimesh = LazyModule("trimesh")

INNER_LANDMARKS = np.arange(17, 68)  # the 68 without the jaw contour (paper: 50 of them + 1)
REGIONS = ("face", "ears", "scalp_neck")


def head_frame(landmarks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation (rows x, y, z) and origin of the head frame defined by 68 landmarks.

    x points to the subject's left (eye centre to eye centre), y up (chin to nasion), z out of
    the face; the origin is midway between the tops of the jaw contour (0 and 16), near the ears.
    """
    L = np.asarray(landmarks, float)
    x = L[42:48].mean(0) - L[36:42].mean(0)
    x /= np.linalg.norm(x)
    y = L[27] - L[8]
    y -= x * (x @ y)
    y /= np.linalg.norm(y)
    z = np.cross(x, y)
    return np.stack([x, y, z]), (L[0] + L[16]) / 2.0


def region_masks(vertices: np.ndarray, landmarks: np.ndarray,
                 faces: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Face / ears / scalp-and-neck masks from landmark geometry (thresholds scale with the head).

    With ``faces``, an ear is told from the skull around it by thickness: a ray sent inwards
    from an ear vertex leaves the thin ear flap within ~0.35 face half-widths, one from the
    skull does not; the mask is then grown over the ear's hollows (which face the skull).
    """
    R, origin = head_frame(landmarks)
    P = (np.asarray(vertices, float) - origin) @ R.T
    Lh = (np.asarray(landmarks, float) - origin) @ R.T
    w = np.abs(Lh[[0, 16], 0]).mean()  # half the face width at ear level (~74 mm)
    behind = P[:, 2] < -0.05 * w
    ear_band = (P[:, 1] > -0.65 * w) & (P[:, 1] < 0.55 * w)
    candidates = behind & ear_band & (np.abs(P[:, 0]) > 0.85 * w)
    ears = candidates
    if faces is not None and candidates.any():
        ears = candidates & (_inward_thickness(vertices, faces, candidates) < 0.35 * w)
        ears = _grow(ears, faces, candidates, rings=2)
    above = P[:, 1] > Lh[27, 1] + 0.85 * w
    below_chin = P[:, 1] < Lh[8, 1] - 0.1 * w
    scalp_neck = ~ears & (behind | above | below_chin)
    return {"face": ~ears & ~scalp_neck, "ears": ears, "scalp_neck": scalp_neck}


def _inward_thickness(vertices: np.ndarray, faces: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Distance along the inward normal to the next surface, for masked vertices (inf: none)."""

    normals = vertex_normals(np.asarray(vertices, float), faces)[mask]
    scene = RaycastScene()
    scene.add(vertices, faces)
    origins = vertices[mask] - 0.05 * normals  # start just inside, past the vertex's own faces
    hit = scene.cast(origins, -normals)["t_hit"]
    out = np.full(len(vertices), np.inf)
    out[mask] = hit
    return out


def _grow(mask: np.ndarray, faces: np.ndarray, allowed: np.ndarray, rings: int) -> np.ndarray:
    """Grow a vertex mask over mesh edges, ``rings`` times, staying inside ``allowed``."""
    mask = mask.copy()
    for _ in range(rings):
        touched = mask[faces].any(axis=1)
        grown = np.zeros_like(mask)
        grown[faces[touched].ravel()] = True
        mask = mask | (grown & allowed)
    return mask


@dataclass
class Template:
    """Template mesh (mm), its 68 landmark vertex ids and region masks."""

    vertices: np.ndarray
    faces: np.ndarray
    landmarks: np.ndarray
    regions: dict[str, np.ndarray] = field(default_factory=dict)
    name: str = "template"

    def __post_init__(self):
        self.vertices = np.asarray(self.vertices, float)
        self.faces = np.asarray(self.faces, np.int64)
        self.landmarks = np.asarray(self.landmarks, np.int64)
        n = len(self.vertices)
        if self.landmarks.shape != (68,) or self.landmarks.min() < 0 or self.landmarks.max() >= n:
            raise InputError(f"template {self.name}: needs 68 landmark vertex ids in [0, {n}), "
                             f"got shape {self.landmarks.shape}")
        if self.faces.ndim != 2 or self.faces.shape[1] != 3 or self.faces.max() >= n:
            raise InputError(f"template {self.name}: faces must be (F, 3) vertex ids below {n}")
        if not self.regions:
            self.regions = region_masks(self.vertices, self.landmark_points, self.faces)

    @property
    def landmark_points(self) -> np.ndarray:
        return self.vertices[self.landmarks]

    def to_trimesh(self) -> trimesh.Trimesh:
        return trimesh.Trimesh(self.vertices, self.faces, process=False)

    def with_vertices(self, vertices: np.ndarray) -> Template:
        """The same topology, landmarks and regions with new vertex positions."""
        return Template(vertices, self.faces, self.landmarks, self.regions, self.name)

    # -- loading ---------------------------------------------------------------------------

    @classmethod
    def from_files(cls, mesh_path: str | Path, landmarks_path: str | Path,
                   scale: float = 1.0, name: str | None = None) -> Template:
        """Mesh (PLY/OBJ) + landmarks: JSON ``{"vertex_ids": [68 ints]}`` or 68 points
        (snapped to the nearest vertices). ``scale`` converts the mesh's units to mm."""
        mesh = load_mesh(mesh_path, what="template mesh")
        vertices = np.asarray(mesh.vertices, float) * scale
        ids = _vertex_ids_from_json(landmarks_path)
        if ids is None:
            points = load_landmarks(landmarks_path) * scale
            if points.shape[1] != 3:
                raise InputError(f"template landmarks {landmarks_path} must be 3D points")
            dist, ids = cKDTree(vertices).query(points)
            if np.max(dist) > 5.0:
                raise InputError(
                    f"template landmarks {landmarks_path} lie up to {np.max(dist):.1f} mm off "
                    f"the mesh {mesh_path}: wrong file or units (scale={scale})")
        return cls(vertices, mesh.faces, ids, name=name or Path(mesh_path).stem)

    @classmethod
    def default(cls) -> Template:
        """menpo3d's face-and-ears template (Basel topology), converted from µm to mm."""

        mesh_path, lm_path = assets.default_template_files()
        return cls.from_files(mesh_path, lm_path, scale=1e-3, name="menpo3d-bfm")

    @classmethod
    def from_ict(cls, npz_path: str | Path, coefficients: np.ndarray | None = None) -> Template:
        """Skin (face + head-and-neck) of an ICT Face Model identity, in mm."""
        model = load_ict_model(npz_path)
        vertices = ict_identity_vertices(model, coefficients)
        tri = ict_skin_faces(model)
        used = np.unique(tri)
        remap = np.full(len(vertices), -1, np.int64)
        remap[used] = np.arange(len(used))
        return cls(vertices[used], remap[tri], remap[model["landmarks68"]], name="ict-skin")

    def save(self, folder: str | Path) -> Path:
        """Write ``template.ply`` + ``template.json`` (landmark ids, region ids) into folder."""
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        self.to_trimesh().export(folder / "template.ply")
        doc = {"name": self.name, "units": "mm", "vertex_ids": self.landmarks.tolist(),
               "regions": {k: np.flatnonzero(v).tolist() for k, v in self.regions.items()}}
        (folder / "template.json").write_text(json.dumps(doc))
        return folder


def _vertex_ids_from_json(path: str | Path) -> np.ndarray | None:
    path = Path(path)
    if path.suffix.lower() != ".json" or not path.is_file():
        return None
    try:
        doc = json.loads(path.read_text())
    except (ValueError, OSError):
        return None
    if isinstance(doc, dict) and "vertex_ids" in doc:
        return np.asarray(doc["vertex_ids"], np.int64)
    return None


# -- ICT Face Model ----------------------------------------------------------------------------

ICT_SKIN_MATERIALS = ("M_Face", "M_BackHead")
ICT_SKIN_VERTEX_END = 11248  # vertex ranges: face 0-9408, head_and_neck 9409-11247
ICT_EYE_MATERIALS = ("M_ScleraLeft", "M_IrisLeft", "M_ScleraRight", "M_IrisRight")


def load_ict_model(npz_path: str | Path) -> dict:
    """Load the ICT Face Model Light npz (see its README) into a dict of arrays.

    Either the full model (100 identity modes, float32) or the trimmed copy that ships in the
    package (``facecap_core/data/``: the skin, sockets and eyeballs, the first modes in
    float16); float16 arrays are cast to float32 here."""
    path = Path(npz_path)
    if not path.is_file():
        raise InputError(f"ICT face model not found: {path} (give the path of ict_face_model.npz)")
    try:
        with np.load(path, allow_pickle=False) as z:
            model = {k: z[k] for k in z.files}
        model = {k: v.astype(np.float32) if v.dtype == np.float16 else v
                 for k, v in model.items()}
    except Exception as exc:
        raise InputError(f"{path} is not a readable ICT face model npz ({type(exc).__name__})"
                         ) from exc
    missing = {"mean_vertices", "identity_basis", "faces", "landmarks68", "face_material",
               "material_names"} - model.keys()
    if missing:
        raise InputError(f"{path} lacks ICT model arrays {sorted(missing)}")
    return model


def ict_identity_vertices(model: dict, coefficients: np.ndarray | None) -> np.ndarray:
    """Vertices (mm) of the identity ``mean + sum_i c_i mode_i`` (modes are at 1 sigma).

    Coefficients beyond the model's modes are ignored: with the trimmed model (30 modes) the
    same coefficients give the full model's head without its finer modes."""
    v = model["mean_vertices"].astype(float)
    if coefficients is not None:
        basis = model["identity_basis"]
        c = np.asarray(coefficients, float)[: len(basis)]
        v = v + np.tensordot(c, basis[: len(c)].astype(float), axes=1)
    return v * 10.0


def ict_faces_of(model: dict, materials: tuple[str, ...]) -> np.ndarray:
    names = list(model["material_names"])
    ids = [names.index(m) for m in materials]
    return model["faces"][np.isin(model["face_material"], ids)].astype(np.int64)


def ict_skin_faces(model: dict) -> np.ndarray:
    """Face and head-and-neck triangles; the mouth and eye sockets (also "M_BackHead") are
    inside the head and left out."""
    tri = ict_faces_of(model, ICT_SKIN_MATERIALS)
    return tri[np.all(tri < ICT_SKIN_VERTEX_END, axis=1)]
