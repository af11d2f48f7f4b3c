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
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from facecap_core.config import KeyframeConfig
from facecap_core.errors import InputError
from facecap_core.video import iter_frames, probe


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
    E, inliers = cv2.findEssentialMat(a, b, K, cv2.RANSAC, 0.999, 1.0)
    if E is None or E.shape != (3, 3):
        return float("nan")
    _, R, _, _ = cv2.recoverPose(E, a, b, K, mask=inliers)
    angle = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))
    # A near-180° turn is the twisted-pair ambiguity of a too-small baseline, not motion.
    return angle if angle < 60 else float("nan")


def select_keyframes(video: str | Path, config: KeyframeConfig | None = None,
                     progress: bool = False) -> Keyframes:
    """Track through the whole video and pick keyframes (see the module docstring)."""
    from tqdm import tqdm

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
                     angles_deg=doc.get("angles_deg", []))


def main(video: str | Path, out_dir: str | Path, config: KeyframeConfig | None = None,
         progress: bool = False) -> Path:
    """Select the keyframes of ``video``; writes ``out_dir/keyframes.json`` (+ tracks)."""
    import time

    start, cpu = time.perf_counter(), time.process_time()
    keyframes = select_keyframes(video, config, progress)
    return save_keyframes(keyframes, out_dir, seconds=round(time.perf_counter() - start, 2),
                          cpu_seconds=round(time.process_time() - cpu, 2))
