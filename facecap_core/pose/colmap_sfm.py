"""Geometric structure from motion on the keyframes with pycolmap (SIFT, sequential
matching, incremental mapping with one shared RADIAL camera).

This is the starting point for photometric bundle adjustment and the peer it is compared
with. Keyframes are written as PNG at ``sfm_width`` and the result is converted back to
full-resolution pixels.
"""

from __future__ import annotations

import errno
import os
import shutil
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from facecap_core.camera import Intrinsics
from facecap_core.errors import FacecapError

# Imported where used: pycolmap (COLMAP, with its logging set up first) only where SfM runs.


@dataclass
class Poses:
    """Intrinsics (full video resolution) and world-to-camera poses of registered keyframes."""

    intrinsics: Intrinsics
    frame_indices: list[int]  # video frame index of each registered keyframe
    R: list[np.ndarray]
    t: list[np.ndarray]
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # sparse points
    seconds: float = 0.0
    # Rows (point number, keyframe number in frame_indices, x, y): full-resolution pixels.
    observations: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    # The principal point was held at the image centre: the tracks put it beyond a phone's.
    principal_point_held: bool = False

    def visibility(self) -> np.ndarray:
        """(keyframes, points) bool: which keyframe observes which sparse point."""
        vis = np.zeros((len(self.frame_indices), len(self.points)), bool)
        obs = self.observations.astype(np.int64)
        vis[obs[:, 1], obs[:, 0]] = True
        return vis


EXHAUSTIVE_MAX_IMAGES = 300
"""Unordered images up to this many are matched pair by pair; beyond, sequentially with
COLMAP's quadratic overlap (pairs i, i+1, ..., i+overlap and i+2, i+4, i+8, ...), which also
links distant parts of a sweep."""



def _unwritable(path: Path) -> OSError:
    """OpenCV says only that a write failed: a full disk is the usual cause, told apart
    by the free space left."""

    full = shutil.disk_usage(path.parent).free < 64 * 2**20
    code = errno.ENOSPC if full else errno.EIO
    return OSError(code, os.strerror(code), str(path))


def run_sfm(images: dict[int, np.ndarray], work_dir: str | Path, video_size: tuple[int, int],
            overlap: int = 10, refine_principal_point: bool = False,
            threads: int = 1, seed: int = 0, ordered: bool = True,
            focal_px: float | None = None, extraction_threads: int = 1) -> Poses:
    """SfM over keyframe images ({video frame index: RGB uint8}, all one size).

    With one thread and a fixed ``seed`` the result is the same on every run; with more,
    COLMAP's threaded matching gives slightly different cameras each time. SIFT extracts
    each image alone: ``extraction_threads`` do not change the result.

    With the defaults this is what a COLMAP user gets (principal point held at the image
    centre); sequential matching pairs each keyframe with the next ``overlap``. Images not
    ``ordered`` along a sweep (photos) are matched exhaustively. ``focal_px`` (full
    resolution), when known, is the initial focal length instead of COLMAP's guess."""
    # Long on purpose: COLMAP's steps in order (database, extraction, matching, mapping, the
    # model's checks), each a few calls.

    import pycolmap

    start = time.perf_counter()
    work = Path(work_dir)
    img_dir = work / "images"
    shutil.rmtree(work, ignore_errors=True)
    img_dir.mkdir(parents=True)
    names = {f"frame_{index:06d}.png": index for index in sorted(images)}

    def write(name: str) -> None:
        image = cv2.cvtColor(images[names[name]], cv2.COLOR_RGB2BGR)
        if not cv2.imwrite(str(img_dir / name), image):
            raise _unwritable(img_dir / name)

    with ThreadPoolExecutor(max(1, extraction_threads)) as pool:  # PNG encoding lets go of the GIL
        list(pool.map(write, names))
    h, w = next(iter(images.values())).shape[:2]
    db = work / "database.db"
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "RADIAL"
    if focal_px:
        f_sfm = focal_px * w / video_size[0]
        reader.camera_params = f"{f_sfm!r},{w / 2!r},{h / 2!r},0,0"  # a prior focal length
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = extraction_threads
    # Images enter the database first, one after another (their ids in name order): with
    # several extraction threads COLMAP would number them in the order their features
    # finish, and matching and mapping follow the ids.
    pycolmap.Database.open(str(db)).close()  # creates it
    pycolmap.import_images(db, img_dir, camera_mode=pycolmap.CameraMode.SINGLE,
                           options=reader)
    pycolmap.extract_features(db, img_dir, camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader, extraction_options=extraction,
                              device=pycolmap.Device.cpu)
    # Fixed seeds: a stage rerun (a retry, a killed worker's successor) gives the same cameras.
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = seed
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = threads
    if ordered or len(images) > EXHAUSTIVE_MAX_IMAGES:
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = overlap
        pycolmap.match_sequential(db, matching_options=matching, pairing_options=pairing,
                                  verification_options=verification,
                                  device=pycolmap.Device.cpu)
    else:
        pycolmap.match_exhaustive(db, matching_options=matching,
                                  verification_options=verification,
                                  device=pycolmap.Device.cpu)
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = threads
    options.random_seed = seed
    options.ba_refine_principal_point = refine_principal_point
    maps = pycolmap.incremental_mapping(db, img_dir, work / "sparse", options)
    if not maps:
        raise FacecapError("structure from motion registered no keyframes: the video has "
                           "too little texture or motion to estimate camera poses")
    rec = max(maps.values(), key=lambda r: r.num_reg_images())
    cam = next(iter(rec.cameras.values()))
    f, cx, cy, k1, k2 = cam.params
    sx, sy = video_size[0] / w, video_size[1] / h
    # COLMAP's image edge is at 0 (pixel centres at +0.5); ours is at -0.5.
    intr = Intrinsics(video_size[0], video_size[1], f * sx, f * sy, cx * sx - 0.5,
                      cy * sy - 0.5, k1, k2)
    order = sorted(rec.images.values(), key=lambda im: names[im.name])
    R, t, idx = [], [], []
    for im in order:
        pose = im.cam_from_world()
        R.append(np.asarray(pose.rotation.matrix()))
        t.append(np.asarray(pose.translation))
        idx.append(names[im.name])
    view_of = {im.image_id: k for k, im in enumerate(order)}
    pts, rows = [], []
    for n, point in enumerate(rec.points3D.values()):
        pts.append(point.xyz)
        for el in point.track.elements:
            xy = rec.images[el.image_id].points2D[el.point2D_idx].xy
            rows.append((n, view_of[el.image_id], xy[0] * sx - 0.5, xy[1] * sy - 0.5))
    rec.write_text(str(work / "sparse"))
    return Poses(intr, idx, R, t, np.array(pts).reshape(-1, 3), time.perf_counter() - start,
                 np.array(rows, float).reshape(-1, 4))
