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
    Protocol,
    Surface,
    align_to_surface,
)
from facecap_core.evaluation.region import check_landmarks, ear_region, face_region
from facecap_core.evaluation.settings import EvaluationConfig
from facecap_core.meshio import load_landmarks, load_mesh


@dataclass
class Stats:
    """Summary of one side's distances (mm) inside a region."""

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
class RegionScore:
    """Accuracy and completion inside one region; the per-vertex distances (mm) are nan
    outside it (one per mesh vertex, one per scan vertex)."""

    accuracy: Stats
    completion: Stats
    accuracy_per_vertex: np.ndarray = field(repr=False)
    completion_per_vertex: np.ndarray = field(repr=False)

    def to_dict(self) -> dict:
        return {"accuracy": self.accuracy.to_dict(), "completion": self.completion.to_dict()}


@dataclass
class Score:
    """Result of :func:`score` for one protocol.

    ``accuracy`` and ``completion`` are the face sphere's, ``ears`` the ear region's (after
    the same alignment). ``accuracy_per_vertex`` has one entry per mesh vertex and
    ``completion_per_vertex`` one per scan vertex: the distance in mm, nan outside the face
    region — ready for :func:`error_heatmap` (accuracy on the *aligned* mesh:
    ``alignment.apply(vertices)``).
    """

    protocol: str
    accuracy: Stats
    completion: Stats
    scale: float
    alignment: Alignment
    accuracy_per_vertex: np.ndarray = field(repr=False)
    completion_per_vertex: np.ndarray = field(repr=False)
    ears: RegionScore

    @property
    def matrix(self) -> np.ndarray:
        """4×4 transform from mesh to scan coordinates."""
        return self.alignment.matrix

    def to_dict(self) -> dict:
        """JSON-ready summary (no per-vertex arrays)."""
        return {"protocol": self.protocol, "accuracy": self.accuracy.to_dict(),
                "completion": self.completion.to_dict(), "ears": self.ears.to_dict(),
                "scale": self.scale, "matrix": self.matrix.tolist(),
                "icp_iterations": self.alignment.iterations, "icp_rms": self.alignment.rms}


def score(mesh_vertices: np.ndarray, mesh_faces: np.ndarray, scan_vertices: np.ndarray,
          scan_faces: np.ndarray, scan_landmarks: np.ndarray,
          mesh_landmarks: np.ndarray | None = None, protocol: Protocol = "similarity",
          config: EvaluationConfig | None = None) -> Score:
    """Align the mesh to the scan under ``protocol`` and measure accuracy and completion.

    ``"similarity"`` fits a scale, ``"metric"`` does not (the score's ``scale`` is then 1).
    Distances are in the scan's units (mm), inside the scan's face sphere and, for
    ``Score.ears``, its ear region; the alignment uses the face sphere only.
    """
    config = config or EvaluationConfig()
    if protocol not in PROTOCOLS:
        raise InputError(f"unknown evaluation protocol {protocol!r}; use one of {', '.join(PROTOCOLS)}")
    scan_lm = check_landmarks(scan_landmarks, "scan")
    scan = Surface(scan_vertices, scan_faces)
    al = align_to_surface(mesh_vertices, scan, scan_lm, mesh_landmarks, protocol == "similarity", config)

    moved = al.apply(mesh_vertices)
    sv = np.asarray(scan_vertices, float)
    mesh_surface = Surface(moved, mesh_faces)

    def region_score(in_region) -> RegionScore:
        """Distances of the mesh and scan vertices that ``in_region`` keeps (both regions
        are cut on the scan's landmarks, so they are the same place on mesh and scan)."""
        acc = np.full(len(moved), np.nan)
        in_mesh = in_region(moved)
        acc[in_mesh] = scan.closest(moved[in_mesh])[1]
        comp = np.full(len(sv), np.nan)
        in_scan = in_region(sv)
        comp[in_scan] = mesh_surface.closest(sv[in_scan])[1]
        return RegionScore(Stats.of(acc), Stats.of(comp), acc, comp)

    face = region_score(lambda v: face_region(v, scan_lm, config.radius_factor))
    ears = region_score(lambda v: ear_region(v, scan_lm, config.radius_factor))
    return Score(protocol=protocol, accuracy=face.accuracy, completion=face.completion,
                 scale=al.s, alignment=al, accuracy_per_vertex=face.accuracy_per_vertex,
                 completion_per_vertex=face.completion_per_vertex, ears=ears)


_JSON_STATS = ("mean", "std", "median", "under_1mm", "under_2mm")


def score_json(score: Score) -> dict:
    """The per-capture record used by reports and :func:`paper_table`.

    ``{"protocol", "accuracy": {mean, std, median, under_1mm, under_2mm}, "completion": {...},
    "scale", "ears": {"accuracy": {...}, "completion": {...}}}``: distances in mm, fractions in
    [0, 1], ``scale`` the fitted mesh→scan scale; ``accuracy`` and ``completion`` are the face
    sphere's, ``ears`` holds the ear region's (None where a region holds no vertex: strict
    JSON has no nan).
    """
    def side(st: Stats) -> dict:
        return {k: float(v) if np.isfinite(v := getattr(st, k)) else None for k in _JSON_STATS}

    return {"protocol": score.protocol, "accuracy": side(score.accuracy),
            "completion": side(score.completion), "scale": float(score.scale),
            "ears": {"accuracy": side(score.ears.accuracy),
                     "completion": side(score.ears.completion)}}


SLIVER = 1e-12
"""A triangle whose area is below this fraction of the squared extent of its mesh is a
point or a line (float rounding leaves a collinear triangle ~1e-16 of it)."""


def check_surface(vertices: np.ndarray, faces: np.ndarray, path: str | Path, what: str) -> None:
    """Refuse a mesh none of whose triangles has an area: distances to it are distances to
    its vertices, so a cloud of the scan's own points would score 1e-14 mm."""
    v = np.asarray(vertices, float)
    corners = v[np.asarray(faces, np.int64).reshape(-1, 3)]
    areas = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0],
                                          corners[:, 2] - corners[:, 0]), axis=1)
    extent = float(np.ptp(v, axis=0).max()) if len(v) else 0.0
    if not np.any(areas > SLIVER * extent ** 2):
        raise InputError(f"{what} file {path} has no triangle with an area (every one is a "
                         "point or a line); repair the mesh")


def evaluate(mesh_path: str | Path, scan_path: str | Path,
             scan_landmarks_path: str | Path | None = None,
             mesh_landmarks: str | Path | np.ndarray | None = None,
             protocols: Sequence[str] = PROTOCOLS,
             config: EvaluationConfig | None = None) -> dict[str, Score]:
    """Score a mesh file against a scan file under each protocol; ``{protocol: Score}``.

    The scan's landmarks (68 3-D points, iBUG order, in the scan's frame) are required: they
    define the face region. The mesh's landmarks are optional and only initialise alignment:
    a landmark file, or the 68 points themselves as an array (the template's landmark
    vertices of a mesh in its topology, which need no file).
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
    check_surface(mesh.vertices, mesh.faces, mesh_path, "mesh")
    scan = load_mesh(scan_path, "scan")
    check_surface(scan.vertices, scan.faces, scan_path, "scan")
    scan_lm = load_landmarks(scan_landmarks_path, expected=68)
    if scan_lm.shape[1] != 3:
        raise InputError(f"scan landmark file {scan_landmarks_path} holds 2-D points; the face "
                         "region needs 3-D landmarks in the scan's frame")
    mesh_lm = None
    if isinstance(mesh_landmarks, np.ndarray):
        mesh_lm = np.asarray(mesh_landmarks, float)
        if mesh_lm.shape != (68, 3) or not np.all(np.isfinite(mesh_lm)):
            raise InputError(f"the mesh's landmarks are an array of shape {mesh_lm.shape}; "
                             "alignment needs 68 finite 3-D points in the mesh's frame")
    elif mesh_landmarks is not None:
        mesh_lm = load_landmarks(mesh_landmarks, expected=68)
        if mesh_lm.shape[1] != 3:
            raise InputError(f"mesh landmark file {mesh_landmarks} holds 2-D points; "
                             "alignment needs 3-D landmarks in the mesh's frame")
    return {p: score(mesh.vertices, mesh.faces, scan.vertices, scan.faces, scan_lm, mesh_lm,
                     protocol=p, config=config)
            for p in dict.fromkeys(protocols)}


REGIONS = ("face", "ears")
"""The regions :func:`paper_table` can tabulate: the face sphere and the ear region."""


def paper_table(rows: Sequence[tuple[str, Sequence[dict]]], region: str = "face") -> str:
    """A Markdown table in the layout of Agrawal et al. 2020, Table 1, for one region.

    ``rows`` are ``(method name, [per-capture record from score_json, ...])``; ``region`` is
    ``"face"`` (the face sphere) or ``"ears"`` (the ear region, ``record["ears"]``). Per method
    and side, *mean* is the mean over captures of the per-capture mean, *std* the (population)
    standard deviation over captures of the per-capture mean (0 for one capture), and *median*
    the mean over captures of the per-capture median — the paper averages per-subject figures
    over subjects. A capture whose region holds no vertex on a side (nan; or a record from
    before the ear region) is left out of that side's figures, "–" when none is left. Values
    in mm with two decimals; the convention is repeated as a footnote.
    """
    if region not in REGIONS:
        raise InputError(f"unknown evaluation region {region!r}; use one of {', '.join(REGIONS)}")
    nan_side = {"mean": float("nan"), "median": float("nan")}
    lines = ["| Method | Captures | Accuracy mean | std | median | Completion mean | std | median |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for name, records in rows:
        cells = [str(name).replace("|", "\\|"), str(len(records))]
        figures = [r if region == "face" else r.get("ears", {}) for r in records]
        for side in ("accuracy", "completion"):
            means = np.array([f.get(side, nan_side)["mean"] for f in figures], float)
            medians = np.array([f.get(side, nan_side)["median"] for f in figures], float)
            kept = np.isfinite(means) & np.isfinite(medians)
            if not kept.any():
                cells += ["–"] * 3
            else:
                means, medians = means[kept], medians[kept]
                cells += [f"{means.mean():.2f}", f"{means.std():.2f}", f"{medians.mean():.2f}"]
        lines.append("| " + " | ".join(cells) + " |")
    where = ("" if region == "face" else
             "Ear region: inside either ear sphere, outside the face sphere. ")
    lines += ["", f"{where}Distances in mm. Mean: mean over captures of the per-capture mean; "
              "std: standard deviation over captures of the per-capture mean (0 for one "
              "capture); median: mean over captures of the per-capture median."]
    return "\n".join(lines)
