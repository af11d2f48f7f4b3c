"""Do the depth maps, the fused cloud and the mesh follow the face's curvature? Their signed
error against the truth, by the true surface's mean curvature.

    python benchmarks/bench_curvature_bias.py RUN CAPTURE [--maps-every 4] [--samples 5000]

RUN is a ``facecap reconstruct … --scan`` output folder (its ``report.json`` names the store
and the artifacts); CAPTURE a ``facecap synth`` folder with ``gt/mesh.ply`` and
``gt/landmarks.json``, the capture RUN reconstructed. Everything is put into the truth's
frame by the evaluation's similarity of the mesh to the scan (the cloud and the depth maps
share the mesh's frame).

For each of the raw depth maps (every ``--maps-every``-th map, back-projected), the fused
cloud and the fitted mesh, a sample of points inside the face sphere:

* the signed distance along the true surface's outward normal at the nearest true point
  (positive: outside the head);
* the true surface's mean curvature there, H, from a quadric fitted to the true vertices
  within ``RADIUS_MM``: negative where the skin is convex (the nose's tip, the cheekbones),
  positive where it is concave (the eye sockets, the sides of the nose, the mouth's
  corners).

Printed: the signed median and the |error| median per H bin. An unbiased surface reads
zero signed error in every bin; one that flattens convex skin and fills concave skin
reads negative on the left and positive on the right
(docs/experiments/2026-11-28-raking-light-lumps.md).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from facecap.tasks.store import open_store  # noqa: E402
from facecap_core.evaluation import evaluate, face_region  # noqa: E402
from facecap_core.evaluation.alignment import Surface  # noqa: E402
from facecap_core.fitting.run import load_cloud_errors  # noqa: E402
from facecap_core.meshio import load_landmarks, load_mesh  # noqa: E402
from facecap_core.mvs.depth import load_depth_map  # noqa: E402
from facecap_core.mvs.filtering import backproject  # noqa: E402
from facecap_core.render import vertex_normals  # noqa: E402

RADIUS_MM = 6.0
"""The true surface's curvature is fitted over this radius: about the depth maps' window on
the face at 640 px."""
BINS = (-np.inf, -0.06, -0.03, -0.01, 0.01, 0.03, 0.06, np.inf)
"""H bin edges (1/mm): a sphere of radius R has |H| = 1/R (17 mm at 0.06, 33 mm at 0.03)."""


class Truth:
    """The true surface: nearest points, outward normals and local mean curvature."""

    def __init__(self, mesh_path: Path):
        mesh = load_mesh(mesh_path)
        self.vertices = np.asarray(mesh.vertices, float)
        self.normals = vertex_normals(self.vertices, np.asarray(mesh.faces))
        self.surface = Surface(self.vertices, np.asarray(mesh.faces))
        self.tree = cKDTree(self.vertices)

    def signed(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(signed distance, nearest true point, its normal) of each point."""
        nearest = self.surface.closest(points)[0]
        normals = self.normals[self.tree.query(nearest)[1]]
        return np.einsum("ij,ij->i", points - nearest, normals), nearest, normals

    def mean_curvature(self, at: np.ndarray, normal: np.ndarray) -> float:
        """The mean curvature H at a true point: z = a x² + b xy + c y² + d x + e y + f
        fitted over the vertices within RADIUS_MM in the normal's frame (z outward); the
        principal curvatures sum to 2(a + c), so H = a + c (negative where convex)."""
        ids = self.tree.query_ball_point(at, RADIUS_MM)
        q = self.vertices[ids] - at
        u = np.cross(normal, [1.0, 0.0, 0.0])
        if np.linalg.norm(u) < 0.1:
            u = np.cross(normal, [0.0, 1.0, 0.0])
        u /= np.linalg.norm(u)
        v = np.cross(normal, u)
        x, y, z = q @ u, q @ v, q @ normal
        design = np.column_stack([x * x, x * y, y * y, x, y, np.ones_like(x)])
        a, _, c, *_ = np.linalg.lstsq(design, z, rcond=None)[0]
        return float(a + c)


def binned(truth: Truth, points: np.ndarray, samples: int, rng) -> list[tuple[float, float, int]]:
    """Per H bin: (signed median, |error| median, count) of a sample of ``points``."""
    if len(points) > samples:
        points = points[rng.choice(len(points), samples, replace=False)]
    signed, nearest, normals = truth.signed(points)
    curvature = np.array([truth.mean_curvature(p, n) for p, n in zip(nearest, normals)])
    rows = []
    for lo, hi in zip(BINS[:-1], BINS[1:]):
        inside = (curvature >= lo) & (curvature < hi)
        if not inside.any():
            rows.append((np.nan, np.nan, 0))
            continue
        rows.append((float(np.median(signed[inside])), float(np.median(np.abs(signed[inside]))),
                     int(inside.sum())))
    return rows


def depth_map_points(store, keys: list[str]) -> np.ndarray:
    """The depth maps' valid pixels back-projected into the world."""
    points = []
    for key in keys:
        depth = load_depth_map(next(store.get(key).glob("depth_*.npz")))
        rows, cols = np.nonzero(np.isfinite(depth.depth) & (depth.depth > 0))
        points.append(backproject(depth, rows, cols)[0])
    return np.concatenate(points) if points else np.zeros((0, 3))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("capture", type=Path)
    ap.add_argument("--maps-every", type=int, default=4)
    ap.add_argument("--samples", type=int, default=5000)
    args = ap.parse_args(argv)

    report = json.loads((args.run / "report.json").read_text())
    store, stages = open_store(report["store"]), report["stages"]
    scan, scan_landmarks = args.capture / "gt" / "mesh.ply", args.capture / "gt" / "landmarks.json"
    landmarks = load_landmarks(scan_landmarks)
    alignment = evaluate(args.run / "mesh.ply", scan, scan_landmarks,
                         args.run / "landmarks3d.json", protocols=("similarity",)
                         )["similarity"].alignment
    truth = Truth(scan)
    rng = np.random.default_rng(0)

    sources = {
        "raw depth maps": depth_map_points(
            store, [v["key"] for k, v in sorted(stages.items())
                    if k.startswith("depth_")][::args.maps_every]),
        "fused cloud": load_cloud_errors(store.get(stages["fusion"]["key"]) / "cloud.ply")[0],
        "fitted mesh": np.asarray(load_mesh(args.run / "mesh.ply").vertices, float),
    }
    names = [f"{lo:+.2f}..{hi:+.2f}" for lo, hi in zip(BINS[:-1], BINS[1:])]
    print(f"{args.run.name}: signed median (|error| median), mm, by the truth's mean "
          "curvature H (1/mm)")
    print(f"{'':16s}" + "".join(f"{n:>16s}" for n in names))
    for label, points in sources.items():
        points = alignment.apply(points)
        points = points[face_region(points, landmarks)]
        rows = binned(truth, points, args.samples, rng)
        print(f"{label:16s}" + "".join(f"{s:+8.2f} ({a:4.2f})" for s, a, _ in rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
