"""Accuracy and completion of an aligned mesh, per capture and averaged as in Table 1."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from facecap_core.errors import InputError
from facecap_core.evaluation.alignment import (
    PROTOCOLS,
    Alignment,
    EvaluationConfig,
    Protocol,
    Surface,
    align_to_surface,
)
from facecap_core.evaluation.region import check_landmarks, region_sphere
from facecap_core.meshio import load_landmarks, load_mesh


@dataclass
class Stats:
    """Summary of one side's distances (mm) inside the face region."""

    mean: float
    std: float
    median: float
    under_1mm: float  # fraction of distances < 1 mm
    under_2mm: float  # fraction of distances < 2 mm
    count: int

    @classmethod
    def of(cls, d: np.ndarray) -> Stats:
        """Statistics of the finite distances in ``d`` (nan everywhere when there are none)."""
        d = np.asarray(d, float)
        d = d[np.isfinite(d)]
        if len(d) == 0:
            nan = float("nan")
            return cls(nan, nan, nan, nan, nan, 0)
        return cls(float(d.mean()), float(d.std()), float(np.median(d)),
                   float(np.mean(d < 1.0)), float(np.mean(d < 2.0)), int(len(d)))

    def to_dict(self) -> dict:
        return {"mean": self.mean, "std": self.std, "median": self.median,
                "under_1mm": self.under_1mm, "under_2mm": self.under_2mm, "count": self.count}


@dataclass
class Score:
    """Result of :func:`score` for one protocol.

    ``accuracy_per_vertex`` has one entry per mesh vertex and ``completion_per_vertex`` one
    per scan vertex: the distance in mm, nan outside the face region — ready for
    :func:`error_heatmap` (accuracy on the *aligned* mesh: ``alignment.apply(vertices)``).
    """

    protocol: str
    accuracy: Stats
    completion: Stats
    scale: float
    alignment: Alignment
    accuracy_per_vertex: np.ndarray = field(repr=False)
    completion_per_vertex: np.ndarray = field(repr=False)

    @property
    def matrix(self) -> np.ndarray:
        """4×4 transform from mesh to scan coordinates."""
        return self.alignment.matrix

    def to_dict(self) -> dict:
        """JSON-ready summary (no per-vertex arrays)."""
        return {"protocol": self.protocol, "accuracy": self.accuracy.to_dict(),
                "completion": self.completion.to_dict(), "scale": self.scale,
                "matrix": self.matrix.tolist(), "icp_iterations": self.alignment.iterations,
                "icp_rms": self.alignment.rms}


def score(mesh_vertices: np.ndarray, mesh_faces: np.ndarray, scan_vertices: np.ndarray,
          scan_faces: np.ndarray, scan_landmarks: np.ndarray,
          mesh_landmarks: np.ndarray | None = None, protocol: Protocol = "similarity",
          config: EvaluationConfig | None = None) -> Score:
    """Align the mesh to the scan under ``protocol`` and measure accuracy and completion.

    ``"similarity"`` fits a scale, ``"metric"`` does not (the score's ``scale`` is then 1).
    Distances are in the scan's units (mm), inside the scan's face sphere.
    """
    config = config or EvaluationConfig()
    if protocol not in PROTOCOLS:
        raise InputError(f"unknown evaluation protocol {protocol!r}; use one of {', '.join(PROTOCOLS)}")
    scan_lm = check_landmarks(scan_landmarks, "scan")
    scan = Surface(scan_vertices, scan_faces)
    al = align_to_surface(mesh_vertices, scan, scan_lm, mesh_landmarks, protocol == "similarity", config)

    centre, radius = region_sphere(scan_lm, config.radius_factor)
    moved = al.apply(mesh_vertices)
    acc = np.full(len(moved), np.nan)
    in_mesh = np.linalg.norm(moved - centre, axis=1) <= radius
    acc[in_mesh] = scan.closest(moved[in_mesh])[1]

    sv = np.asarray(scan_vertices, float)
    comp = np.full(len(sv), np.nan)
    in_scan = np.linalg.norm(sv - centre, axis=1) <= radius
    comp[in_scan] = Surface(moved, mesh_faces).closest(sv[in_scan])[1]

    return Score(protocol=protocol, accuracy=Stats.of(acc), completion=Stats.of(comp),
                 scale=al.s, alignment=al, accuracy_per_vertex=acc, completion_per_vertex=comp)


_JSON_STATS = ("mean", "std", "median", "under_1mm", "under_2mm")


def score_json(score: Score) -> dict:
    """The per-capture record used by reports and :func:`paper_table`.

    ``{"protocol", "accuracy": {mean, std, median, under_1mm, under_2mm}, "completion": {...},
    "scale"}``: distances in mm, fractions in [0, 1], ``scale`` the fitted mesh→scan scale.
    """
    def side(st: Stats) -> dict:
        return {k: float(getattr(st, k)) for k in _JSON_STATS}

    return {"protocol": score.protocol, "accuracy": side(score.accuracy),
            "completion": side(score.completion), "scale": float(score.scale)}


def evaluate(mesh_path: str | Path, scan_path: str | Path,
             scan_landmarks_path: str | Path | None = None,
             mesh_landmarks_path: str | Path | None = None,
             protocols: Sequence[str] = PROTOCOLS,
             config: EvaluationConfig | None = None) -> dict[str, Score]:
    """Score a mesh file against a scan file under each protocol; ``{protocol: Score}``.

    The scan's landmarks (68 3-D points, iBUG order, in the scan's frame) are required: they
    define the face region. The mesh's landmarks are optional and only initialise alignment.
    """
    config = config or EvaluationConfig()
    unknown = [p for p in protocols if p not in PROTOCOLS]
    if unknown or not protocols:
        raise InputError(f"unknown evaluation protocol(s) {unknown or '(none given)'}; "
                         f"use {' and/or '.join(PROTOCOLS)}")
    if scan_landmarks_path is None:
        raise InputError(f"scan {scan_path} has no landmarks: pass --scan-landmarks FILE "
                         "(68 points, iBUG order) so the face region can be cut")
    mesh = load_mesh(mesh_path, "mesh")
    scan = load_mesh(scan_path, "scan")
    scan_lm = load_landmarks(scan_landmarks_path, expected=68)
    if scan_lm.shape[1] != 3:
        raise InputError(f"scan landmark file {scan_landmarks_path} holds 2-D points; the face "
                         "region needs 3-D landmarks in the scan's frame")
    mesh_lm = None
    if mesh_landmarks_path is not None:
        mesh_lm = load_landmarks(mesh_landmarks_path, expected=68)
        if mesh_lm.shape[1] != 3:
            raise InputError(f"mesh landmark file {mesh_landmarks_path} holds 2-D points; "
                             "alignment needs 3-D landmarks in the mesh's frame")
    return {p: score(mesh.vertices, mesh.faces, scan.vertices, scan.faces, scan_lm, mesh_lm,
                     protocol=p, config=config)
            for p in dict.fromkeys(protocols)}


def paper_table(rows: Sequence[tuple[str, Sequence[dict]]]) -> str:
    """A Markdown table in the layout of Agrawal et al. 2020, Table 1.

    ``rows`` are ``(method name, [per-capture record from score_json, ...])``. Per method and
    side, *mean* is the mean over captures of the per-capture mean, *std* the (population)
    standard deviation over captures of the per-capture mean (0 for one capture), and *median*
    the mean over captures of the per-capture median — the paper averages per-subject figures
    over subjects. Values in mm with two decimals; the convention is repeated as a footnote.
    """
    lines = ["| Method | Captures | Accuracy mean | std | median | Completion mean | std | median |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for name, records in rows:
        cells = [str(name).replace("|", "\\|"), str(len(records))]
        for side in ("accuracy", "completion"):
            means = np.array([r[side]["mean"] for r in records], float)
            medians = np.array([r[side]["median"] for r in records], float)
            if len(records) == 0:
                cells += ["–"] * 3
            else:
                cells += [f"{means.mean():.2f}", f"{means.std():.2f}", f"{medians.mean():.2f}"]
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "Distances in mm. Mean: mean over captures of the per-capture mean; std: "
              "standard deviation over captures of the per-capture mean (0 for one capture); "
              "median: mean over captures of the per-capture median."]
    return "\n".join(lines)
