"""A dataset on disk: subjects, their captures and their scans.

Layout::

    ROOT/<subject>/<capture>.mp4        one or more captures (.mp4, .mov, .m4v, .mkv)
    ROOT/<subject>/<capture>/           or a folder of photos (JPEG/PNG/HEIC) as a capture
    ROOT/<subject>/scan.ply             optional ground-truth scan in mm (.ply/.obj/.stl/.off)
    ROOT/<subject>/scan_landmarks.json  68 3D landmarks of the scan (iBUG order); needed
                                        to score against the scan

Results go to ``OUT/<subject>/<capture>/`` (see :mod:`facecap.flows.capture`). Names may contain
spaces and any Unicode; hidden entries (``.name``) are ignored; nothing outside ROOT is
ever read — a symbolic link that leaves ROOT is refused.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from facecap_core.errors import InputError
from facecap_core.geometry import umeyama
from facecap_core.photos import list_photos

VIDEO_SUFFIXES = (".mp4", ".mov", ".m4v", ".mkv")
SCAN_SUFFIXES = (".ply", ".obj", ".stl", ".off")
LANDMARK_NAMES = ("scan_landmarks.json", "scan_landmarks.ljson", "scan_landmarks.txt")


@dataclass(frozen=True)
class CaptureEntry:
    subject: str
    capture: str
    video: Path
    scan: Path | None
    scan_landmarks: Path | None

    @property
    def name(self) -> str:
        """``subject/capture``: how reports, summaries and the UI name the capture."""
        return f"{self.subject}/{self.capture}"

    def out_dir(self, out_root: str | Path) -> Path:
        return inside(Path(out_root), Path(out_root) / self.subject / self.capture)


SUMMARY_NAMES = ("dataset.json", "consistency.json", "evaluations", "index.html")
"""What the dataset and evaluation flows write at the top of OUT, beside the subjects'
folders."""


def inside(root: Path, path: Path, what: str = "dataset folder") -> Path:
    """``path`` resolved, refusing anything that leaves ``root`` (the ``what``)."""
    root_r = root.resolve()
    resolved = path.resolve()
    if resolved != root_r and root_r not in resolved.parents:
        raise InputError(f"{path} lies outside the {what} {root}; move it inside or "
                         "remove the link")
    return resolved


def _visible(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if not p.name.startswith("."))


def _first(folder: Path, names) -> Path | None:
    for name in names:
        if (folder / name).is_file():
            return folder / name
    return None


def scan_dataset(root: str | Path) -> list[CaptureEntry]:
    """Every capture under ``root`` (sorted by subject, capture)."""
    root = Path(root)
    if not root.is_dir():
        raise InputError(f"dataset folder not found: {root}; check the path")
    entries = []
    for subject in _visible(root):
        if not subject.is_dir():
            continue
        inside(root, subject)
        scan = next((p for p in (subject / f"scan{s}" for s in SCAN_SUFFIXES) if p.is_file()),
                    None)
        landmarks = _first(subject, LANDMARK_NAMES)
        names: dict[str, Path] = {}
        for video in _visible(subject):
            photos = list_photos(video) if video.is_dir() else []
            if video.is_file() and video.suffix.lower() in VIDEO_SUFFIXES:
                name = video.stem
            elif photos:
                name = video.name
                for photo in photos:
                    inside(root, photo)
            else:
                continue
            if name in names:
                raise InputError(f"{names[name].name} and {video.name} in {subject} are both "
                                 f"capture '{name}' (their results would share one folder); "
                                 "rename one")
            names[name] = video
            entries.append(CaptureEntry(
                subject.name, name, inside(root, video),
                inside(root, scan) if scan else None,
                inside(root, landmarks) if landmarks else None))
    if not entries:
        raise InputError(f"no captures in {root}: expected ROOT/<subject>/<capture>.mp4 "
                         f"({', '.join(VIDEO_SUFFIXES)}) or ROOT/<subject>/<capture>/ of photos")
    return entries


def mesh_consistency(a_vertices: np.ndarray, b_vertices: np.ndarray) -> dict:
    """Vertex-to-vertex distances (mm) between two meshes of one subject in template
    topology, after a rigid alignment (the captures' world frames differ): mean, median,
    95th percentile, max."""

    a = np.asarray(a_vertices, float)
    b = np.asarray(b_vertices, float)
    if a.shape != b.shape:
        raise InputError(f"meshes differ in vertex count ({len(a)} vs {len(b)}): not the same "
                         "template topology")
    s, R, t = umeyama(b, a, with_scale=False)
    d = np.linalg.norm(a - (s * b @ R.T + t), axis=1)
    return {"mean_mm": float(d.mean()), "median_mm": float(np.median(d)),
            "p95_mm": float(np.percentile(d, 95)), "max_mm": float(d.max())}
