"""A capture page looked at in headless Chromium (Debian's ``chromium``, which the Makefile
installs, driven by Playwright): what a person would see, as numbers a test can assert."""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

CHROMIUM = "/usr/bin/chromium"
ARGS = ["--headless=new", "--no-sandbox", "--disable-gpu", "--use-angle=swiftshader",
        "--enable-unsafe-swiftshader", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync"]
"""Software WebGL (no GPU on CI); no background requests (the machine has no network)."""
BACKGROUND = np.array([244, 244, 244])
READY_TIMEOUT_MS = 60_000


SETTLED_FRAMES = 5
"""Frames without a draw after which the view has settled (the damped turn ended)."""


def settled(page, timeout_ms: float = 15000) -> None:
    """Wait until the viewer has drawn a frame and then drawn nothing for
    :data:`SETTLED_FRAMES` frames: what is on the canvas is what stays there, on a fast
    machine or a slow software renderer alike."""
    page.wait_for_function(f"window.facecap.drawn > 0 && window.facecap.still >= "
                           f"{SETTLED_FRAMES}", timeout=timeout_ms)


def _pixels(png: bytes) -> np.ndarray:
    import cv2

    return cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)[..., ::-1].astype(int)


def look_at_page(page_file: Path | str, shots: Path | None = None, browser=None) -> dict:
    """Open ``page_file`` from disk (or from an ``http://`` address) and report: ``ready``
    (the viewer read the mesh) and the seconds until then, ``drawn`` (share of the view's
    middle that is not background),
    ``accuracy_change`` and ``cameras_change`` (mean absolute pixel change when the heat map
    or the cameras are switched on), ``keyframe_opened`` (a click on a camera showed its
    image), ``figures`` (data-figure key -> text shown), ``errors``
    (console errors and uncaught exceptions). Screenshots go to ``shots`` when given. In
    ``browser`` (one of :func:`chromium`'s) when given, else in a Chromium of its own."""
    found: dict = {"errors": [], "figures": {}}
    if browser is not None:
        return _look(browser, page_file, shots, found)
    with chromium() as browser:
        return _look(browser, page_file, shots, found)


@contextmanager
def chromium():
    """Headless Chromium, its profile and socket in a short folder of its own (a socket's
    path has at most 107 bytes, which a deep temp folder exceeds)."""
    from playwright.sync_api import sync_playwright

    short = tempfile.mkdtemp(prefix="page-", dir="/tmp")
    saved = os.environ.get("TMPDIR")
    os.environ["TMPDIR"] = short  # the Playwright driver makes the profile in its TMPDIR
    try:
        with sync_playwright() as playwright:
            browser = playwright.chromium.launch(executable_path=CHROMIUM, args=ARGS)
            try:
                yield browser
            finally:
                browser.close()
    finally:
        if saved is None:
            os.environ.pop("TMPDIR", None)
        else:
            os.environ["TMPDIR"] = saved
        shutil.rmtree(short, ignore_errors=True)


def _open_a_keyframe(page, view) -> bool | None:
    """Click the first camera inside the view: whether its keyframe image opened (None when
    no camera is inside the view)."""
    box = view.bounding_box()
    count = page.evaluate("JSON.parse(document.getElementById('facecap-data').textContent)"
                          ".cameras.count")
    for i in range(count):
        at = page.evaluate(f"window.facecap.cameraOnScreen({i})")
        if at and 30 < at[0] < box["width"] - 30 and 30 < at[1] < box["height"] - 30:
            page.mouse.click(box["x"] + at[0], box["y"] + at[1])
            page.wait_for_timeout(200)
            figure = page.query_selector("#keyframe")
            source = page.get_attribute("#keyframe img", "src") or ""
            return figure.is_visible() and source.startswith("data:image/jpeg")
    return None


def _look(browser, page_file: Path | str, shots: Path | None, found: dict) -> dict:
    """What :func:`look_at_page` reports, in ``browser``."""
    page = browser.new_page(viewport={"width": 1100, "height": 700})
    page.on("console", lambda m: found["errors"].append(m.text)
            if m.type == "error" else None)
    page.on("pageerror", lambda e: found["errors"].append(str(e)))
    start = time.perf_counter()
    page.goto(page_file if isinstance(page_file, str) else page_file.resolve().as_uri())
    try:
        page.wait_for_function("window.facecap && (window.facecap.ready || "
                               "window.facecap.reason)", timeout=READY_TIMEOUT_MS)
        found["ready"] = page.evaluate("window.facecap.ready")
    except Exception:  # noqa: BLE001 - Playwright's timeout: the viewer never got ready
        found["ready"] = False
    found["seconds"] = time.perf_counter() - start
    for element in page.query_selector_all("[data-figure]"):
        found["figures"][element.get_attribute("data-figure")] = element.inner_text()
    if not found["ready"]:
        return found
    view = page.locator("#canvas")

    def shot(name: str) -> np.ndarray:
        settled(page)
        png = view.screenshot()
        if shots is not None:
            shots.mkdir(parents=True, exist_ok=True)
            (shots / f"{name}.png").write_bytes(png)
        return _pixels(png)

    colour = shot("colour")
    h, w = colour.shape[:2]
    middle = colour[h // 4: 3 * h // 4, w // 4: 3 * w // 4]
    found["drawn"] = float((np.abs(middle - BACKGROUND).sum(axis=2) > 30).mean())
    found["accuracy_change"] = None
    if page.query_selector("[data-mode=accuracy]"):
        page.click("[data-mode=accuracy]")
        found["accuracy_change"] = float(np.abs(shot("accuracy") - colour).mean())
        page.click("[data-mode=colour]")
    found["cameras_change"] = None
    if page.query_selector("[data-toggle=cameras]"):
        before = shot("before-cameras")
        page.click("[data-toggle=cameras]")
        found["cameras_change"] = float(np.abs(shot("cameras") - before).mean())
        found["keyframe_opened"] = _open_a_keyframe(page, view)
    if shots is not None:
        page.screenshot(path=str(shots / "page.png"))
    return found
