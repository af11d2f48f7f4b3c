"""``cameras.json``: the keyframe cameras. The pose stage writes it in its own units; the
coarse stage writes it again in mm (``units``, ``metric_scale``); the synthetic captures'
ground-truth keyframes write it in a transformed world (``world_from_gt``).

Pixels are full-resolution pixels with the centre of the top-left pixel at (0, 0); poses are
world-to-camera, ``x_cam = R x_world + t`` (OpenCV; :mod:`facecap_core.camera`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import numpy as np
from pydantic import Field

from facecap_core.artifact_json import ArtifactJson, Matrix3, Vector3
from facecap_core.camera import CameraSet, Intrinsics

CONVENTION = ("world-to-camera x_cam = R x_world + t (OpenCV); pixel centres at integer "
              "coordinates; distortion RADIAL (k1, k2) on normalised coordinates")
"""What the poses and pixels of every ``cameras.json`` mean."""


class CameraIntrinsics(ArtifactJson):
    """The one camera all keyframes share (:class:`facecap_core.camera.Intrinsics`)."""

    width: int
    """Image width, px (the video's, upright)."""
    height: int
    """Image height, px."""
    fx: float
    """Focal length along x, px."""
    fy: float
    """Focal length along y, px."""
    cx: float
    """Principal point x, px (the top-left pixel's centre at 0)."""
    cy: float
    """Principal point y, px."""
    k1: float = 0.0
    """First radial distortion coefficient, on normalised coordinates (no unit)."""
    k2: float = 0.0
    """Second radial distortion coefficient, on normalised coordinates (no unit)."""

    def intrinsics(self) -> Intrinsics:
        return Intrinsics(**self.model_dump())


class KeyframePose(ArtifactJson):
    """One keyframe's world-to-camera pose."""

    frame_index: int
    """The keyframe's index among the video's frames (0 is the first)."""
    R: Matrix3
    """Rotation, world to camera (3 x 3, rows)."""
    t: Vector3
    """Translation, world to camera, in the file's ``units`` (camera units or mm)."""


class DroppedKeyframe(ArtifactJson):
    """A keyframe the pose stage could not give a camera."""

    frame_index: int
    """The keyframe's index among the video's frames."""
    reason: str
    """Why, in words."""


class Reprojection(ArtifactJson):
    """Reprojection error of the sparse points, px."""

    median: float
    """Median, px."""
    rms: float
    """Root mean square, px."""


class SolveFigures(ArtifactJson):
    """The solve's own figures for the run's report (``facecap_core.pose.checks``)."""

    focal_px: float
    """Focal length fx, px (2 decimals)."""
    principal_point_px: Annotated[list[float], Field(min_length=2, max_length=2)]
    """Principal point (cx, cy), px."""
    principal_point_held: bool = False
    """The principal point was held at the image centre: the tracks put it further from it
    than a phone camera's (``facecap_core.pose.geometric.PRINCIPAL_POINT_MAX_PCT``)."""
    field_of_view_deg: Annotated[list[float], Field(min_length=2, max_length=2)]
    """Horizontal and vertical field of view, degrees."""
    reprojection_px: Reprojection | None = None
    """Reprojection error of the sparse points (none without sparse points)."""
    track_length: float | None = None
    """Mean number of views per sparse point (none without sparse points)."""
    turn_deg: float
    """Sum of the view-to-view rotations along the keyframes, degrees."""
    tracked_turn_deg: float | None = None
    """The same turn as the tracker measured it, degrees (keyframes in sweep order)."""
    circling_factor: float | None = None
    """How much further the solve turns than the tracker step by step (1-2; keyframes in
    sweep order): what the order check scales the tracking by."""
    largest_step_ratio: float | None = None
    """Largest step between consecutive views over the step expected between them
    (keyframes: the tracking times the circling factor, or the frames between them at the
    solve's typical turn per frame; jumps are over 2)."""


class WorldFromGt(ArtifactJson):
    """The similarity ``x' = scale * rotation @ x + translation`` from a synthetic capture's
    ground-truth world (mm) to the file's world."""

    scale: float
    """Scale, file units per mm."""
    rotation: Matrix3
    """Rotation (3 x 3, rows)."""
    translation: Vector3
    """Translation, file units."""


class Cameras(ArtifactJson):
    """``cameras.json``: the shared camera, every keyframe's pose and the solve's figures.
    Only ``units``, ``intrinsics`` and ``keyframes`` are in every file; the rest is written
    by the stage named in its description and left out by the others."""

    file_name = "cameras.json"
    written_by = "the pose stage"

    convention: str = CONVENTION
    """What the poses and pixels mean (:data:`CONVENTION`)."""
    units: str
    """Units of ``t`` and of the world: ``mm`` after the coarse stage, otherwise the pose
    stage's own (arbitrary, monocular) camera units."""
    intrinsics: CameraIntrinsics
    """The camera (px)."""
    keyframes: Annotated[list[KeyframePose], Field(min_length=1)]
    """The keyframes' poses, in keyframe order (one at least)."""
    seconds: float | None = None
    """Pose stage: seconds the solve took (2 decimals)."""
    method: str | None = None
    """Pose stage: the last step that gave these poses (``sfm``, ``geometric``, ``pba``)."""
    dropped: list[DroppedKeyframe] | None = None
    """Pose stage: the keyframes left without a camera."""
    solve: SolveFigures | None = None
    """Pose stage: the solve's figures."""
    wall_seconds: float | None = None
    """Pose stage: wall-clock seconds of the whole stage."""
    cpu_seconds: float | None = None
    """Pose stage: CPU seconds of the whole stage."""
    world_from_gt: WorldFromGt | None = None
    """Synthetic ground truth: the world of the file from the ground truth's."""
    metric_scale: float | None = None
    """Coarse stage: mm per camera unit of the pose stage (``t`` is already in mm)."""

    def camera_set(self) -> CameraSet:
        """The cameras as arrays (:class:`facecap_core.camera.CameraSet`)."""
        R = np.array([k.R for k in self.keyframes], float).reshape(-1, 3, 3)
        t = np.array([k.t for k in self.keyframes], float).reshape(-1, 3)
        return CameraSet(self.intrinsics.intrinsics(),
                         [k.frame_index for k in self.keyframes], R, t, self.units,
                         self.metric_scale)


def read_cameras_json(path: str | Path) -> CameraSet:
    """The cameras of the ``cameras.json`` at ``path`` (pose or coarse stage) as arrays;
    :class:`facecap_core.errors.InputError` naming the file when it is missing or not
    one."""
    return Cameras.read(path).camera_set()


def keyframe_poses(frame_indices, R, t) -> list[KeyframePose]:
    """The keyframes' entries from their indices and world-to-camera rotations and
    translations (arrays or lists)."""
    return [KeyframePose(frame_index=int(i), R=np.asarray(r, float).tolist(),
                         t=np.asarray(v, float).tolist())
            for i, r, v in zip(frame_indices, R, t, strict=True)]
