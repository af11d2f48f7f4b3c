"""``index.html``: a capture's results as one self-contained page, and ``mesh.glb``.

The page opens from disk, from a bucket or from a mail attachment: no server, no network.
It holds the mesh as binary glTF (the same bytes as ``mesh.glb``), the accuracy of each
vertex against the scan (as colours of the heat map, with its colour bar in mm), a sample of
the fused cloud, the keyframe cameras as frusta, the figures of ``report.json`` in words and
the stages' times, and the viewer: the three.js bundle vendored in ``pages/viewer`` (MIT,
``pages/viewer/LICENSE-three.txt``; rebuilt by ``tools/viewer/build.sh``) and
``pages/viewer/viewer.js``.
"""

from __future__ import annotations

import base64
import html
import json
from importlib import resources
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import trimesh

from facecap.pages.figures import figure_rows, run_summary, warnings
from facecap.tasks.graph import is_keyframe_row
from facecap_core.frames import frame_name

GLB_NAME = "mesh.glb"
HEAT_MAX_MM = 5.0
"""The heat map's scale: 0 (blue) to this many mm (red) and beyond, as in the PNG heat maps."""
KEYFRAME_SIDE = 480
"""The keyframe images a click on a camera shows are this many pixels on their long side."""
MAX_CLOUD_POINTS = 60_000
"""The fused cloud is sampled down to this many points: enough to see it, a few MB at most."""


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


def _stage_rows(report: dict) -> str:
    """The stage table's rows: each stage computed by this run with its seconds, or reused
    (with the seconds it took when it was computed, which this run did not spend)."""
    rows, depth = [], []
    for name, info in report.get("stages", {}).items():
        if is_keyframe_row(name):
            depth.append(info)
            continue
        seconds = info.get("seconds") or 0
        if info.get("cached"):
            cells = ("reused", f'<span class="muted">({seconds:.1f} s when computed)</span>')
        else:
            cells = ("computed", f"{seconds:.1f} s")
        rows.append(f'<tr data-stage="{html.escape(name)}"><td>{html.escape(name)}</td>'
                    f"<td>{cells[0]}</td><td>{cells[1]}</td></tr>")
    if depth:
        computed = [i for i in depth if not i.get("cached")]
        seconds = sum(i.get("seconds") or 0 for i in computed)
        time = (f"{seconds:.1f} s summed over the maps (made side by side)" if computed
                else '<span class="muted">reused</span>')
        rows.append(f'<tr data-stage="depth"><td>depth</td><td>{len(computed)} of '
                    f"{len(depth)} maps computed</td><td>{time}</td></tr>")
    return "\n".join(rows)


def _ticks() -> str:
    """The colour bar's labels: every mm from 0 to :data:`HEAT_MAX_MM`, the last one "and
    more", each at its place on the bar."""
    count = int(HEAT_MAX_MM)
    return "".join(f'<span style="left: {100 * k / count:g}%">'
                   f"{f'≥ {k} mm' if k == count else k}</span>" for k in range(count + 1))


def build_page(report: dict, results: dict[str, Path], glb: bytes | None,
               accuracy_mm: np.ndarray | None = None, frames: Path | None = None) -> bytes:
    """The page of one capture run: ``report`` (as in ``report.json``), ``results`` (name ->
    this run's file: cameras.json, cloud.ply, ...), the mesh's glTF bytes (None without a
    mesh), the per-vertex accuracy in mm (metric protocol; nan outside the scored regions)
    if scored, and the frames stage's folder (the keyframe images) if there is one. Without
    a mesh the page has no 3D view: it says where the run stopped and what it made."""
    data: dict = {"mesh_glb": base64.b64encode(glb).decode("ascii") if glb else None}
    centre = None
    if glb:
        centre = np.asarray(trimesh.load(results["mesh.ply"], process=False,
                                         force="mesh").bounding_box.centroid)
    if glb and accuracy_mm is not None:
        data["accuracy"] = {"colours": _b64(turbo(accuracy_mm, HEAT_MAX_MM)),
                            "max_mm": HEAT_MAX_MM}
    if glb and "cloud.ply" in results:
        data["cloud"] = _cloud(results["cloud.ply"])
    if glb:
        data["measure"] = _measure_data(report)
    if "cameras.json" in results and centre is not None:
        data["cameras"], data["view_direction"], data["view_up"] = _cameras(
            results["cameras.json"], centre, frames)
    title = f"{report.get('subject', '')} / {report.get('capture', '')}"
    figures = "\n".join(f'<dt>{html.escape(label)}</dt><dd data-figure="{html.escape(key)}">'
                        f"{html.escape(text)}</dd>" for key, label, text in figure_rows(report))
    warned = warnings(report)
    warning_list = ('<ul id="warnings">' + "".join(
        f'<li data-warning="{html.escape(key)}">{html.escape(text)}</li>' for key, text in warned)
        + "</ul>") if warned else ""
    viewer = resources.files("facecap.pages") / "viewer"
    if glb:
        buttons = ['<button data-mode="colour">Colour</button>',
                   '<button data-mode="plain">Plain</button>']
        if "accuracy" in data:
            buttons.append('<button data-mode="accuracy">Accuracy</button>')
        for name, label in (("cloud", "Cloud"), ("cameras", "Cameras")):
            if name in data:
                buttons.append(f'<button data-toggle="{name}" aria-pressed="false">{label}'
                               "</button>")
        if "cloud" in data:  # off, the cloud is seen alone
            buttons.append('<button data-toggle="mesh" aria-pressed="true">Mesh</button>')
        buttons += ['<button data-toggle="wireframe" aria-pressed="false">Wireframe</button>',
                    '<button id="measure-button" aria-pressed="false">Measure</button>',
                    '<label id="light">Light <input type="range" min="-90" max="90" '
                    'value="0" step="5" aria-label="the light\'s side"></label>']
        view = VIEW.format(buttons="\n".join(buttons), ticks=_ticks(),
                           presets=_preset_buttons(data["measure"]))
        no_mesh = ""
    else:
        until = str(report.get("until", ""))
        made = [name for name in report.get("stages", {}) if not is_keyframe_row(name)]
        if any(is_keyframe_row(name) for name in report.get("stages", {})):
            made.append("depth")
        view = ""
        no_mesh = ('<p class="note" id="no-mesh">This run made no mesh: it stopped after '
                   f"{html.escape(until)} (<code>--until {html.escape(until)}</code>), so there "
                   "is no face to turn. It made: "
                   f"{html.escape(', '.join(made)) if made else 'nothing'} (below). Run it "
                   "again without <code>--until</code> for the mesh: what it made is "
                   "reused.</p>")
    page = TEMPLATE.format(
        title=html.escape(title), view=view, main_class="" if glb else ' class="no-view"',
        summary=html.escape(run_summary(report)), no_mesh=no_mesh, warnings=warning_list,
        bar=_colour_bar(), figures=figures, stages=_stage_rows(report),
        three=(viewer / "three.bundle.min.js").read_text() if glb else "",
        data=json.dumps(data).replace("</", "<\\/"),
        viewer=((viewer / "viewer.js").read_text() if glb
                else 'window.facecap = {ready: false, reason: "no mesh"};'))
    return page.encode("utf-8")


def _measure_data(report: dict) -> dict:
    """What the Measure mode needs: the metric scale's 1σ (%, None if unknown) and the
    anatomical presets of ``figures.measurements`` (their vertices and figures)."""
    fig = report.get("figures") or {}
    sigma = (fig.get("scale") or {}).get("sigma_pct")
    presets = []
    for key, m in (fig.get("measurements") or {}).items():
        if isinstance(m, dict) and isinstance(m.get("vertices"), list) and \
                len(m["vertices"]) == 2 and all(isinstance(v, int) for v in m["vertices"]):
            presets.append({"key": str(key), "name": str(m.get("name", key)),
                            "vertices": m["vertices"], "straight": m.get("straight"),
                            "surface": m.get("surface")})
    return {"sigma_pct": sigma if isinstance(sigma, (int, float)) else None,
            "presets": presets}


def _preset_buttons(measure: dict) -> str:
    return "".join(f'<button data-preset="{html.escape(p["key"])}">{html.escape(p["name"])}'
                   "</button>" for p in measure["presets"])


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

VIEW = """<div id="view">
  <canvas id="canvas"></canvas>
  <div id="controls">
{buttons}
  <div class="break"></div>
  <div id="measure" hidden>
    <div>Click two points on the face: the distance between them, straight and along the
      surface, ± the metric scale's uncertainty.</div>
    <div class="presets">{presets}</div>
    <output id="measure-result"></output>
  </div>
  </div>
  <figure id="keyframe" hidden><img alt=""><figcaption></figcaption></figure>
  <div id="colourbar" hidden>
    <div>Accuracy, metric protocol: each vertex's distance to the scan, in the mesh's own
      millimetres</div>
    <div class="ramp"></div>
    <div class="ticks">{ticks}</div>
    <div><i class="grey"></i> not scored (outside the face and the ears)</div>
  </div>
</div>"""
"""The 3D view of a page with a mesh: the canvas, the mode and toggle buttons, the keyframe a
click on a camera opens and the heat map's colour bar."""

TEMPLATE = PAGE_HEAD + """<style>
  body {{ margin: 0; font: 15px/1.45 system-ui, sans-serif; color: #222; background: #fff; }}
  main {{ display: flex; min-height: 100vh; }}
  /* The view keeps the screen's height and stays on it while the figures beside it scroll:
     its colour bar is always in sight, and the wheel over it zooms the face, as in any 3D
     viewer, without taking the page's scrolling away from anything. */
  #view {{ position: sticky; top: 0; align-self: flex-start; flex: 1 1 auto; min-width: 0;
           height: 100vh; }}
  #canvas {{ width: 100%; height: 100%; display: block; touch-action: none; }}
  #controls {{ position: absolute; top: 8px; left: 8px; display: flex; flex-wrap: wrap;
               align-items: flex-start; gap: 6px; }}
  button {{ font: inherit; padding: 6px 12px; border: 1px solid #999; border-radius: 6px;
            background: #fff; cursor: pointer; }}
  button[aria-pressed="true"] {{ background: #2060c0; color: #fff; border-color: #2060c0; }}
  #colourbar {{ position: absolute; bottom: 10px; left: 10px; right: 10px; max-width: 400px;
                padding: 6px 10px 4px; font-size: 13px; line-height: 1.3;
                background: rgba(255, 255, 255, 0.88); border-radius: 6px; }}
  #colourbar .ramp {{ height: 12px; margin: 4px 0 0; border-radius: 3px;
                      background: linear-gradient(to right, {bar}); }}
  #colourbar .ticks {{ position: relative; height: 18px; }}
  #colourbar .ticks span {{ position: absolute; transform: translateX(-50%);
                            white-space: nowrap; }}
  #colourbar .ticks span:first-child {{ transform: none; }}
  #colourbar .ticks span:last-child {{ transform: translateX(-100%); }}
  #colourbar i.grey {{ display: inline-block; width: 12px; height: 12px; border-radius: 2px;
                       background: rgb(170, 170, 170); vertical-align: -1px; }}
  aside {{ flex: 0 0 420px; box-sizing: border-box; padding: 12px 20px;
           overflow-wrap: anywhere; }}
  main.no-view aside {{ flex: 1 1 auto; max-width: 760px; }}
  @media (max-width: 899px) {{
    /* A narrow screen: the view above the figures. */
    main {{ flex-direction: column; }}
    #view {{ position: relative; align-self: stretch; flex: none; height: 70vh; }}
    aside {{ flex: none; }}
  }}
  h1 {{ font-size: 20px; margin: 4px 0 8px; }}
  dt {{ font-weight: 600; margin-top: 8px; }}
  dd {{ margin: 0; }}
  table {{ border-collapse: collapse; margin-top: 12px; font-size: 14px; }}
  th {{ text-align: left; border-bottom: 1px solid #999; }}
  th, td {{ padding: 2px 10px 2px 0; }}
  td:first-child {{ overflow-wrap: normal; }}
  .muted {{ color: #777; }}
  .note {{ color: #a04000; }}
  #warnings {{ margin: 8px 0; padding: 8px 12px 8px 28px; background: #fff0e0;
               border: 1px solid #e0a060; border-radius: 6px; color: #7a3000; }}
  #light {{ display: flex; align-items: center; gap: 4px; padding: 2px 8px;
            background: rgba(255, 255, 255, 0.88); border-radius: 6px; }}
  #light input {{ width: 90px; }}
  #controls .break {{ flex-basis: 100%; height: 0; }}
  #measure {{ max-width: 380px; padding: 6px 10px; box-sizing: border-box;
              font-size: 13px; line-height: 1.35; background: rgba(255, 255, 255, 0.9);
              border-radius: 6px; }}
  #measure[hidden] {{ display: none; }}
  #measure .presets {{ display: flex; flex-wrap: wrap; gap: 4px; margin: 4px 0; }}
  #measure .presets button {{ padding: 2px 8px; font-size: 13px; }}
  #measure output {{ display: block; font-weight: 600; }}
  #keyframe {{ position: absolute; right: 8px; top: 52px; margin: 0; max-width: 45%;
               background: #fff; padding: 6px; border: 1px solid #999; border-radius: 6px;
               cursor: pointer; }}
  #keyframe img {{ width: 100%; display: block; }}
  #keyframe figcaption {{ font-size: 13px; }}
</style>
</head>
<body>
<main{main_class}>
{view}
<aside>
  <h1>{title}</h1>
  <p>{summary}</p>
  {no_mesh}
  {warnings}
  <dl>
{figures}
  </dl>
  <table id="stages">
  <thead><tr><th>stage</th><th>this run</th><th>time</th></tr></thead>
  <tbody>
{stages}
  </tbody>
  </table>
</aside>
</main>
<script>{three}</script>
<script id="facecap-data" type="application/json">{data}</script>
<script>{viewer}</script>
</body>
</html>
"""
