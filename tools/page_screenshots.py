"""Screenshots of the capture page in each of its modes, for docs/results_page.md, and the
page's size and the seconds until it is ready.

    python tools/page_screenshots.py [--results out/demo/result] [--out docs/images]

Builds the page of a finished run (its results folder: ``make demo`` writes
``out/demo/result``; the heat map, the keyframe images and the scan come from the run's
store), opens it in headless Chromium at 1280×800 and saves ``page_<mode>.png`` for each
mode: colour, heatmap, plain, light (raked), wireframe, measure (a preset), cameras, scan
(beside the heat map). A report without the measurements (a run from before the fitting
stage made them) gets them measured here on its mesh, in template topology, and one from
before the anatomical figures gets those. Then loads the page ``--loads`` times, each in a
fresh browser, and prints the median seconds until ``window.facecap.drawn``.
"""

from __future__ import annotations

import argparse
import io
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

WIDTH, HEIGHT = 1280, 800
MAX_PNG_BYTES = 300_000
"""A screenshot above this is stored with fewer colours (an adaptive palette)."""
PRESET = "outer_eyes"


def build(results: Path, target: Path) -> bytes:
    """The page of the run in ``results``, written to ``target``."""
    from facecap.pages.capture import build_page, mesh_glb
    from facecap.tasks.store import open_store
    from facecap_core.measure import landmark_measurements, under_scale
    from facecap_core.meshio import load_mesh
    from facecap_core.template import Template

    report = json.loads((results / "report.json").read_text())
    names = ("mesh.ply", "mesh.obj", "mesh.mtl", "texture.png", "mesh.glb", "cameras.json",
             "cloud.ply")
    files = {n: results / n for n in names if (results / n).is_file()}
    figures = report.setdefault("figures", {})
    sigma = (figures.get("scale") or {}).get("sigma_pct")
    if not figures.get("measurements"):
        mesh, template = load_mesh(files["mesh.ply"]), Template.default()
        if len(mesh.vertices) == len(template.vertices):
            figures["measurements"] = landmark_measurements(
                mesh.vertices, mesh.faces, template.landmarks, sigma)
    if figures.get("measurements") and not all("anatomical" in m for m in
                                                figures["measurements"].values()):
        figures["measurements"] = under_scale(figures["measurements"], sigma)
    accuracy, frames, stages = None, None, report.get("stages", {})
    if report.get("store"):
        store = open_store(report["store"])
        if "evaluation" in stages:
            path = store.get(stages["evaluation"]["key"]) / "accuracy_metric.npy"
            accuracy = np.load(path) if path.is_file() else None
        if "frames" in stages:
            frames = store.get(stages["frames"]["key"])
    page = build_page(report, files, mesh_glb(files["mesh.ply"]), accuracy, frames)
    target.parent.mkdir(parents=True, exist_ok=True)
    target.write_bytes(page)
    return page


def small_png(png: bytes) -> bytes:
    """``png`` as it is, or with an adaptive palette of 256 colours where it is larger than
    :data:`MAX_PNG_BYTES` (a render's smooth shading takes that well)."""
    from PIL import Image

    if len(png) <= MAX_PNG_BYTES:
        return png
    image = Image.open(io.BytesIO(png)).convert("RGB").quantize(256, dither=Image.Dither.NONE)
    out = io.BytesIO()
    image.save(out, format="PNG", optimize=True)
    return out.getvalue()


def _modes(page) -> dict:
    """Each mode's setting-up, from the page as it opened (colour, the light in front)."""
    def reset():
        page.reload()
        page.wait_for_function("window.facecap && window.facecap.ready", timeout=60_000)

    def click(*selectors):
        def run():
            reset()
            for selector in selectors:
                page.click(selector)
        return run

    def raked():
        reset()
        page.click("[data-mode=plain]")
        page.fill("#light input", "75")

    return {"colour": reset, "heatmap": click("[data-mode=accuracy]"),
            "plain": click("[data-mode=plain]"), "light": raked,
            "wireframe": click("[data-toggle=wireframe]"),
            "measure": click("#measure-button", f"[data-preset={PRESET}]"),
            "cameras": click("[data-toggle=cameras]"),
            "scan": click("[data-mode=accuracy]", "#scan-button")}


def screenshots(page_file: Path, out: Path) -> list[Path]:
    """``page_<mode>.png`` in ``out`` for each mode the page has."""
    from tests.browser import chromium, settled

    saved = []
    with chromium() as browser:
        page = browser.new_page(viewport={"width": WIDTH, "height": HEIGHT})
        page.goto(page_file.resolve().as_uri())
        for mode, setup in _modes(page).items():
            try:
                setup()
            except Exception as exc:  # noqa: BLE001 - a page without the mode: said, not shot
                print(f"{mode}: not on this page ({str(exc).splitlines()[0]})")
                continue
            settled(page)
            path = out / f"page_{mode}.png"
            path.write_bytes(small_png(page.screenshot()))
            saved.append(path)
            print(f"{path}: {path.stat().st_size / 1000:.0f} kB")
    return saved


def ready_seconds(page_file: Path, loads: int) -> list[float]:
    """Seconds from the start of each load to the viewer's first drawn frame, each load in a
    fresh browser."""
    from tests.browser import chromium

    seconds = []
    for _ in range(loads):
        with chromium() as browser:
            page = browser.new_page(viewport={"width": WIDTH, "height": HEIGHT})
            start = time.perf_counter()
            page.goto(page_file.resolve().as_uri())
            page.wait_for_function("window.facecap && window.facecap.drawn > 0",
                                   timeout=60_000, polling=10)
            seconds.append(time.perf_counter() - start)
    return seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--results", type=Path, default=Path("out/demo/result"))
    parser.add_argument("--out", type=Path, default=Path("docs/images"))
    parser.add_argument("--loads", type=int, default=5)
    args = parser.parse_args()
    if not (args.results / "mesh.ply").is_file():
        sys.exit(f"no mesh in {args.results}: run `make demo` first, or give --results")
    page_file = Path("out/page_screenshots/index.html")
    start = time.perf_counter()
    page = build(args.results, page_file)
    built = time.perf_counter() - start
    args.out.mkdir(parents=True, exist_ok=True)
    screenshots(page_file, args.out)
    loads = ready_seconds(page_file, args.loads)
    print(f"page {len(page) / 1e6:.2f} MB ({len(page) / 2**20:.2f} MiB), built in {built:.1f} s;"
          f" drawn in Chromium: median {statistics.median(loads):.2f} s over {len(loads)} "
          f"loads (min {min(loads):.2f}, max {max(loads):.2f})")


if __name__ == "__main__":
    main()
