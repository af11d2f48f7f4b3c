"""Keyframes from a continuous video: Lucas–Kanade tracks and a baseline angle.

Good features are tracked through every frame with pyramidal LK (forward–backward
checked) and re-seeded as they are lost. A new keyframe is due when the view has turned by
``keyframe_angle_deg`` since the last keyframe: the rotation of the essential matrix between
the two frames' tracks, with a nominal focal length. In an ear-to-ear sweep the camera
circles the head while looking at it, so its rotation is the angle travelled around the
head, and the baseline grows with it; no pose or scene model is needed yet. (Raw flow
depends on how much of the picture the head fills; a homography residual ignores any motion
in front of a planar wall.) Of the frames past most of that angle, the sharpest (variance of
the Laplacian) becomes the keyframe, which avoids motion-blurred frames.

The count follows the angle swept, not the frame rate: an ear-to-ear sweep gives about the
same keyframes at 30 or 240 fps.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from pydantic import Field
from tqdm import tqdm

from facecap_core.config import MAX_FRAMES, StrictModel
from facecap_core.errors import InputError
from facecap_core.face import face_box
from facecap_core.photos import probe_photos
from facecap_core.stage import Folders, Stage, capture_in
from facecap_core.video import is_photo_folder, iter_frames, probe


class KeyframeConfig(StrictModel):
    """Lucas–Kanade tracking and keyframe selection (``facecap_core/keyframes.py``)."""

    track_width: int = Field(640, ge=160, le=4096)
    """Frames are tracked at this width (pixels); keyframe positions are full resolution."""
    max_features: int = Field(800, ge=50, le=10000)
    """Features kept per frame."""
    min_features: int = Field(400, ge=20, le=10000)
    """Re-seed new features when fewer than this many are tracked."""
    feature_quality: float = Field(0.005, gt=0, lt=1)
    """Shi–Tomasi quality level relative to the best corner."""
    min_distance_px: int = Field(8, ge=1, le=100)
    """Minimum spacing of features (tracking pixels)."""
    lk_window: int = Field(21, ge=5, le=101)
    """LK window size (tracking pixels)."""
    lk_levels: int = Field(3, ge=0, le=8)
    """LK pyramid levels above the base image."""
    fb_max_px: float = Field(0.7, gt=0, le=10)
    """Largest forward–backward error of a kept track (tracking pixels)."""
    keyframe_angle_deg: float = Field(4.0, gt=0.2, le=45)
    """A keyframe is due when the view has turned this much since the last one."""
    angle_slack: float = Field(0.25, ge=0, lt=1)
    """Frames past (1 - slack) of that angle compete on sharpness to be the keyframe."""
    nominal_hfov_deg: float = Field(65.0, gt=20, lt=150)
    """Horizontal field of view assumed while measuring angles (the true focal comes later)."""
    min_shared_tracks: int = Field(30, ge=8, le=10000)
    """A keyframe is forced when fewer tracks than this link back to the last one."""
    min_frames: int = Field(15, ge=2, le=MAX_FRAMES)
    """Videos with fewer frames are refused."""
    min_keyframes: int = Field(5, ge=2, le=1000)
    """Fewer keyframes than this means the camera did not move enough."""



@dataclass
class Keyframes:
    """Keyframe indices into the video, and the LK tracks observed in them.

    ``observations`` rows are (keyframe number, track id, x, y) in full-resolution pixels.
    """

    indices: list[int]
    times: list[float]
    sharpness: list[float]
    observations: np.ndarray
    video_size: tuple[int, int]
    frames_read: int
    angles_deg: list[float] = field(default_factory=list)  # view angle at each new keyframe
    ordered: bool = True  # video frames in sweep order; photos come in any order
    focal_px: float | None = None  # initial focal length (the photos' EXIF), full resolution

    def tracks_between(self, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
        """Matched pixel positions (N, 2), (N, 2) of tracks seen in keyframes a and b."""
        obs = self.observations
        ka, kb = obs[obs[:, 0] == a], obs[obs[:, 0] == b]
        common, ia, ib = np.intersect1d(ka[:, 1], kb[:, 1], return_indices=True)
        return ka[ia, 2:4], kb[ib, 2:4]


def sharpness(image: np.ndarray) -> float:
    """Variance of the Laplacian of the grey image: falls with motion blur and defocus."""
    grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    return float(cv2.Laplacian(grey, cv2.CV_32F).var())


def _seed(grey: np.ndarray, existing: np.ndarray, config: KeyframeConfig, count: int) -> np.ndarray:
    mask = np.full(grey.shape, 255, np.uint8)
    for x, y in existing:
        cv2.circle(mask, (int(x), int(y)), config.min_distance_px, 0, -1)
    pts = cv2.goodFeaturesToTrack(grey, maxCorners=count, qualityLevel=config.feature_quality,
                                  minDistance=config.min_distance_px, mask=mask, blockSize=7)
    return np.zeros((0, 2), np.float32) if pts is None else pts.reshape(-1, 2)


def _track(prev: np.ndarray, cur: np.ndarray, pts: np.ndarray, config: KeyframeConfig):
    """LK from prev to cur with a forward–backward check; returns new points and a mask."""
    if len(pts) == 0:
        return pts, np.zeros(0, bool)
    lk = dict(winSize=(config.lk_window, config.lk_window), maxLevel=config.lk_levels,
              criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
    p0 = pts.reshape(-1, 1, 2).astype(np.float32)
    p1, st1, _ = cv2.calcOpticalFlowPyrLK(prev, cur, p0, None, **lk)
    p0b, st2, _ = cv2.calcOpticalFlowPyrLK(cur, prev, p1, None, **lk)
    fb = np.linalg.norm(p0b.reshape(-1, 2) - pts, axis=1)
    h, w = cur.shape
    p1 = p1.reshape(-1, 2)
    ok = (st1.ravel() == 1) & (st2.ravel() == 1) & (fb < config.fb_max_px)
    ok &= (p1[:, 0] >= 0) & (p1[:, 0] < w) & (p1[:, 1] >= 0) & (p1[:, 1] < h)
    return p1, ok


def view_angle_deg(a: np.ndarray, b: np.ndarray, focal_px: float, size: tuple[int, int]) -> float:
    """Rotation angle (degrees) between two views from matched points (nan if unknown).

    The essential matrix is estimated with a nominal focal length; a few percent of focal
    error changes the angle by about as much, which is plenty for spacing keyframes.
    """
    if len(a) < 12:
        return float("nan")
    K = np.array([[focal_px, 0, (size[0] - 1) / 2], [0, focal_px, (size[1] - 1) / 2], [0, 0, 1]])
    try:
        E, inliers = cv2.findEssentialMat(a, b, K, cv2.RANSAC, 0.999, 1.0)
    except cv2.error as exc:
        # Matches that determine no motion (a still camera: every point where it was) can
        # leave RANSAC's five-point solver a degenerate polynomial (OpenCV's solvePoly).
        if "solvePoly" not in str(exc):
            raise
        return float("nan")
    if E is None or E.shape != (3, 3):
        return float("nan")
    _, R, _, _ = cv2.recoverPose(E, a, b, K, mask=inliers)
    angle = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))
    # A near-180° turn is the twisted-pair ambiguity of a too-small baseline, not motion.
    return angle if angle < 60 else float("nan")


@dataclass
class HeadMotionProbe:
    """Whether the head moves against a still scene (the camera on a tripod, the subject
    turning): features around the face hold still while those on it move. A still head
    filmed by a moving camera shows the opposite (the scene behind moves more than the
    face). ``windows`` start at evenly spaced frames; each compares the positions of the
    tracks on the face box and outside a margin around it ``span`` frames later."""

    starts: set[int]
    span: int
    open: dict[int, tuple] = field(default_factory=dict)  # start -> (end, box, {id: xy})
    ratios: list[float] = field(default_factory=list)  # outside / face median motion

    @classmethod
    def for_video(cls, frame_count: int, fps: float, windows: int = 12) -> HeadMotionProbe:
        span = max(2, int(round(0.2 * (fps or 30))))  # a fifth of a second
        last = max(1, (frame_count or 30 * windows) - span - 1)
        return cls(set(np.linspace(0, last, windows).astype(int).tolist()), span)

    def update(self, index: int, grey: np.ndarray, ids: np.ndarray, pts: np.ndarray) -> None:
        if index in self.starts:
            found = face_box(grey)
            if found is not None:
                self.open[index] = (index + self.span, found[0], dict(zip(ids.tolist(), pts)))
        for start, (end, box, before) in list(self.open.items()):
            if index == end:
                del self.open[start]
                self._close(box, before, ids, pts)

    def _close(self, box, before: dict, ids: np.ndarray, pts: np.ndarray) -> None:
        left, top, right, bottom = box
        w, h = right - left, bottom - top
        common = [(before[i], p) for i, p in zip(ids.tolist(), pts) if i in before]
        if not common:
            return
        a, b = (np.array(x, float) for x in zip(*common))
        moved = np.linalg.norm(b - a, axis=1)
        x, y = a[:, 0], a[:, 1]
        on_face = (x > left) & (x < right) & (y > top) & (y < bottom)
        # Hair, ears and neck move with the head: "outside" starts well clear of the box.
        near = ((x > left - 0.6 * w) & (x < right + 0.6 * w) & (y > top - 0.8 * h)
                & (y < bottom + 0.4 * h))
        if on_face.sum() >= 10 and (~near).sum() >= 10:
            face = float(np.median(moved[on_face]))
            if face > 1.0:  # the head (or the camera) moved at all
                self.ratios.append(float(np.median(moved[~near])) / face)

    def head_moves(self) -> bool:
        """Most measurable windows show a still scene around a moving face."""
        r = np.array(self.ratios)
        return len(r) >= 3 and float(np.mean(r < 0.25)) > 0.5


def select_keyframes(video: str | Path, config: KeyframeConfig | None = None,
                     progress: bool = False) -> Keyframes:
    """Track through the whole video and pick keyframes (see the module docstring)."""
    # Long on purpose: one pass over the video: decoding, tracking and the selection share the
    # tracker's state frame by frame.
    config = config or KeyframeConfig()
    info = probe(video)
    if info.frame_count and info.frame_count < config.min_frames:
        raise InputError(f"{video} has {info.frame_count} frames; an ear-to-ear capture needs "
                         f"at least {config.min_frames} (record a slow sweep of several seconds)")
    size = (min(config.track_width, info.width),
            int(round(info.height * min(config.track_width, info.width) / info.width)))
    scale = info.width / size[0]
    focal = (size[0] / 2) / np.tan(np.radians(config.nominal_hfov_deg) / 2)

    ids = np.zeros(0, np.int64)
    pts = np.zeros((0, 2), np.float32)
    next_id = 0
    kf_pos: dict[int, np.ndarray] = {}  # track id -> position in the last keyframe
    recent: list[tuple] = []  # (index, time, sharpness, ids, points, angle) since the last keyframe
    keyframes: list[tuple] = []
    angles: list[float] = []
    prev = None
    frames_read = 0
    tracked: list[int] = []  # features held in each frame

    def make_keyframe(entry):
        keyframes.append(entry)
        kf_pos.clear()
        kf_pos.update(zip(entry[3].tolist(), entry[4]))

    probe_motion = HeadMotionProbe.for_video(info.frame_count, info.fps)
    bar = tqdm(total=info.frame_count or None, desc="tracking", unit="frame", disable=not progress)
    for frame in iter_frames(video, width=config.track_width, grey=True):
        grey = frame.image
        frames_read += 1
        bar.update()
        if prev is not None:
            pts, ok = _track(prev, grey, pts, config)
            ids, pts = ids[ok], pts[ok]
        if len(pts) < config.min_features:
            new = _seed(grey, pts, config, config.max_features - len(pts))
            ids = np.concatenate([ids, np.arange(next_id, next_id + len(new))])
            pts = np.concatenate([pts, new]).astype(np.float32)
            next_id += len(new)
        prev = grey
        tracked.append(len(pts))
        probe_motion.update(frame.index, grey, ids, pts)
        if not keyframes:
            make_keyframe((frame.index, frame.time, sharpness(grey), ids.copy(), pts.copy(), 0.0))
            continue
        common = [i for i, tid in enumerate(ids.tolist()) if tid in kf_pos]
        a = np.array([kf_pos[int(ids[i])] for i in common]).reshape(-1, 2)
        angle = view_angle_deg(a, pts[common], focal, size)
        recent.append((frame.index, frame.time, sharpness(grey), ids.copy(), pts.copy(), angle))
        lost = len(common) < config.min_shared_tracks
        if angle >= config.keyframe_angle_deg or lost:
            # The sharpest frame of those far enough from the last keyframe.
            lo = config.keyframe_angle_deg * (1 - config.angle_slack)
            eligible = [e for e in recent if e[5] >= lo] or recent[-1:]
            best = max(eligible, key=lambda e: e[2])
            angles.append(best[5])
            make_keyframe(best)
            recent = [e for e in recent if e[0] > best[0]]
    bar.close()

    if probe_motion.head_moves():
        raise InputError(
            f"{video}: the head moves while the scene around it stands still (the camera "
            f"was fixed in {sum(r < 0.25 for r in probe_motion.ratios)} of "
            f"{len(probe_motion.ratios)} sampled moments): facecap needs a still head and a "
            "moving camera; keep the head still and move the phone round it, ear to ear")
    if frames_read < config.min_frames:
        raise InputError(f"{video} has {frames_read} frames; an ear-to-ear capture needs "
                         f"at least {config.min_frames} (record a slow sweep of several seconds)")
    if np.median(tracked) < config.min_shared_tracks:
        raise InputError(f"{video}: too little texture to track (median {np.median(tracked):.0f}"
                         f" features per frame, need {config.min_shared_tracks}); film a lit, "
                         "detailed scene, not a blank wall")
    if len(keyframes) < config.min_keyframes:
        raise InputError(f"{video}: only {len(keyframes)} keyframe(s) — the camera barely moves "
                         f"(need {config.min_keyframes}); sweep the phone around the head, "
                         "ear to ear")
    rows = []
    for k, entry in enumerate(keyframes):
        full = (entry[4].astype(np.float64) + 0.5) * scale - 0.5  # pixel centres at integers
        rows.append(np.column_stack([np.full(len(entry[3]), k), entry[3], full]))
    return Keyframes(
        indices=[e[0] for e in keyframes], times=[e[1] for e in keyframes],
        sharpness=[e[2] for e in keyframes], observations=np.concatenate(rows),
        video_size=(info.width, info.height), frames_read=frames_read, angles_deg=angles)


def photo_keyframes(folder: str | Path, progress: bool = False) -> Keyframes:
    """Every photo of a photo folder is a keyframe (a photo set is already a selection of
    views); there are no tracks between photos, and their order is not a sweep's."""


    info = probe_photos(folder)
    sharp = [sharpness(f.image) for f in tqdm(iter_frames(folder, width=640, grey=True),
                                               total=len(info.paths), desc="photos",
                                               unit="photo", disable=not progress)]
    n = len(info.paths)
    return Keyframes(indices=list(range(n)), times=[float(i) for i in range(n)],
                     sharpness=sharp, observations=np.zeros((0, 4)),
                     video_size=(info.width, info.height), frames_read=n, ordered=False,
                     focal_px=info.focal_px)


KEYFRAMES_JSON = "keyframes.json"
TRACKS_NPZ = "keyframe_tracks.npz"


def save_keyframes(keyframes: Keyframes, out_dir: str | Path, **meta) -> Path:
    """``keyframes.json`` (indices, times, sharpness, angles, sizes) and the LK observations
    in ``keyframe_tracks.npz`` beside it; returns the JSON path."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out / TRACKS_NPZ, observations=keyframes.observations)
    doc = {
        "frame_indices": [int(i) for i in keyframes.indices],
        "times": [round(float(x), 6) for x in keyframes.times],
        "sharpness": [round(float(x), 3) for x in keyframes.sharpness],
        "angles_deg": [round(float(x), 4) for x in keyframes.angles_deg],
        "video_size": list(keyframes.video_size),
        "ordered": keyframes.ordered,
        "focal_px": keyframes.focal_px,
        "frames_read": int(keyframes.frames_read),
        "tracks": TRACKS_NPZ,
        "observations": "rows (keyframe number, track id, x, y): full-resolution pixels, "
                        "pixel centres at integer coordinates",
        **meta,
    }
    path = out / KEYFRAMES_JSON
    path.write_text(json.dumps(doc, indent=1))
    return path


def load_keyframes(path: str | Path) -> Keyframes:
    """The keyframes written by :func:`save_keyframes`."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"keyframes file not found: {path}; run the keyframe stage first")
    doc = json.loads(path.read_text())
    tracks = path.parent / doc.get("tracks", TRACKS_NPZ)
    if not tracks.is_file():
        raise InputError(f"{tracks} is missing (written with {path.name}); re-run the keyframe "
                         "stage")
    observations = np.load(tracks)["observations"]
    return Keyframes(indices=doc["frame_indices"], times=doc["times"],
                     sharpness=doc["sharpness"], observations=observations,
                     video_size=tuple(doc["video_size"]), frames_read=doc["frames_read"],
                     angles_deg=doc.get("angles_deg", []), ordered=doc.get("ordered", True),
                     focal_px=doc.get("focal_px"))


def main(video: str | Path, out_dir: str | Path, config: KeyframeConfig | None = None,
         progress: bool = False) -> Path:
    """Select the keyframes of ``video`` (a photo folder: all its photos); writes
    ``out_dir/keyframes.json`` (+ tracks)."""


    start, cpu = time.perf_counter(), time.process_time()
    if is_photo_folder(video):
        keyframes = photo_keyframes(video, progress)
    else:
        keyframes = select_keyframes(video, config, progress)
    return save_keyframes(keyframes, out_dir, seconds=round(time.perf_counter() - start, 2),
                          cpu_seconds=round(time.process_time() - cpu, 2))


def run(inputs: Folders, out: Path, config: KeyframeConfig, params: dict) -> None:
    main(capture_in(inputs["video"]), out, config)


STAGE = Stage("keyframes", version="2", inputs=("video",), work_seconds=7.6,
              section="keyframes", run=run, outputs=(KEYFRAMES_JSON, TRACKS_NPZ))
