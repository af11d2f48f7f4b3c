"""A whole synthetic capture: the shot, the frames, the encoded video and the ground truth."""

from __future__ import annotations

import json
import os
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

import av
import numpy as np
import trimesh
from tqdm import tqdm

from facecap.synthetic.config import SynthConfig
from facecap.synthetic.scene import CameraPath, HeadSway, Room, SmoothNoise
from facecap.synthetic.sensor import (
    Readout,
    Renderer,
    draw_intrinsics,
    draw_lights,
    motion_blur,
    project_lines,
    rolling_readout,
    sensor_image,
    turn_image,
)
from facecap.synthetic.subjects import Subject, make_subject
from facecap.tasks.outputs import ResultWriter, check_results_folder
from facecap.tasks.runner import default_store_url
from facecap.tasks.scratch import process_scratch
from facecap_core.camera import (
    Intrinsics,
    project,
)
from facecap_core.config import dump_yaml
from facecap_core.errors import InputError
from facecap_core.meshio import save_landmarks
from facecap_core.pose.cameras_json import (
    CONVENTION,
    CameraIntrinsics,
    Cameras,
    KeyframePose,
    WorldFromGt,
)
from facecap_core.render import (
    Hits,
)


@dataclass
class Capture:
    """What :func:`synthesize` wrote."""

    folder: Path
    video: Path
    gt_mesh: Path
    gt_landmarks: Path
    gt_cameras: Path
    frames: int
    seconds: float


CODECS = {"h264": "libx264", "hevc": "libx265"}


def _encode(frames_path: Path, width: int, height: int, fps: float, crf: int,
            codec: str = "h264", rotation_deg: int = 0):

    container = av.open(str(frames_path), mode="w", format="mp4")
    rate = Fraction(fps).limit_denominator(1001)
    stream = container.add_stream(CODECS[codec], rate=rate)
    stream.width, stream.height = width, height
    stream.pix_fmt = "yuv420p"
    stream.time_base = 1 / rate
    stream.options = {"crf": str(crf), "preset": "medium"}
    if codec == "hevc":
        stream.codec_tag = "hvc1"  # as phones write it (Apple players need this tag)
        stream.options["x265-params"] = "log-level=error"
    if rotation_deg:
        stream.set_display_rotation(rotation_deg)
    return container, stream


@dataclass
class FrameRender:
    """One frame before sensor noise: linear RGB (upright, exposure gain applied), the
    ray-cast hits of its sharp image, and its ground truth."""

    image: np.ndarray
    hits: Hits
    time: float  # the ground-truth instant (s): mid-exposure of the sensor's middle line
    R: np.ndarray  # world-to-camera at ``time``, world = the head frame (the GT mesh's)
    t: np.ndarray
    gain: float
    head: tuple[np.ndarray, np.ndarray] | None  # head-to-room (R, c) at ``time`` when swaying


@dataclass
class Shot:
    """A capture's scene, camera path and sensor, ready to render any frame or instant."""

    config: SynthConfig
    subject: Subject
    intrinsics: Intrinsics  # of the upright image
    lights: list
    renderer: Renderer
    path: CameraPath  # camera in the room
    target: np.ndarray
    gain_noise: SmoothNoise
    readout: Readout | None
    sway: HeadSway | None
    frames: int
    exposure: float
    uv0: np.ndarray

    def frame_time(self, i: int) -> float:
        """Frame ``i``'s ground-truth instant: mid-exposure of the sensor's middle line."""
        return i / self.config.fps + self.exposure / 2 + self.config.rolling_shutter_s / 2

    def camera(self, time: float):
        """The room-to-camera pose at ``time``: (R, t), or per sensor line (L, 3, 3), (L, 3)
        with a rolling shutter."""
        if self.readout is None:
            return self.path.pose(time)
        poses = [self.path.pose(time + o) for o in self.readout.offsets]
        return np.stack([p[0] for p in poses]), np.stack([p[1] for p in poses])

    def _projection(self, time: float) -> Callable:
        R, t = self.camera(time)
        intr = self.intrinsics
        if self.readout is None:
            return lambda p, valid: project(p, R, t, intr)[0]
        line = self.readout.lines.ravel()
        return lambda p, valid: project_lines(p, R, t, line[valid], intr)

    def render(self, time: float):
        """Linear RGB image of the (blurred) exposure centred on ``time`` (its sensor lines
        at their own times with a rolling shutter; the head at its pose at ``time``), the
        sharp image's hits, and the head's pose."""
        c = self.config
        R, t = self.camera(time)
        head = None if self.sway is None else self.sway.pose(time)
        lines = None if self.readout is None else self.readout.lines
        img, hits = self.renderer.render(R, t, lines, head)
        if c.blur_samples > 1 and self.exposure > 0:
            offsets = np.linspace(-self.exposure / 2, self.exposure / 2, c.blur_samples)
            img = motion_blur(img, hits.points, [self._projection(time + d) for d in offsets],
                               self.uv0)
        return img, hits, head

    def frame(self, i: int) -> FrameRender:
        time = self.frame_time(i)
        img, hits, head = self.render(time)
        gain = float(np.exp(self.config.exposure_drift * self.gain_noise(i / self.config.fps)[0]))
        R, t = self.path.pose(time)
        if head is not None:
            # Head-relative ground truth: x_cam = R (R_h p + c_h) + t for a head-frame p.
            R, t = R @ head[0], R @ head[1] + t
        return FrameRender(img * gain, hits, time, R, t, gain, head)


def prepare(config: SynthConfig) -> Shot:
    """Subject, camera, lights, room and motions of a capture (every random draw)."""
    rng = np.random.default_rng(config.seed)
    subject = make_subject(config)
    intr = draw_intrinsics(config, rng)
    if config.display_rotation_deg in (90, 270):
        # Portrait: the sensor's drawn camera, as seen in the upright image.
        intr = Intrinsics(intr.height, intr.width, intr.fy, intr.fx, intr.cy, intr.cx,
                          intr.k1, intr.k2)
    lights = draw_lights(rng)
    room = (Room.random(np.random.default_rng([config.seed, 2]), plain=config.plain_walls)
            if config.room else None)
    renderer = Renderer(subject, room, intr, lights, config.ambient, config.specular)
    w = np.abs(subject.landmarks[[0, 16], 0]).mean()
    target = np.array([0.0, subject.landmarks[27, 1] * 0.5, 0.3 * w])
    path = CameraPath(config, target, np.random.default_rng([config.seed, 3]))
    gain_noise = SmoothNoise(np.random.default_rng([config.seed, 4]), 1, 0.05, 0.4)
    n_frames = max(2, int(round(config.duration_s * config.fps)))
    exposure = config.exposure_fraction / config.fps
    uv0 = np.stack(np.meshgrid(np.arange(intr.width, dtype=float),
                               np.arange(intr.height, dtype=float)), -1).reshape(-1, 2)
    shot = Shot(config, subject, intr, lights, renderer, path, target, gain_noise,
                rolling_readout(config), None, n_frames, exposure, uv0)
    if config.sway_mm > 0 or config.sway_deg > 0:
        times = np.array([shot.frame_time(i) for i in range(n_frames)])
        shot.sway = HeadSway(np.random.default_rng([config.seed, 6]), config.sway_mm,
                             config.sway_deg, times)
    return shot


SYNTH_OUTPUTS = ("video.mp4", "gt/mesh.ply", "gt/landmarks.json", "gt/cameras.json",
                 "gt/subject.json", "gt/config.yaml", "gt/render.json")
"""What :func:`synthesize` writes into its output folder."""


def synth_inputs(config: SynthConfig) -> list[Path]:
    """The files a capture of ``config`` is rendered from (a mesh subject, its landmarks,
    the ICT model): no result may replace them."""
    named = [config.subject_landmarks, config.ict_model]
    if not (config.subject.startswith("ict:") or config.subject == "james"):
        named.append(Path(config.subject))
    return [Path(p) for p in named if p is not None]


def check_synth_output(out: Path, inputs: list[str | os.PathLike]) -> None:
    """Refuse, before any frame is rendered, an output folder that lies in the artifact
    store or facecap's own folders, or where a result would replace an input or a link
    stands for the ``gt`` folder."""
    gt = out / "gt"
    if gt.is_symlink() or (gt.exists() and not gt.is_dir()):
        raise InputError(f"{gt} is a link or a file where facecap writes the ground truth "
                         "folder; remove it or give another --out")
    check_results_folder(out, default_store_url(), SYNTH_OUTPUTS, inputs)


def synthesize(config: SynthConfig, out_dir: str | Path, progress: bool = True,
               inputs: tuple[str | os.PathLike | None, ...] = ()) -> Capture:
    """Render a capture of ``config`` into ``out_dir`` (see the module docstring).

    The files are rendered in this process's scratch folder and written into ``out_dir``
    as the reconstruction writes its results (:class:`facecap.tasks.outputs.ResultWriter`):
    all at once when every one is made, never through a link, never over an input (the
    subject's mesh and landmarks, the ICT model, ``inputs`` such as a config file)."""
    start = time.perf_counter()
    out = Path(out_dir)
    if config.width % 2 or config.height % 2:
        raise InputError(f"video size {config.width}x{config.height}: H.264 needs even sizes")
    sources = [*synth_inputs(config), *(Path(p) for p in inputs if p is not None)]
    check_synth_output(out, sources)
    with tempfile.TemporaryDirectory(dir=process_scratch()) as scratch:
        frames, seconds = _render(config, Path(scratch), start, progress)
        with ResultWriter(out, sources) as writer:
            for name in SYNTH_OUTPUTS:
                writer.add(name, source=Path(scratch) / name)
            writer.commit()
    gt_dir = out / "gt"
    return Capture(out, out / "video.mp4", gt_dir / "mesh.ply", gt_dir / "landmarks.json",
                   gt_dir / "cameras.json", frames, seconds)


def _render(config: SynthConfig, out: Path, start: float, progress: bool) -> tuple[int, float]:
    """Every file of :data:`SYNTH_OUTPUTS` into the empty folder ``out``; returns the frame
    count and the seconds taken."""
    gt_dir = out / "gt"
    gt_dir.mkdir()
    shot = prepare(config)
    subject, intr = shot.subject, shot.intrinsics
    noise_rng = np.random.default_rng([config.seed, 5])
    seen = np.zeros(len(subject.faces), bool)
    frames_meta = []
    container, stream = _encode(out / "video.mp4", config.width, config.height, config.fps,
                                config.crf, config.codec, config.display_rotation_deg)
    try:
        for i in tqdm(range(shot.frames), desc="render", unit="frame", disable=not progress):
            f = shot.frame(i)
            on_subject = f.hits.mesh == 0
            seen[np.unique(f.hits.triangle[on_subject])] = True
            # Stored as the sensor holds it; the display rotation turns it upright again.
            stored = turn_image(sensor_image(f.image, config, noise_rng),
                                -config.display_rotation_deg)
            frame = av.VideoFrame.from_ndarray(stored, format="rgb24")
            frame.pts = i
            for packet in stream.encode(frame):
                container.mux(packet)
            meta = {"index": i, "time": round(f.time, 6), "R": f.R.round(12).tolist(),
                    "t": f.t.round(9).tolist(), "exposure_gain": round(f.gain, 6)}
            if f.head is not None:
                meta["head_R"] = f.head[0].round(12).tolist()
                meta["head_t"] = f.head[1].round(9).tolist()
            frames_meta.append(meta)
        for packet in stream.encode():
            container.mux(packet)
    finally:
        container.close()

    gt_faces = subject.gt_faces | (subject.optional_faces & seen)
    gt = trimesh.Trimesh(subject.vertices, subject.faces[gt_faces], process=False)
    gt.remove_unreferenced_vertices()
    gt.export(gt_dir / "mesh.ply")
    save_landmarks(gt_dir / "landmarks.json", subject.landmarks, subject=subject.name)
    cameras = {"units": "mm", "convention": "world-to-camera x_cam = R x_world + t (OpenCV); "
               "pixel centres at integer coordinates", "model": "RADIAL (k1, k2)",
               "width": intr.width, "height": intr.height, "fps": config.fps,
               "intrinsics": intr.to_dict(), "frames": frames_meta}
    cameras.update(_conditions_doc(config))
    (gt_dir / "cameras.json").write_text(json.dumps(cameras, indent=1))
    (gt_dir / "subject.json").write_text(json.dumps({"name": subject.name, **subject.info},
                                                    indent=1))
    dump_yaml(config, gt_dir / "config.yaml")
    seconds = time.perf_counter() - start
    render_info = {"intrinsics": intr.to_dict(), "horizontal_fov_deg": intr.horizontal_fov_deg,
                   "lights": [{"direction": d.round(6).tolist(), "intensity": round(s, 6)}
                              for d, s in shot.lights],
                   "ambient": config.ambient, "specular": config.specular,
                   "exposure_s": shot.exposure, "frames": shot.frames,
                   "look_at_target": shot.target.tolist(),
                   "render_seconds": round(seconds, 3)}
    (gt_dir / "render.json").write_text(json.dumps(render_info, indent=1))
    return shot.frames, seconds


def _conditions_doc(config: SynthConfig) -> dict:
    """What ``gt/cameras.json`` says about the phone-like conditions that are on (nothing
    for a default capture, whose file stays as it was)."""
    doc = {}
    if config.display_rotation_deg:
        doc["display_rotation_deg"] = config.display_rotation_deg
        doc["stored_size"] = [config.width, config.height]
        doc["orientation"] = ("width, height and intrinsics are of the upright image (the "
                              "stored frames turned counter-clockwise by display_rotation_deg)")
    if config.rolling_shutter_s > 0:
        doc["rolling_shutter"] = {
            "readout_s": config.rolling_shutter_s, "lines": config.height,
            "meaning": "stored row r (a column of the upright image in portrait) is exposed "
                       "at frames[].time + readout_s * ((r + 0.5) / lines - 0.5); the frame's "
                       "R, t are the pose at frames[].time, mid-exposure of the middle line"}
    if config.sway_mm > 0 or config.sway_deg > 0:
        doc["sway"] = {
            "sway_mm": config.sway_mm, "sway_deg": config.sway_deg,
            "meaning": "the head sways in a still room; world = the head frame (the GT mesh's "
                       "at rest), so R, t are camera relative to the head; head_R, head_t map "
                       "head-frame points into the room at frames[].time: p_room = head_R p + "
                       "head_t (the room-relative camera is R head_R^T, t - R head_R^T head_t)"}
    return doc


def load_gt_cameras(path: str | Path) -> tuple[Intrinsics, list[dict]]:
    """Intrinsics and per-frame poses (R, t as arrays) from a ``gt/cameras.json``."""
    doc = json.loads(Path(path).read_text())
    frames = [{**f, "R": np.asarray(f["R"]), "t": np.asarray(f["t"])} for f in doc["frames"]]
    return Intrinsics.from_dict(doc["intrinsics"]), frames


def write_gt_keyframe_cameras(gt_cameras: str | Path, out_path: str | Path,
                              frame_indices: list[int] | None = None, step: int = 8,
                              scale: float = 1.0, rotation: np.ndarray | None = None,
                              translation: np.ndarray | None = None) -> Path:
    """Convert a synthetic capture's ``gt/cameras.json`` (one pose per video frame) into a
    keyframe ``cameras.json``, in the world ``x' = scale * rotation @ x + translation``.

    Keyframes are ``frame_indices`` or every ``step``-th frame. The transformed world proves
    that a stage relies neither on the ground-truth frame nor on its millimetres.
    """
    intr, poses = load_gt_cameras(gt_cameras)
    Q = np.eye(3) if rotation is None else np.asarray(rotation, float)
    d = np.zeros(3) if translation is None else np.asarray(translation, float)
    wanted = set(frame_indices) if frame_indices is not None else None
    keyframes = []
    for p in poses:
        i = int(p["index"])
        if (wanted is not None and i not in wanted) or (wanted is None and i % step):
            continue
        # x_cam' = scale * x_cam = R Q^T (x' - d) + scale * t
        R = p["R"] @ Q.T
        keyframes.append(KeyframePose(frame_index=i, R=R.tolist(),
                                      t=(scale * p["t"] - R @ d).tolist()))
    cameras = Cameras(convention=CONVENTION,
                      units="arbitrary (ground truth in a transformed world)",
                      intrinsics=CameraIntrinsics(**intr.to_dict()), keyframes=keyframes,
                      world_from_gt=WorldFromGt(scale=scale, rotation=Q.tolist(),
                                                translation=d.tolist()))
    out = Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    return cameras.write(out)
