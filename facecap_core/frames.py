"""The keyframe images, decoded once from the video and kept as lossless PNG.

Later stages (depth maps, fitting edges, texture) read single keyframes many times and on
any worker; decoding the video for each of them would cost a pass over the stream every
time. The images are full resolution and as recorded (distortion included).

Output folder::

    frame_<index:06d>.png   one per keyframe of the cameras file, RGB
    frames.json             {"frame_indices": [...], "width": W, "height": H}
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from facecap_core.camera import CAMERAS_JSON
from facecap_core.errors import InputError
from facecap_core.pose.cameras_json import read_cameras_json
from facecap_core.stage import Folders, Stage, capture_in
from facecap_core.video import iter_frames

FRAMES_JSON = "frames.json"


def frame_name(index: int) -> str:
    return f"frame_{int(index):06d}.png"


def main(video: str | Path, cameras_json: str | Path, out_dir: str | Path) -> Path:
    """Write the keyframes listed in ``cameras_json``; returns ``frames.json``."""
    cams = read_cameras_json(cameras_json)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    size = None
    written = []
    for frame in iter_frames(video, indices=cams.frame_indices):
        h, w = frame.image.shape[:2]
        size = (w, h)
        path = out / frame_name(frame.index)
        if not cv2.imwrite(str(path), cv2.cvtColor(frame.image, cv2.COLOR_RGB2BGR)):
            raise InputError(f"could not write {path}: check the disk and permissions")
        written.append(frame.index)
    missing = sorted(set(cams.frame_indices) - set(written))
    if missing:
        raise InputError(f"{video} has no frame(s) {missing[:5]} named in {cameras_json}: the "
                         "cameras belong to another video")
    if size != (cams.intrinsics.width, cams.intrinsics.height):
        raise InputError(f"{video} decodes at {size[0]}x{size[1]} but the cameras are for "
                         f"{cams.intrinsics.width}x{cams.intrinsics.height}")
    path = out / FRAMES_JSON
    path.write_text(json.dumps({"frame_indices": written, "width": size[0], "height": size[1]}))
    return path


def load_frame(frames_dir: str | Path, index: int) -> np.ndarray:
    """One keyframe as RGB uint8."""
    path = Path(frames_dir) / frame_name(index)
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise InputError(f"keyframe image {path} is missing or unreadable")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def run(inputs: Folders, out: Path, config: None, params: dict) -> None:
    main(capture_in(inputs["video"]), inputs["poses"] / CAMERAS_JSON, out)


STAGE = Stage("frames", version="1", inputs=("video", "poses"), work_seconds=2.0,
              section=None, run=run, outputs=(FRAMES_JSON, "frame_{index:06d}.png"))
