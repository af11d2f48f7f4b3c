"""The capture page (``index.html``) of a finished run: its size, the seconds to build it and
the seconds until headless Chromium shows the mesh (median of ``--loads`` page loads, each in
a fresh browser), from the run's own results folder.

    python benchmarks/bench_page.py [--results out/demo/result] [--loads 5]

``make demo`` writes ``out/demo/result``. The budget (docs/results_page.md): under 15 MB,
ready in under 2 s on the 2-core machine.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--results", default="out/demo/result")
    parser.add_argument("--loads", type=int, default=5)
    args = parser.parse_args()
    from facecap.pages.capture import build_page, mesh_glb
    from tests.browser import look_at_page

    folder = Path(args.results)
    if not (folder / "mesh.ply").is_file():
        sys.exit(f"no mesh in {folder}: run `make demo` first, or give --results")
    report = json.loads((folder / "report.json").read_text())
    results = {n: folder / n for n in ("mesh.ply", "cameras.json", "cloud.ply")
               if (folder / n).is_file()}
    store = report.get("store")
    accuracy, frames = None, None
    stages = report.get("stages", {})
    if store:
        from facecap.tasks.store import open_store

        if "evaluation" in stages:
            path = open_store(store).get(stages["evaluation"]["key"]) / "accuracy_metric.npy"
            accuracy = np.load(path) if path.is_file() else None
        if "frames" in stages:
            frames = open_store(store).get(stages["frames"]["key"])
    start = time.perf_counter()
    page = build_page(report, results, mesh_glb(folder / "mesh.ply"), accuracy, frames)
    built = time.perf_counter() - start
    target = Path("out/bench_page/index.html")
    target.parent.mkdir(parents=True, exist_ok=True)
    target.write_bytes(page)
    loads = [look_at_page(target) for _ in range(args.loads)]
    assert all(seen["ready"] and not seen["errors"] for seen in loads), loads[0]
    print(f"page {len(page) / 2**20:.2f} MiB (heat map: {'yes' if accuracy is not None else 'no'}"
          f", keyframe images: {'yes' if frames is not None else 'no'}), built in {built:.2f} s; "
          "ready in Chromium: median "
          f"{statistics.median(s['seconds'] for s in loads):.2f} s over {args.loads} loads "
          f"(min {min(s['seconds'] for s in loads):.2f}, max {max(s['seconds'] for s in loads):.2f})")


if __name__ == "__main__":
    main()
