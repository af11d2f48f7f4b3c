"""``landmarks3d.json``: the landmark stage's 68 3D landmarks (iBUG 68 order, in the camera
units of the pose stage's ``cameras.json``), how they were triangulated, and the irises'
measurement the coarse stage's scale uses. ``null`` stands for a point that is not
measured (the jaw contour, a point too uncertain)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import numpy as np
from pydantic import Field

from facecap_core.artifact_json import ArtifactJson, Matrix3, Vector3
from facecap_core.errors import InputError

Per68 = Field(min_length=68, max_length=68)
"""A list with one entry per iBUG 68 landmark."""


class Reprojection(ArtifactJson):
    """Reprojection error of the final triangulation's inlier views, px (``null`` without
    any)."""

    median: float | None
    """Median, px."""
    rms: float | None
    """Root mean square, px."""


class HeadFrame(ArtifactJson):
    """The head's frame: x the subject's left, y up, z out of the face."""

    R: Matrix3
    """Rotation from world to head axes (3 x 3, rows)."""
    origin: Vector3
    """The frame's origin in the world, camera units."""


class Pupils(ArtifactJson):
    """The triangulated pupils, camera units (``null``: not measured)."""

    right: Vector3 | None
    """The subject's right pupil."""
    left: Vector3 | None
    """The subject's left pupil."""


class Irises(ArtifactJson):
    """The irises' measurement (``facecap_core.landmarks.iris``)."""

    detector: str
    """The iris detector, in words."""
    units: str
    """Units of the pupils and diameters: the cameras' units."""
    views: list[int]
    """Frame indices of the frontal keyframes used."""
    pupils: Pupils
    """The pupils in 3D."""
    pupil_distance: float | None
    """Distance between the pupils, camera units."""
    iris_diameter: float | None
    """Median iris diameter over the views, camera units."""
    iris_diameter_spread_rel: float | None
    """Robust spread of the diameters over their median (no unit)."""
    iris_diameter_views: list[Annotated[tuple[int, str, float], Field(strict=False)]]
    """Each measurement: frame index, side (``right``/``left``), diameter in camera
    units."""
    reason: str | None
    """Why the irises were not measured (``null`` when they were)."""


class Coverage(ArtifactJson):
    """How far round the head the registered keyframes go (yaw +: the subject's left)."""

    yaw_min_deg: float
    """Smallest yaw, degrees."""
    yaw_max_deg: float
    """Largest yaw, degrees."""
    yaw_span_deg: float
    """Their difference, degrees."""
    yaw_by_frame: list[Annotated[tuple[int, float], Field(strict=False)]]
    """Each keyframe: frame index and yaw, degrees."""


class Timings(ArtifactJson):
    """Seconds the stage took."""

    wall: float
    """Wall-clock seconds."""
    cpu: float
    """CPU seconds."""
    cpu_detection: float
    """CPU seconds of the face detection."""


class Landmarks3d(ArtifactJson):
    """``landmarks3d.json`` as the landmark stage writes it."""

    file_name = "landmarks3d.json"
    written_by = "the landmark stage"

    convention: str
    """The landmarks' convention: ``ibug68``."""
    units: str
    """Units of every point and length: those of the cameras (``cameras.json``)."""
    landmarks: Annotated[list[Vector3 | None], Per68]
    """The 68 landmarks, camera units, after the convention correction (``null``: the jaw
    contour and the points too uncertain)."""
    convention_correction: dict[str, Any] | None
    """The record of the offsets from the face mesh's points to 3D landmarks (what,
    captures, command, ...; ``null`` when the correction is off)."""
    triangulated: Annotated[list[Vector3 | None], Per68]
    """The 68 points as triangulated, before the correction, camera units."""
    views: list[int]
    """Frame indices of the confident views the inner points were triangulated from."""
    dropped_uncertain: list[int]
    """Landmark numbers (0-67) left out for the spread of their views' directions."""
    spread_rel: Annotated[list[float | None], Per68]
    """Each point's uncertainty along its rays over the eye-centre distance (no unit;
    ``null`` for the jaw contour)."""
    inlier_views: Annotated[list[int], Per68]
    """Each point's number of inlier views."""
    reprojection_px: Reprojection
    """Reprojection error of the triangulation, px."""
    head_frame: HeadFrame
    """The head's frame."""
    irises: Irises
    """The irises' measurement."""
    detected: int
    """Keyframes in which a face was detected."""
    keyframes: int
    """Keyframes in ``cameras.json``."""
    coverage: Coverage
    """Yaw coverage of the registered keyframes."""
    seconds: Timings | None = None
    """Seconds the stage took."""

    def points(self) -> np.ndarray:
        """The landmarks as a (68, 3) array, NaN where ``null``."""
        return np.array([[np.nan] * 3 if p is None else p for p in self.landmarks], float)


def load_landmarks3d(path: str | Path) -> tuple[np.ndarray, Landmarks3d]:
    """(68, 3) points (NaN where ``null``) and the model of a ``landmarks3d.json``;
    :class:`InputError` naming the file when it is missing or not one."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"3D landmark file not found: {path} (run the landmark stage first)")
    landmarks = Landmarks3d.read(path)
    return landmarks.points(), landmarks
