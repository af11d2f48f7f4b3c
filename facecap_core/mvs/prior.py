"""What the coarse mesh tells PatchMatch: where the head is and how far away.

The coarse mesh (a 3DMM fitted to landmarks, a few mm off) is ray cast through each
reference camera. Its silhouette, grown by a few pixels, is the only region computed (the
room behind the head is never matched); its depth ± a margin bounds the search; its plane is
a good first hypothesis; and depths far from it are rejected afterwards.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from facecap_core.errors import InputError
from facecap_core.mvs.images import MVSView
from facecap_core.render import RaycastScene, projected_box


@dataclass
class CoarsePrior:
    """Per-pixel coarse-mesh information for one reference view (arrays (H, W[, 3]))."""

    depth: np.ndarray  # float32 coarse depth (camera z), inf where the mesh is not hit
    normal: np.ndarray  # float32 camera-frame unit normal facing the camera, 0 if no hit
    lo: np.ndarray  # float32 lower depth bound of the search (0 outside mask)
    hi: np.ndarray  # float32 upper depth bound (0 outside mask)
    mask: np.ndarray  # bool: pixels PatchMatch computes

    @property
    def pixels(self) -> int:
        return int(self.mask.sum())


def coarse_prior(view: MVSView, vertices: np.ndarray, faces: np.ndarray,
                 margin_mm: float, dilation_px: int,
                 scene: RaycastScene | None = None) -> CoarsePrior:
    """Ray cast the coarse mesh through ``view``; raises InputError if it is not in sight.
    ``scene``: one holding that mesh alone (its rays are cast only where it can be seen)."""
    if scene is None:
        scene = RaycastScene()
        scene.add(vertices, faces)
    # Only the rays that can hit it: the same hits, a third of the rays on a 720p sweep.
    hits = scene.cast_camera(view.intr, view.R, view.t,
                             box=projected_box(view.intr, view.R, view.t, vertices))
    hit = hits.valid & np.isfinite(hits.depth)
    if hit.sum() < 16:
        raise InputError(f"keyframe {view.index}: the coarse mesh does not overlap the image "
                         f"(it projects onto {int(hit.sum())} pixels); check the poses and the "
                         "coarse mesh's frame and units")
    v = np.asarray(vertices, float)
    f = np.asarray(faces, np.int64)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-12)
    normal = np.zeros(hit.shape + (3,), np.float32)
    n_cam = fn[hits.triangle[hit]] @ view.R.T
    rays = np.stack(np.nonzero(hit)[::-1], 1).astype(float)  # (u, v)
    rays = np.concatenate([(rays - [view.intr.cx, view.intr.cy]) / [view.intr.fx, view.intr.fy],
                           np.ones((len(rays), 1))], 1)
    # Orient normals towards the camera whatever the mesh's winding.
    n_cam *= np.where(np.sum(n_cam * rays, 1) > 0, -1.0, 1.0)[:, None]
    normal[hit] = n_cam
    depth = np.where(hit, hits.depth, np.inf).astype(np.float32)

    size = 2 * dilation_px + 1
    kernel = np.ones((size, size), np.uint8)
    mask = cv2.dilate(hit.astype(np.uint8), kernel) > 0
    big = np.float32(1e9)
    # Min / max of the coarse depth over the dilation window: pixels grown beyond the
    # silhouette borrow their neighbours' range, and depth edges get both sides' depths.
    d_min = cv2.erode(np.where(hit, depth, big).astype(np.float32), kernel)
    d_max = cv2.dilate(np.where(hit, depth, 0).astype(np.float32), kernel)
    lo = np.where(mask, np.maximum(d_min - margin_mm, 1.0), 0).astype(np.float32)
    hi = np.where(mask, d_max + margin_mm, 0).astype(np.float32)
    return CoarsePrior(depth, normal, lo, hi, mask)
