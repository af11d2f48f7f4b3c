"""Synthetic handheld captures of a textured head, with exact ground truth (an offline tool:
the tests, benchmarks and ``facecap synth`` use it, the pipeline does not).

Modules: :mod:`.subjects` (who is filmed), :mod:`.scene` (the room and the motions),
:mod:`.sensor` (the phone camera and the lights), :mod:`.capture` (frames, video and ground
truth); :mod:`.ground_truth` and :mod:`.cloud` derive stage inputs from the ground truth for
tests and benchmarks.

A capture is an ear-to-ear sweep: the camera moves on an arc from one profile to the other
at 35–50 cm, looking at the head, with slow drifts (distance, elevation, roll) and fast hand
tremor. The camera is a phone-like pinhole with an unknown focal length (~65° horizontal
field of view), a jittered principal point and radial distortion. Each frame is ray cast
(open3d) through the distorted pixel grid — no resampling — shaded (Lambert + a little
specular) under fixed world lights, blurred by the camera's motion during the exposure,
scaled by a drifting auto-exposure gain, given Poisson–Gaussian sensor noise, and encoded as
H.264. A static textured room surrounds the subject so there is a background to track.

What phones do and a plain render does not, each a :class:`SynthConfig` field that is off by
default: portrait frames stored landscape with a display rotation
(``display_rotation_deg``), a rolling shutter whose every sensor line is ray cast and
blurred at its own camera pose (``rolling_shutter_s``), HEVC (``codec``), a head that sways
rigidly before the still room (``sway_mm``, ``sway_deg``), untextured walls
(``plain_walls``) and smoother skin (``skin_detail``). 4K and 120 fps are ``width``,
``height`` and ``fps``.

World frame: the subject's head frame (mm) from its landmarks (see
:func:`facecap_core.template.head_frame`): +x the subject's left, +y up, +z out of the face,
origin between the tops of the jaw contour.

Output folder::

    video.mp4            the capture (H.264 or HEVC, yuv420p, display rotation if any)
    gt/mesh.ply          the visible head surface in mm (world frame): the "scan"
    gt/landmarks.json    68 3D landmarks (iBUG order, mm)
    gt/cameras.json      intrinsics + distortion (of the upright image), and per frame:
                         time, world-to-camera R, t (OpenCV convention, at mid-exposure of
                         the sensor's middle line), exposure gain; with sway the world is
                         the head frame and head_R, head_t give the head's pose in the room
    gt/subject.json      what the subject is (ICT coefficients, texture, ...)
    gt/config.yaml       the exact SynthConfig used
    gt/render.json       every drawn quantity (focal, distortion, lights, ...)
    .facecap-results.json  what facecap wrote there (its results writer's record)

The files are written as the reconstruction writes its results: all at once, never through
a link in the folder, never over the subject's own mesh or landmarks; a folder of the
artifact store or of facecap's own is refused before anything is rendered.
"""

from facecap.synthetic.capture import (
    CODECS,
    Capture,
    Shot,
    load_gt_cameras,
    prepare,
    synthesize,
    write_gt_keyframe_cameras,
)
from facecap.synthetic.scene import CameraPath, HeadSway, Room
from facecap.synthetic.sensor import Renderer, draw_intrinsics, to_srgb8
from facecap.synthetic.subjects import (
    HAIR_COLOURS,
    IRIS_DIAMETER_MM,
    SolidNoise,
    Subject,
    ict_subject,
    make_subject,
    textured_subject,
)

__all__ = [
    "CODECS", "HAIR_COLOURS", "IRIS_DIAMETER_MM", "CameraPath", "Capture", "HeadSway",
    "Renderer", "Room", "Shot", "SolidNoise", "Subject", "draw_intrinsics", "ict_subject",
    "load_gt_cameras", "make_subject", "prepare", "synthesize", "textured_subject", "to_srgb8",
    "write_gt_keyframe_cameras",
]
