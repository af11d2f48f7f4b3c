"""Is the camera solve right? Checks of the cameras after SfM and after each refinement.

A solve can go wrong without any step failing: on few, low-texture views incremental mapping
may settle on half the focal length with the views scrambled round the head, and the run
then fails stages later for a reason the user cannot act on. Each check here compares the
solve with what it must agree with, and a failure is one line
(:class:`CameraSolveError`: ``the camera solve failed: what — what to try``):

- **focal length** (:func:`focal_problem`): the field of view across the image's long side
  within what phone cameras have (``FOV_RANGE_DEG``);
- **order** (:func:`order_jumps`): consecutive views of the capture (a video's keyframes;
  the photos of a folder numbered at a constant step, a video's frames) must be neighbours
  in the solve: the rotation between them within ``JUMP_FACTOR`` times what the sweep is
  expected to turn between them, and ``MIN_JUMP_DEG``. A video's keyframes: the larger of
  what the tracker measured between them, scaled by how much more the whole solve turns than
  the tracker (:func:`circling_factor`), and the solve's typical turn per frame times the
  frames between them, bounded (:func:`keyframe_steps_deg`); numbered photos: the folder's
  typical step;
- **span** (:func:`span_ratio`): the views' rotation along the sweep, summed, against the
  tracker's (a video): within ``SPAN_RANGE``.

The landmark stage adds the last check, that the landmarks triangulated with the cameras
form a face (:func:`face_problem`).
"""

from __future__ import annotations

import re
from functools import lru_cache
from pathlib import Path

import numpy as np

from facecap_core.assets import packaged_ict_model
from facecap_core.camera import Intrinsics
from facecap_core.errors import InputError
from facecap_core.geometry import umeyama

FOV_RANGE_DEG = (35.0, 100.0)
"""Fields of view (degrees, across the image's long side) a phone camera has: a 2× telephoto
lens is about 35–40° and a front camera's or a wide main camera's about 80°; ultra-wide
lenses (over 100°) are not for face captures. The short side is not held to it: a 16:9
frame of a 60° lens is 35° across its short side, a 2× telephoto's about 22°."""
MIN_JUMP_DEG = 10.0
"""Consecutive views may be this far apart in the solve whatever the tracking says."""
JUMP_FACTOR = 2.0
"""... or this many times the rotation expected between them (keyframes: the tracker's
angle, corrected to the solve's focal length and scaled by the circling factor, or the
frames between them at the solve's typical turn per frame, see :func:`keyframe_steps_deg`;
numbered photos: the folder's typical step)."""
SPAN_RANGE = (1 / 1.5, 2.0)
"""The views' summed rotation along the sweep over the tracker's. The tracker's angle is the
image's motion over the focal length, right for a camera that turns on the spot; one that
circles a face sees the face (near the circle's centre) move less than the room behind it,
so the tracker measures less than the turn, by how much depending on how much of the frame
the face fills: the ratio is ~1 and more (0.73-1.29 on the test suite's rendered captures;
1.46-1.63 on three 512×512 phone-like sweeps through a 50° lens, whose cameras were right to
0.3-0.4°). Under the range the solve has collapsed; over it the solve turns further than a
circling camera explains (a face flattened into a wider turn)."""
NOMINAL_HFOV_DEG = 65.0
"""The field of view across the width that the keyframe tracker measures its angles with
(``KeyframeConfig.nominal_hfov_deg``'s default)."""
CIRCLING_MAX = 2.0
"""Most that the tracker's angles are scaled by for the order check (see
:func:`circling_factor`)."""
UNDER_MEASURED_MAX = 3.0
"""Most that the frames between two keyframes may make of the step between them, in the
tracker's median steps (:func:`keyframe_steps_deg`): the tracker under-measured steps of a
240×320 phone-like sweep by up to 4× (2.7° for 11.7°, 3.9× its median step of 3.0°), and
a camera that pauses piles up frames without turning, which must not excuse a fold there."""
FACE_SHAPE_MAX = 0.2
"""Largest rms distance of the triangulated inner landmarks from a mean face's after a
similarity alignment, as a fraction of the eye-centre distance. Faces differ from the mean
by up to 0.06 (ICT identities at 1 σ, 300 drawn: median 0.030, max 0.060) and 0.15 (at 2 σ:
median 0.064, max 0.150); 2 mm of noise on every point adds 0.05 in quadrature (0.16).
Scrambled points score 0.7, a face three times too deep 0.23."""
MIN_FACE_LANDMARKS = 6
"""Fewest inner landmarks in 3D that can be a face (what the coarse stage needs)."""


class CameraSolveError(InputError):
    """The cameras solved for a capture are wrong: one line saying how, and what to try."""

    def __init__(self, what: str, to_try: str):
        super().__init__(f"the camera solve failed: {what} — {to_try}")
        self.what, self.to_try = what, to_try


def fields_of_view_deg(intr: Intrinsics) -> tuple[float, float]:
    """Field of view across the image's width and across its height (degrees)."""
    return (float(np.degrees(2 * np.arctan2(intr.width / 2, intr.fx))),
            float(np.degrees(2 * np.arctan2(intr.height / 2, intr.fy))))


def focal_problem(intr: Intrinsics) -> str | None:
    """What is wrong with the solve's focal length (None: a phone's)."""
    lo, hi = FOV_RANGE_DEG
    h, v = fields_of_view_deg(intr)
    if lo <= max(h, v) <= hi:
        return None
    return (f"its focal length, {intr.fx:.0f} px, gives a field of view of {h:.0f}° × {v:.0f}°"
            f" ({intr.width}×{intr.height}), outside any phone camera's {lo:.0f}–{hi:.0f}° "
            "across the long side")


def rotation_angles_deg(R) -> np.ndarray:
    """Rotation angle (degrees) between each view and the next."""
    R = np.asarray(R, float)
    if len(R) < 2:
        return np.zeros(0)
    trace = np.einsum("kij,kij->k", R[1:], R[:-1])  # trace(R_{k+1} R_k^T)
    return np.degrees(np.arccos(np.clip((trace - 1) / 2, -1, 1)))


def tracked_steps_deg(angles_deg, positions, width: int, fx: float) -> np.ndarray | None:
    """The tracker's rotation between consecutive registered keyframes (degrees), corrected
    from its nominal focal length to ``fx``: ``angles_deg[j]`` is its angle from keyframe j
    to j + 1 and ``positions`` the registered keyframes' numbers, ascending. An angle the
    tracker could not measure (a keyframe forced by lost tracks) counts as the median of the
    others; None when most are unknown."""
    angles = np.asarray(angles_deg, float)
    positions = np.asarray(positions, np.int64)
    if len(positions) < 2 or len(angles) < positions[-1]:
        return None
    known = np.isfinite(angles)
    if known.sum() < max(2, 0.5 * len(angles)):
        return None
    angles = np.where(known, angles, np.median(angles[known]))
    # In small turns the image moves by focal × angle: the tracker's angle is the image's
    # motion over its nominal focal length.
    nominal_fx = (width / 2) / np.tan(np.radians(NOMINAL_HFOV_DEG) / 2)
    cumulative = np.r_[0.0, np.cumsum(angles)]
    return np.diff(cumulative[positions]) * nominal_fx / fx


def circling_factor(steps_deg, expected_deg) -> float:
    """How much further the solve turns than the tracker measures, step by step: the lower
    quartile of the steps' ratios, within 1 and ``CIRCLING_MAX``. A camera circling a face
    sees the face move less than its turn, by a share that depends on how much of the frame
    the face fills, the same all along the sweep (1.46-1.63 in all on phone-like 512×512
    sweeps through a 50° lens): the order check measures each step against the tracker's
    angle times this. Views out of order lengthen steps: the lower quartile stays with the
    steps in order unless three in four are lengthened."""
    steps, expected = np.asarray(steps_deg, float), np.asarray(expected_deg, float)
    known = expected > 0
    if not known.any():
        return 1.0
    ratio = np.quantile(steps[known] / expected[known], 0.25)
    return float(np.clip(ratio, 1.0, CIRCLING_MAX))


def keyframe_steps_deg(steps_deg, tracked_deg, frames) -> tuple[np.ndarray, float]:
    """The rotation expected between a video's consecutive keyframes ``frames`` (ascending
    frame numbers), and the :func:`circling_factor` it scales the tracking by: the larger of
    the tracker's angle times that factor and the solve's typical turn per frame times the
    frames between them (:func:`numbered_steps_deg`), the latter at most
    ``UNDER_MEASURED_MAX`` of the scaled tracking's median step. The tracker's angle is an
    essential matrix's rotation over the tracks shared with the last keyframe; where they are
    lost (low texture, small frames) the next keyframe is forced with whatever angle they
    last gave: 2.7° for a right 11.7° step over 6 frames of a 240×320 phone-like render. The
    frames between keyframes count a sweep's steady turn; a sweep that speeds up is covered
    by the tracker, one that pauses by the bound; a view out of order jumps against both."""
    steps = np.asarray(steps_deg, float)
    factor = circling_factor(steps, tracked_deg)
    tracked = np.asarray(tracked_deg, float) * factor
    by_frames = np.minimum(numbered_steps_deg(steps, frames),
                           UNDER_MEASURED_MAX * np.median(tracked))
    return np.maximum(tracked, by_frames), factor


def order_jumps(steps_deg, expected_deg) -> np.ndarray:
    """Indices k where views k and k + 1 of the capture are further apart in the solve than
    consecutive views can be: over ``MIN_JUMP_DEG`` and ``JUMP_FACTOR`` × expected."""
    steps, expected = np.asarray(steps_deg, float), np.asarray(expected_deg, float)
    return np.flatnonzero(steps > np.maximum(MIN_JUMP_DEG, JUMP_FACTOR * expected))


def numbered_steps_deg(steps_deg, numbers) -> np.ndarray:
    """Expected rotation between consecutive numbered photos (a video's frames): the
    folder's typical rotation per number (the lower quartile of the solve's steps, which
    a scrambled minority cannot raise) times the numbers between them."""
    gaps = np.diff(np.asarray(numbers, float))
    rate = np.quantile(np.asarray(steps_deg, float) / gaps, 0.25)
    return rate * gaps


def span_ratio(steps_deg, expected_deg) -> float:
    """The solve's summed rotation along the sweep over the tracker's."""
    tracked = float(np.sum(expected_deg))
    return float(np.sum(steps_deg)) / tracked if tracked > 0 else float("nan")


_NUMBERED = re.compile(r"^(.*?)(\d+)(\D*)$")


def frame_numbers(names) -> np.ndarray | None:
    """The frame numbers of photo file names that are a video's frames in order: one
    pattern (``frame_0001.jpg``, ``IMG_1234.JPG``) whose numbers rise at a constant step
    (every frame, every third, ...). None for other folders: a photo set may be numbered
    in the order the photos were taken, not along the sweep."""
    parts = [_NUMBERED.match(Path(n).stem) for n in names]
    if len(parts) < 3 or not all(parts):
        return None
    if len({(p.group(1), Path(n).suffix.lower()) for p, n in zip(parts, names)}) != 1:
        return None
    numbers = np.array([int(p.group(2)) for p in parts])
    steps = np.diff(numbers)
    if steps[0] <= 0 or np.any(steps != steps[0]):
        return None
    return numbers


def order_problem(R, expected_deg, labels, kind: str) -> str | None:
    """What is wrong with the order of the views ``R`` (in capture order; ``labels`` name
    them) against the rotation ``expected_deg`` expected between consecutive ones; None when
    they are in order."""
    steps = rotation_angles_deg(R)
    expected_deg = np.asarray(expected_deg, float)
    jumps = order_jumps(steps, expected_deg)
    if not len(jumps):
        return None
    k = int(jumps[np.argmax(steps[jumps] - expected_deg[jumps])])
    return (f"{len(jumps)} of {len(steps)} steps between consecutive {kind} turn further "
            f"than the sweep does (the views are out of order round the head): {labels[k]} "
            f"and {labels[k + 1]} are {steps[k]:.0f}° apart in the solve, where the sweep turns "
            f"~{expected_deg[k]:.0f}° between them")


def span_problem(R, expected_deg) -> str | None:
    """What is wrong with the views' total turn against the tracker's (None: none)."""
    steps = rotation_angles_deg(R)
    ratio = span_ratio(steps, expected_deg)
    if not np.isfinite(ratio) or SPAN_RANGE[0] <= ratio <= SPAN_RANGE[1]:
        return None
    return (f"its views turn {np.sum(steps):.0f}° in all along the sweep where the video's "
            f"tracking measured ~{np.sum(expected_deg):.0f}°")


def face_shape_error(landmarks, reference) -> tuple[int, float]:
    """How far the inner landmarks ``landmarks`` (68, 3; NaN where missing) are from a face:
    the count of finite inner points, and their rms distance from ``reference``'s (a mean
    face's 68 points) after the best similarity alignment, per the reference's eye-centre
    distance (inf with fewer than 4 points)."""
    L, ref = np.asarray(landmarks, float), np.asarray(reference, float)
    inner = np.arange(17, 68)
    ok = inner[np.all(np.isfinite(L[inner]), axis=1)]
    if len(ok) < 4:
        return len(ok), float("inf")
    scale, rot, t = umeyama(L[ok], ref[ok], with_scale=True)
    residual = ref[ok] - (scale * L[ok] @ rot.T + t)
    eyes = float(np.linalg.norm(ref[42:48].mean(0) - ref[36:42].mean(0)))
    return len(ok), float(np.sqrt((residual ** 2).sum(1).mean()) / eyes)


def _steps(poses, keyframes, numbers=None):
    """The views of ``poses`` in capture order (rotations, frame numbers; photos without an
    order in their names: in the poses' own, sweep order), the solve's rotation between
    consecutive ones and what the capture says it is (None where it says nothing)."""
    ordered = keyframes.ordered or numbers is not None
    order = np.argsort(poses.frame_indices) if ordered else np.arange(len(poses.R))
    R = np.asarray(poses.R, float)[order]
    frames = np.asarray(poses.frame_indices, np.int64)[order]
    steps = rotation_angles_deg(R)
    expected = None
    if len(frames) < 3:
        pass
    elif keyframes.ordered:
        position = {int(i): k for k, i in enumerate(keyframes.indices)}
        expected = tracked_steps_deg(keyframes.angles_deg, [position[int(i)] for i in frames],
                                     poses.intrinsics.width, poses.intrinsics.fx)
    elif numbers is not None:
        expected = numbered_steps_deg(steps, np.asarray(numbers)[frames])
    return R, frames, steps, expected


def solve_problem(poses, keyframes, numbers=None, names=None) -> str | None:
    """What is wrong with the cameras ``poses`` (a :class:`~facecap_core.pose.colmap_sfm.
    Poses`) of ``keyframes``: the focal length, the views' order (a video's keyframes, or
    photos whose file names give ``numbers``, see :func:`frame_numbers`; ``names`` the
    photos' file names) and a video's span against its tracking; None when nothing is."""
    problem = focal_problem(poses.intrinsics)
    if problem:
        return problem
    R, frames, _, expected = _steps(poses, keyframes, numbers)
    if expected is None:
        return None
    if keyframes.ordered:
        allowed, _ = keyframe_steps_deg(rotation_angles_deg(R), expected, frames)
        return (order_problem(R, allowed, [f"frame {i}" for i in frames], "keyframes")
                or span_problem(R, expected))
    labels = [str(names[i]) if names is not None else f"photo {i}" for i in frames]
    return order_problem(R, expected, labels, "photos (by file name)")


def solve_figures(poses, keyframes, numbers=None) -> dict:
    """The solve's own figures for the run's report: focal length, principal point (and
    whether it was held at the image centre) and field of view; the sparse points'
    reprojection error and track length; the views' turn along the sweep, against the
    tracker's, and the largest step between consecutive views over the step expected (a
    video: :func:`keyframe_steps_deg`, with the :func:`circling_factor`; the order check's
    ratio: jumps are over 2)."""
    intr = poses.intrinsics
    doc = {"focal_px": round(float(intr.fx), 2),
           "principal_point_px": [round(float(intr.cx), 2), round(float(intr.cy), 2)],
           "principal_point_held": bool(poses.principal_point_held),
           "field_of_view_deg": [round(x, 2) for x in fields_of_view_deg(intr)]}
    obs = np.asarray(poses.observations, float)
    if len(obs) and len(poses.points):
        R, t = np.asarray(poses.R, float), np.asarray(poses.t, float)
        point, view = obs[:, 0].astype(np.int64), obs[:, 1].astype(np.int64)
        cam = np.einsum("nij,nj->ni", R[view], poses.points[point]) + t[view]
        xy = cam[:, :2] / np.where(np.abs(cam[:, 2:]) > 1e-12, cam[:, 2:], 1e-12)
        r2 = (xy ** 2).sum(1, keepdims=True)
        xy = xy * (1 + intr.k1 * r2 + intr.k2 * r2 ** 2)
        pixels = xy * [intr.fx, intr.fy] + [intr.cx, intr.cy]
        error = np.linalg.norm(pixels - obs[:, 2:4], axis=1)
        doc["reprojection_px"] = {"median": round(float(np.median(error)), 3),
                                  "rms": round(float(np.sqrt(np.mean(error ** 2))), 3)}
        doc["track_length"] = round(float(len(obs) / len(poses.points)), 2)
    _, frames, steps, expected = _steps(poses, keyframes, numbers)
    doc["turn_deg"] = round(float(steps.sum()), 1)
    if expected is not None:
        if keyframes.ordered:
            doc["tracked_turn_deg"] = round(float(np.sum(expected)), 1)
            expected, factor = keyframe_steps_deg(steps, expected, frames)  # as the check
            doc["circling_factor"] = round(factor, 3)
        floor = np.maximum(expected, MIN_JUMP_DEG / JUMP_FACTOR)
        doc["largest_step_ratio"] = round(float(np.max(steps / floor)), 3)
    return doc


@lru_cache(maxsize=1)
def mean_face_landmarks() -> np.ndarray:
    """The 68 landmarks (mm) of the ICT Face Model's mean face (the packaged trimmed model),
    the face :func:`face_shape_error` measures against."""
    with np.load(packaged_ict_model(), allow_pickle=False) as model:
        return model["mean_vertices"][model["landmarks68"]].astype(float) * 10.0


def face_problem(landmarks) -> str | None:
    """What is wrong with triangulated landmarks (68, 3; NaN where missing) as a face:
    fewer than ``MIN_FACE_LANDMARKS`` inner ones, or a shape further than
    ``FACE_SHAPE_MAX`` from a mean face's (None: they form a face)."""
    count, error = face_shape_error(landmarks, mean_face_landmarks())
    if count < MIN_FACE_LANDMARKS:
        return (f"only {count} of the face's 51 inner landmarks could be placed in 3D from its "
                "views (the cameras do not see one face)")
    if error > FACE_SHAPE_MAX:
        return (f"the face's landmarks triangulated with its cameras do not form a face (rms "
                f"{error:.2f} eye distances from a mean face's after alignment, where faces "
                f"stay under {FACE_SHAPE_MAX:.2f})")
    return None
