"""``index.html``: a capture's results as one self-contained page, and ``mesh.glb``.

The page opens from disk, from a bucket or from a mail attachment: no server, no network.
It holds the mesh as binary glTF (the same bytes as ``mesh.glb``), the accuracy of each
vertex against the scan (as colours of the heat map, with its colour bar in mm), a sample of
the fused cloud, the keyframe cameras as frusta, the figures of ``report.json`` in words and
the stages' times, and the viewer: the three.js bundle vendored in ``flows/viewer`` (MIT,
``flows/viewer/LICENSE-three.txt``; rebuilt by ``tools/viewer/build.sh``) and
``flows/viewer/viewer.js``.
"""

from __future__ import annotations

import base64
import hashlib
import html
import json
import logging
from importlib import resources
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import trimesh

from facecap.tasks.graph import is_keyframe_row
from facecap.tasks.runner import lease, network_errors
from facecap.tasks.store import artifact_key
from facecap.tasks.store.keys import KEY_PATTERN
from facecap_core.coarse import ears_summary, scale_summary
from facecap_core.errors import FacecapError
from facecap_core.frames import frame_name

_log = logging.getLogger(__name__)

PAGE_NAME = "index.html"
GLB_NAME = "mesh.glb"
HEAT_MAX_MM = 5.0
"""The heat map's scale: 0 (blue) to this many mm (red) and beyond, as in the PNG heat maps."""
KEYFRAME_SIDE = 480
"""The keyframe images a click on a camera shows are this many pixels on their long side."""
MAX_CLOUD_POINTS = 60_000
"""The fused cloud is sampled down to this many points: enough to see it, a few MB at most."""


PAGE_STAGE = "page"
"""The store keeps each run's page as an artifact of this name, made from the run's stage
artifacts: what a link from the Prefect UI opens (:func:`facecap.flows.ui.results_link`), what
``forget`` removes with the face it shows, what ``prune --unreferenced`` keeps while a
``report.json`` names it."""


def keep_page(store, inputs: dict[str, str], page: bytes) -> str:
    """Keep ``page`` in the store as an artifact made from ``inputs`` (name -> key), held
    for the run in progress; returns its key."""


    config = {"sha256": hashlib.sha256(page).hexdigest()}
    key = artifact_key(PAGE_STAGE, inputs, config, "1")
    lease(store, key)
    store.put(key, {PAGE_NAME: page}, stage=PAGE_STAGE, inputs=inputs, config=config,
              version="1")
    return key


def store_page(store, report: dict, page: bytes) -> str:
    """Keep ``page`` (this run's ``index.html``) in the store, made from the run's stage
    artifacts; returns its key."""
    return keep_page(store, {name: info["key"] for name, info in
                             report.get("stages", {}).items()}, page)


def mesh_glb(mesh_ply: Path) -> bytes:
    """The mesh as binary glTF with its vertex colours (Blender, three.js, Windows 3D Viewer)."""

    mesh = trimesh.load(mesh_ply, process=False, force="mesh")
    return mesh.export(file_type="glb")


def _b64(array: np.ndarray) -> str:
    return base64.b64encode(np.ascontiguousarray(array).tobytes()).decode("ascii")


def turbo(values: np.ndarray, max_value: float) -> np.ndarray:
    """RGB (uint8) of ``values`` on OpenCV's TURBO map over 0..``max_value``; nan in grey."""

    v = np.asarray(values, float)
    level = np.clip(np.nan_to_num(v / max_value, nan=0.0), 0.0, 1.0)
    rgb = cv2.applyColorMap(np.round(level * 255).astype(np.uint8)[:, None],
                            cv2.COLORMAP_TURBO)[:, 0, ::-1].copy()
    rgb[~np.isfinite(v)] = 170
    return rgb


def _colour_bar() -> str:
    stops = turbo(np.linspace(0.0, HEAT_MAX_MM, 9), HEAT_MAX_MM)
    return ", ".join(f"rgb({r},{g},{b})" for r, g, b in stops)


def _keyframe_image(frames: Path | None, index: int) -> str | None:
    """A keyframe's image, shrunk to :data:`KEYFRAME_SIDE` on its long side, as a JPEG data
    URI (None where the frames stage's folder does not hold it)."""


    if frames is None or not (frames / frame_name(index)).is_file():  # OpenCV would warn
        return None
    image = cv2.imread(str(frames / frame_name(index)), cv2.IMREAD_COLOR)
    if image is None:
        return None
    scale = KEYFRAME_SIDE / max(image.shape[:2])
    if scale < 1:
        image = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    ok, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 80])
    return "data:image/jpeg;base64," + base64.b64encode(jpeg.tobytes()).decode() if ok else None


def _cameras(cameras_json: Path, centre: np.ndarray, frames: Path | None = None
             ) -> tuple[dict, list, list]:
    """Frusta (line segments, mm) of the keyframe cameras with their centres and images (a
    click on a camera shows what it saw), and the direction and up vector from which they saw
    the head (the viewer starts there)."""
    doc = json.loads(cameras_json.read_text())
    intr, keyframes = doc["intrinsics"], doc["keyframes"]
    rotations = np.array([k["R"] for k in keyframes], float)
    centres = np.array([-np.asarray(k["R"]).T @ np.asarray(k["t"]) for k in keyframes], float)
    depth = 0.15 * float(np.median(np.linalg.norm(centres - centre, axis=1)))
    w, h, fx, fy = intr["width"], intr["height"], intr["fx"], intr["fy"]
    cx, cy = intr["cx"], intr["cy"]
    corners = np.array([[(u - cx) / fx, (v - cy) / fy, 1.0]
                        for u, v in ((0, 0), (w, 0), (w, h), (0, h))]) * depth
    lines = []
    for R, c in zip(rotations, centres, strict=True):
        world = corners @ R + c  # R^T p + c, row-wise
        for i in range(4):
            lines += [c, world[i], world[i], world[(i + 1) % 4]]
    direction = centres.mean(axis=0) - centre
    up = -rotations[:, 1, :].mean(axis=0)  # OpenCV cameras look along +z with y down
    data = {"lines": _b64(np.asarray(lines, np.float32)), "count": len(keyframes),
            "distance": float(np.median(np.linalg.norm(centres - centre, axis=1))),
            "centres": _b64(centres.astype(np.float32)),
            "frames": [int(k["frame_index"]) for k in keyframes],
            "images": [_keyframe_image(frames, k["frame_index"]) for k in keyframes]}
    return data, direction.tolist(), up.tolist()


def _cloud(cloud_ply: Path, seed: int = 0) -> dict:
    cloud = o3d.io.read_point_cloud(str(cloud_ply))
    points = np.asarray(cloud.points, np.float32)
    colours = (np.clip(np.asarray(cloud.colors), 0, 1) * 255).astype(np.uint8) \
        if cloud.has_colors() else np.full((len(points), 3), 160, np.uint8)
    if len(points) > MAX_CLOUD_POINTS:
        keep = np.sort(np.random.default_rng(seed).choice(len(points), MAX_CLOUD_POINTS,
                                                           replace=False))
        points, colours = points[keep], colours[keep]
    return {"positions": _b64(points), "colours": _b64(colours), "count": int(len(points))}


def figure_rows(report: dict) -> list[tuple[str, str, str]]:
    """(key, label, text) of the figures that matter, in words, rounded, with their units:
    what the page and the Prefect UI's summary show."""
    fig, rows = report.get("figures", {}), []
    scale = fig.get("scale") or {}
    parts = []
    if fig.get("metric_scale") is not None:
        parts.append(f"{fig['metric_scale']:.4g} mm per camera unit")
    if scale.get("sigma_pct") is not None:
        parts.append(scale_summary(scale))
    if parts:
        rows.append(("metric_scale", "Metric scale", ", ".join(parts)))
    if fig.get("keyframes") is not None:
        rows.append(("keyframes", "Keyframes", str(fig["keyframes"])))
    if fig.get("focal_px") is not None:
        rows.append(("focal_px", "Focal length", f"{fig['focal_px']:.1f} px"))
    if fig.get("ears"):
        rows.append(("ears", "Ears", ears_summary(fig["ears"])))
    rough = fig.get("roughness") or {}
    if rough.get("bent_share_pct") is not None:
        rows.append(("roughness", "Surface", f"{rough['bent_share_pct']:.1f} % of the face's "
                     f"edges bent over {rough['bent_deg']:g}°, median bend "
                     f"{rough['median_bend_deg']:.1f}° (smooth skin: under 7 % and 3°)"))
    for protocol, sc in (fig.get("evaluation") or {}).items():
        a, c = sc["accuracy"], sc["completion"]
        rows.append((f"evaluation_{protocol}", f"Accuracy ({protocol})",
                     f"mean {a['mean']:.3f} mm, median {a['median']:.3f} mm; completion mean "
                     f"{c['mean']:.3f} mm, median {c['median']:.3f} mm"))
    return rows


def run_summary(report: dict) -> str:
    """``3 artifacts computed, 1 reused, 81.5 s``."""
    computed = report.get("computed", 0)
    return (f"{computed} artifact{'' if computed == 1 else 's'} computed, "
            f"{report.get('cached', 0)} reused, {report.get('wall_seconds', 0):.1f} s")


def _stage_rows(report: dict) -> str:
    rows, depth = [], []
    for name, info in report.get("stages", {}).items():
        if is_keyframe_row(name):
            depth.append(info)
            continue
        state = "reused" if info.get("cached") else "computed"
        rows.append(f"<tr><td>{html.escape(name)}</td><td>{state}</td>"
                    f"<td>{(info.get('seconds') or 0):.1f} s</td></tr>")
    if depth:
        seconds = sum(i.get("seconds") or 0 for i in depth)
        computed = sum(not i.get("cached") for i in depth)
        rows.append(f"<tr><td>depth</td><td>{computed} of {len(depth)} maps computed</td>"
                    f"<td>{seconds:.1f} s</td></tr>")
    return "\n".join(rows)


def build_page(report: dict, results: dict[str, Path], glb: bytes | None,
               accuracy_mm: np.ndarray | None = None, frames: Path | None = None) -> bytes:
    """The page of one capture run: ``report`` (as in ``report.json``), ``results`` (name ->
    this run's file: cameras.json, cloud.ply, ...), the mesh's glTF bytes (None without a
    mesh), the per-vertex accuracy in mm (nan outside the scored region) if scored, and the
    frames stage's folder (the keyframe images) if there is one."""
    data: dict = {"mesh_glb": base64.b64encode(glb).decode("ascii") if glb else None}
    centre = None
    if glb:
        centre = np.asarray(trimesh.load(results["mesh.ply"], process=False,
                                         force="mesh").bounding_box.centroid)
    if accuracy_mm is not None:
        data["accuracy"] = {"colours": _b64(turbo(accuracy_mm, HEAT_MAX_MM)),
                            "max_mm": HEAT_MAX_MM}
    if "cloud.ply" in results:
        data["cloud"] = _cloud(results["cloud.ply"])
    if "cameras.json" in results and centre is not None:
        data["cameras"], data["view_direction"], data["view_up"] = _cameras(
            results["cameras.json"], centre, frames)
    title = f"{report.get('subject', '')} / {report.get('capture', '')}"
    figures = "\n".join(f'<dt>{html.escape(label)}</dt><dd data-figure="{key}">'
                        f"{html.escape(text)}</dd>" for key, label, text in figure_rows(report))
    buttons = ['<button data-mode="colour">Colour</button>',
               '<button data-mode="plain">Plain</button>']
    if accuracy_mm is not None:
        buttons.append('<button data-mode="accuracy">Accuracy</button>')
    for name, label in (("cloud", "Cloud"), ("cameras", "Cameras")):
        if name in data:
            buttons.append(f'<button data-toggle="{name}" aria-pressed="false">{label}</button>')
    viewer = resources.files("facecap.flows") / "viewer"
    page = TEMPLATE.format(
        title=html.escape(title),
        summary=html.escape(run_summary(report)),
        no_mesh="" if glb else '<p class="note">This run made no mesh (it stopped at '
                               f'{html.escape(str(report.get("until", "")))}).</p>',
        buttons="\n".join(buttons), bar=_colour_bar(), max_mm=f"{HEAT_MAX_MM:g}",
        figures=figures, stages=_stage_rows(report),
        three=(viewer / "three.bundle.min.js").read_text() if glb else "",
        data=json.dumps(data).replace("</", "<\\/"),
        viewer=((viewer / "viewer.js").read_text() if glb
                else 'window.facecap = {ready: false, reason: "no mesh"};'))
    return page.encode("utf-8")


PAGE_HEAD = """<!doctype html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<link rel="icon" href="data:,">
<title>{title} · facecap</title>
"""
"""The start of facecap's pages (a format string of ``title``): a phone's width, and no
request for an icon that is not there."""

TEMPLATE = PAGE_HEAD + """<style>
  body {{ margin: 0; font: 15px/1.45 system-ui, sans-serif; color: #222; background: #fff; }}
  main {{ display: flex; flex-wrap: wrap; min-height: 100vh; }}
  #view {{ position: relative; flex: 1 1 480px; min-height: 60vh; }}
  #canvas {{ width: 100%; height: 100%; display: block; touch-action: none; }}
  #controls {{ position: absolute; top: 8px; left: 8px; display: flex; flex-wrap: wrap;
               gap: 6px; }}
  button {{ font: inherit; padding: 6px 12px; border: 1px solid #999; border-radius: 6px;
            background: #fff; cursor: pointer; }}
  button[aria-pressed="true"] {{ background: #2060c0; color: #fff; border-color: #2060c0; }}
  #colourbar {{ position: absolute; bottom: 12px; left: 12px; right: 12px; max-width: 360px; }}
  #colourbar div {{ height: 12px; border-radius: 3px; background: linear-gradient(to right, {bar}); }}
  #colourbar span {{ font-size: 13px; }}
  aside {{ flex: 0 1 380px; padding: 12px 20px; overflow-wrap: anywhere; }}
  h1 {{ font-size: 20px; margin: 4px 0 8px; }}
  dt {{ font-weight: 600; margin-top: 8px; }}
  dd {{ margin: 0; }}
  table {{ border-collapse: collapse; margin-top: 12px; font-size: 14px; }}
  td {{ padding: 2px 10px 2px 0; }}
  .note {{ color: #a04000; }}
  #keyframe {{ position: absolute; right: 8px; top: 52px; margin: 0; max-width: 45%;
               background: #fff; padding: 6px; border: 1px solid #999; border-radius: 6px;
               cursor: pointer; }}
  #keyframe img {{ width: 100%; display: block; }}
  #keyframe figcaption {{ font-size: 13px; }}
</style>
</head>
<body>
<main>
<div id="view">
  <canvas id="canvas"></canvas>
  <div id="controls">
{buttons}
  </div>
  <figure id="keyframe" hidden><img alt=""><figcaption></figcaption></figure>
  <div id="colourbar" hidden><div></div><span>0 mm</span>
    <span style="float: right">{max_mm} mm and more (grey: not scored)</span></div>
</div>
<aside>
  <h1>{title}</h1>
  <p>{summary}</p>
  {no_mesh}
  <dl>
{figures}
  </dl>
  <table>
{stages}
  </table>
</aside>
</main>
<script>{three}</script>
<script id="facecap-data" type="application/json">{data}</script>
<script>{viewer}</script>
</body>
</html>
"""


RESULTS_LINK_SECONDS = 24 * 3600
"""How long the link from the Prefect UI to a capture's page lasts: whoever has it can open
the page (the face in 3D) until then, without credentials. A rerun (every stage reused,
seconds) publishes a fresh one; ``facecap forget`` deletes the link and the page."""


def stored_link(store, key: str | None, name: str) -> str | None:
    """A link that opens file ``name`` of artifact ``key`` of ``store`` (an ArtifactStore)
    in a browser for :data:`RESULTS_LINK_SECONDS`: S3's presigned URL, or for a folder store
    the page server's (``FACECAP_PAGES_URL``); None where the store can make none or does not
    hold the artifact."""

    if not isinstance(key, str) or not KEY_PATTERN.fullmatch(key):
        return None
    try:
        return store.presigned_url(key, name, RESULTS_LINK_SECONDS)
    except (OSError, FacecapError, *network_errors()) as exc:
        # The results are made: a link is not worth failing for (a missing or damaged page,
        # an unreadable link secret, a store that cannot be reached).
        _log.warning("no link to %s of %s: %s", name, key, str(exc).splitlines()[0]
                     if str(exc) else type(exc).__name__)
        return None
