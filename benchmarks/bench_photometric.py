"""The photometric refinement on a stored run: the fitted mesh before and after, against the
truth.

    python benchmarks/bench_photometric.py RUN CAPTURE [--config C.yaml]

RUN is a ``facecap reconstruct … --scan`` output folder (its ``report.json`` names the store
and the keyframes' artifact; ``mesh.ply`` and ``cameras.json`` are its fitted mesh and
metric cameras); CAPTURE a ``facecap synth`` folder with ``gt/mesh.ply`` and
``gt/landmarks.json``. The keyframes are loaded as the fitting stage loads them (960 px
wide at most), the mesh refined with the ``fitting.photometric`` settings of ``--config``
(default: the defaults), and both meshes scored as the evaluation stage scores them.
Printed: face and ear accuracy (mean / median), completion, under the similarity and the
metric protocol, and the refinement's rounds. The refinement runs on the mesh before the
fitting stage's fold relaxation; a run whose fit relaxed folds differs from the pipeline's
by that (on ICT 12 at ``phone_512``: 0.002 mm).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from facecap.tasks.store import open_store  # noqa: E402
from facecap_core.config import load_yaml  # noqa: E402
from facecap_core.evaluation import score  # noqa: E402
from facecap_core.fitting.stage import load_keyframes  # noqa: E402
from facecap_core.meshio import load_landmarks, load_mesh  # noqa: E402
from facecap_core.nonrigid.photometric import refine  # noqa: E402
from facecap_core.pipeline import PipelineConfig  # noqa: E402
from facecap_core.pose.cameras_json import read_cameras_json  # noqa: E402
from facecap_core.template import Template  # noqa: E402


def keyframes(run: Path) -> list:
    """The run's keyframes and metric cameras, as the fitting stage loads them."""
    report = json.loads((run / "report.json").read_text())
    frames = open_store(report["store"]).get(report["stages"]["frames"]["key"])
    return load_keyframes(frames, read_cameras_json(run / "cameras.json"))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("capture", type=Path)
    ap.add_argument("--config", type=Path, help="PipelineConfig YAML (its fitting.photometric)")
    args = ap.parse_args(argv)

    config = load_yaml(PipelineConfig, args.config) if args.config else PipelineConfig()
    mesh = load_mesh(args.run / "mesh.ply")
    truth = load_mesh(args.capture / "gt" / "mesh.ply")
    truth_landmarks = load_landmarks(args.capture / "gt" / "landmarks.json")
    template = Template.default()
    refined, log = refine(mesh.vertices, mesh.faces, keyframes(args.run),
                          config.fitting.photometric)
    for rnd in log["rounds"]:
        print("round", rnd)
    for label, vertices in (("fit", mesh.vertices), ("refined", refined)):
        row = []
        for protocol in ("similarity", "metric"):
            s = score(vertices, mesh.faces, truth.vertices, truth.faces, truth_landmarks,
                      template.with_vertices(vertices).landmark_points, protocol=protocol)
            row.append(f"{protocol} face {s.accuracy.mean:.3f} / {s.accuracy.median:.3f}, "
                       f"ears {s.ears.accuracy.mean:.3f} / {s.ears.accuracy.median:.3f}, "
                       f"completion {s.completion.mean:.3f} / {s.completion.median:.3f}")
        print(f"{label:8s}" + " | ".join(row))
    print(f"refinement: {log['seconds']} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
