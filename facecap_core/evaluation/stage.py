"""The evaluation stage: score the fitting stage's mesh against a scan, write the figures."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from facecap_core.errors import InputError
from facecap_core.evaluation.alignment import PROTOCOLS, Alignment
from facecap_core.evaluation.figures import error_heatmap
from facecap_core.evaluation.scoring import evaluate, score_json
from facecap_core.evaluation.settings import EvaluationConfig
from facecap_core.fitting.run import MESH_LANDMARKS, MESH_PLY
from facecap_core.meshio import load_mesh
from facecap_core.stage import Folders, Stage
from facecap_core.template import Template

EVALUATION_JSON = "evaluation.json"
ACCURACY_NPY = "accuracy_{protocol}.npy"
"""Each mesh vertex's distance to the scan (mm; nan outside the scored regions: the face
sphere and the ear region), per protocol: the heat map on the mesh of the capture's page."""
ALIGNMENT_JSON = "alignment_{protocol}.json"
"""The transform the protocol brought the mesh onto the scan with (``s``, ``R``, ``t``:
x_scan = s R x_mesh + t): the capture page moves the scan into the mesh's frame by it."""


def scored_per_vertex(sc) -> np.ndarray:
    """Each mesh vertex's distance to the scan (mm) where the evaluation scores it, the face
    sphere's or the ear region's (the two are disjoint), nan elsewhere: what the heat maps
    show (``sc`` a :class:`~facecap_core.evaluation.scoring.Score`)."""
    face = np.asarray(sc.accuracy_per_vertex, float)
    return np.where(np.isfinite(face), face, np.asarray(sc.ears.accuracy_per_vertex, float))


def find_file(folder: str | Path, suffixes: Sequence[str], what: str) -> Path:
    """The single file in ``folder`` with one of ``suffixes`` (an input artifact's file)."""
    found = sorted(p for p in Path(folder).iterdir()
                   if p.is_file() and p.suffix.lower() in suffixes and p.name != "manifest.json")
    if not found:
        raise InputError(f"no {what} ({'/'.join(suffixes)}) in {folder}")
    return found[0]


def mesh_landmarks(mesh_dir: str | Path, vertices: np.ndarray) -> Path | np.ndarray | None:
    """The mesh's 68 landmarks for the alignment's start. A mesh in the default template's
    topology whose landmark file (the fitting's, beside it) names that template, or that
    has none, takes its own landmark vertices: the same mesh.ply then scores the same with
    or without the file (``evaluate-dataset`` ingests mesh.ply alone), which holds the same
    points rounded to a micrometre, while the trimmed ICP's fixed point moves with its start
    by hundredths of a millimetre. Any other mesh takes the file, or None without one."""
    template = Template.default()
    path = Path(mesh_dir) / MESH_LANDMARKS
    named = _template_named(path) if path.is_file() else template.name
    if len(vertices) == len(template.vertices) and named == template.name:
        return np.asarray(vertices, float)[template.landmarks]
    return path if path.is_file() else None


def _template_named(landmarks_json: Path) -> str | None:
    """The template a landmark file says its points are on (None where it says none, or
    cannot be read: the alignment's reader then says what is wrong with it)."""
    try:
        named = json.loads(landmarks_json.read_text()).get("template")
    except (OSError, ValueError, AttributeError):
        return None
    return named if isinstance(named, str) else None


def main(mesh_dir: str | Path, scan_dir: str | Path, out_dir: str | Path,
                   scan_landmarks: str | Path | None = None,
                   config: EvaluationConfig | None = None) -> Path:
    """Score the fitting stage's ``mesh.ply`` against a scan; writes ``evaluation.json``
    (:func:`score_json` per protocol), ``heatmap_<protocol>.png``,
    ``accuracy_<protocol>.npy`` (per vertex) and ``alignment_<protocol>.json`` (the transform
    from the mesh to the scan, :func:`read_alignment`); returns the JSON."""

    mesh_path = Path(mesh_dir) / MESH_PLY
    scan_path = find_file(scan_dir, (".ply", ".obj", ".stl", ".off"), "scan mesh")
    lm_path = (find_file(scan_landmarks, (".json", ".ljson", ".txt", ".pts"), "scan landmarks")
               if scan_landmarks is not None else None)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    mesh = load_mesh(mesh_path, "mesh")
    scores = evaluate(mesh_path, scan_path, lm_path, mesh_landmarks(mesh_dir, mesh.vertices),
                      config=config)
    for name, sc in scores.items():
        scored = scored_per_vertex(sc)
        error_heatmap(sc.alignment.apply(mesh.vertices), mesh.faces, scored,
                      out / f"heatmap_{name}.png")
        np.save(out / ACCURACY_NPY.format(protocol=name), scored.astype(np.float32))
        a = sc.alignment
        (out / ALIGNMENT_JSON.format(protocol=name)).write_text(json.dumps(
            {"s": float(a.s), "R": np.asarray(a.R, float).tolist(),
             "t": np.asarray(a.t, float).tolist(), "maps": "mesh to scan: s R x + t"}))
    path = out / EVALUATION_JSON
    path.write_text(json.dumps({p: score_json(s) for p, s in scores.items()}, indent=1))
    return path


def read_alignment(folder: str | Path, protocol: str) -> Alignment:
    """The transform the evaluation in ``folder`` brought the mesh onto the scan with."""
    path = Path(folder) / ALIGNMENT_JSON.format(protocol=protocol)
    try:
        d = json.loads(path.read_text())
        return Alignment(float(d["s"]), np.asarray(d["R"], float).reshape(3, 3),
                         np.asarray(d["t"], float).reshape(3))
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputError(f"{path} holds no alignment ({exc}); evaluate the mesh again") from exc


def figures(folder: str | Path) -> dict:
    """The scores of an evaluation artifact, per protocol."""
    path = Path(folder) / EVALUATION_JSON
    return {"evaluation": json.loads(path.read_text())} if path.is_file() else {}


def run(inputs: Folders, out: Path, config: EvaluationConfig, params: dict) -> None:
    main(inputs["mesh"], inputs["scan"], out, scan_landmarks=inputs.get("scan_landmarks"),
         config=config)


HEATMAPS = tuple(f"heatmap_{p}.png" for p in PROTOCOLS)
ACCURACY = tuple(ACCURACY_NPY.format(protocol=p) for p in PROTOCOLS)
ALIGNMENTS = tuple(ALIGNMENT_JSON.format(protocol=p) for p in PROTOCOLS)

STAGE = Stage("evaluation", version="6", inputs=("mesh", "scan"), work_seconds=3.0,
              section="evaluation", run=run, outputs=(EVALUATION_JSON, *HEATMAPS, *ACCURACY, *ALIGNMENTS),
              exported=(EVALUATION_JSON, *HEATMAPS), optional=("scan_landmarks",),
              sources={"mesh": "fitting"}, figures=figures)
