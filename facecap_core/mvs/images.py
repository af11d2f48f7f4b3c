"""Keyframes prepared for matching: resized, undistorted to a pinhole camera, greyscale.

PatchMatch warps windows with plane homographies, which hold only for a pinhole camera, so
lens distortion is removed once per image here (OpenCV remap) instead of per sample.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from facecap_core.camera import CameraSet, Intrinsics, camera_center
from facecap_core.errors import InputError
from facecap_core.frames import frame_name, load_frame
from facecap_core.pose.cameras_json import read_cameras_json


@dataclass
class MVSView:
    """One keyframe ready for stereo: pinhole camera, pose, RGB and grey [0, 1] images."""

    index: int
    intr: Intrinsics  # pinhole (k1 = k2 = 0), at the image's resolution
    R: np.ndarray  # world-to-camera rotation (3, 3)
    t: np.ndarray  # world-to-camera translation (3,)
    rgb: np.ndarray  # uint8 (H, W, 3)
    grey: np.ndarray  # float32 (H, W) in [0, 1]

    @property
    def centre(self) -> np.ndarray:
        return camera_center(self.R, self.t)

    @property
    def shape(self) -> tuple[int, int]:
        return self.grey.shape


def pinhole(intr: Intrinsics) -> Intrinsics:
    """The same camera without distortion (what the undistorted image is seen through)."""
    return Intrinsics(intr.width, intr.height, intr.fx, intr.fy, intr.cx, intr.cy)


def undistort(image: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """Resample ``image`` (taken through ``intr``) as seen by :func:`pinhole` (intr)."""
    if intr.k1 == 0.0 and intr.k2 == 0.0:
        return image
    K = intr.K
    mapx, mapy = cv2.initUndistortRectifyMap(K, intr.dist, None, K,
                                             (intr.width, intr.height), cv2.CV_32FC1)
    return cv2.remap(image, mapx, mapy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def prepare_view(index: int, image: np.ndarray, intr: Intrinsics, R: np.ndarray,
                 t: np.ndarray, width: int | None = None) -> MVSView:
    """Resize (area filter) to ``width``, undistort and convert an RGB keyframe.

    ``intr`` is the camera at the image's own resolution or at any other one with the same
    aspect ratio (it is rescaled to the processed size).
    """
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise InputError(f"keyframe {index}: expected an RGB uint8 image (H, W, 3); got "
                         f"{image.dtype} {image.shape}")
    h, w = image.shape[:2]
    if abs(w / h - intr.width / intr.height) > 0.01:
        raise InputError(f"keyframe {index}: image is {w}x{h} but the camera is "
                         f"{intr.width}x{intr.height} (aspect ratios differ)")
    if width is not None and width < w:
        nw, nh = int(width), int(round(h * width / w))
        image = cv2.resize(image, (nw, nh), interpolation=cv2.INTER_AREA)
        h, w = nh, nw
    cam = intr.scaled(w, h)
    rgb = undistort(image, cam)
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32) / 255.0
    R = np.asarray(R, float).reshape(3, 3)
    t = np.asarray(t, float).reshape(3)
    return MVSView(int(index), pinhole(cam), R, t, np.ascontiguousarray(rgb), grey)


def downscale_view(view: MVSView, factor: float) -> MVSView:
    """The view at ``factor`` times its size (area filter), for a coarser pyramid level."""
    h, w = view.grey.shape
    nw, nh = max(1, int(round(w * factor))), max(1, int(round(h * factor)))
    grey = cv2.resize(view.grey, (nw, nh), interpolation=cv2.INTER_AREA)
    rgb = cv2.resize(view.rgb, (nw, nh), interpolation=cv2.INTER_AREA)
    return MVSView(view.index, view.intr.scaled(nw, nh), view.R, view.t, rgb, grey)


VIEW_CACHE_BYTES = 256 * 2**20
"""Prepared views a process keeps for its next depth maps: each map reads its reference and
12 sources, neighbouring maps mostly the same ones, and decoding and undistorting a 720p
keyframe costs about as much as a tenth of a plane-sweep map. 256 MB holds ~90 views at the
default 640 px. Views are shared: nothing writes into their arrays."""

_views: OrderedDict[tuple, MVSView] = OrderedDict()
_views_lock = threading.Lock()


def load_view(frames_dir: str | Path, cams: CameraSet, index: int, width: int) -> MVSView:
    """Keyframe ``index`` of the frames stage, prepared at ``width`` for matching (kept for
    the next call with the same file, camera and width)."""
    R, t = cams.pose(index)
    path = Path(frames_dir).resolve()
    stat = (path / frame_name(index)).stat() if (path / frame_name(index)).is_file() else None
    key = (str(path), int(index), int(width), cams.intrinsics, np.asarray(R, float).tobytes(),
           np.asarray(t, float).tobytes(), stat and (stat.st_mtime_ns, stat.st_size))
    with _views_lock:
        if key in _views:
            _views.move_to_end(key)
            return _views[key]
    view = prepare_view(index, load_frame(frames_dir, index), cams.intrinsics, R, t, width)
    with _views_lock:
        _views[key] = view
        while sum(v.rgb.nbytes + v.grey.nbytes for v in _views.values()) > VIEW_CACHE_BYTES:
            _views.popitem(last=False)
    return view


def metric_cameras(cameras_json: str | Path) -> CameraSet:
    """The coarse stage's cameras; anything not in millimetres is refused."""
    cams = read_cameras_json(cameras_json)
    if cams.units != "mm":
        raise InputError(f"{cameras_json} is not metric (units: {cams.units}); MVS needs the "
                         "coarse stage's cameras in mm")
    return cams
