"""``index.html``: a capture's results as one self-contained page, and ``mesh.glb``.

The page opens from disk, from a bucket or from a mail attachment: no server, no network.
It holds the mesh as binary glTF (the same bytes as ``mesh.glb``), the accuracy of each
vertex against the scan (as colours of the heat map, with its colour bar in mm), a sample of
the fused cloud, the keyframe cameras as frusta, the scan it was scored against (beside the
mesh, :mod:`facecap.pages.scan`), the figures of ``report.json`` in words and the stages'
times, links to download the results folder's files, and the viewer: the three.js bundle
vendored in ``pages/viewer`` (MIT, ``pages/viewer/LICENSE-three.txt``; rebuilt by
``tools/viewer/build.sh``) and ``pages/viewer/viewer.js``. The HTML is
``templates/capture.html.j2``'s.
"""

from __future__ import annotations

import base64
from concurrent.futures import ThreadPoolExecutor
from importlib import resources
from pathlib import Path

import cv2
import numpy as np
from markupsafe import Markup

from facecap.pages.figures import figure_rows, run_summary, warnings
from facecap.pages.render import render
from facecap.pages.scan import stored_scan
from facecap.tasks.graph import is_keyframe_row
from facecap_core.camera import camera_center
from facecap_core.frames import frame_name
from facecap_core.lazy import LazyModule
from facecap_core.meshio import ply_vertices
from facecap_core.pose.cameras_json import Cameras

o3d = LazyModule("open3d")
trimesh = LazyModule("trimesh")

GLB_NAME = "mesh.glb"
HEAT_MAX_MM = 5.0
"""The heat map's scale: 0 (blue) to this many mm (red) and beyond, as in the PNG heat maps."""
KEYFRAME_SIDE = 480
"""The keyframe images a click on a camera shows are this many pixels on their long side."""
MAX_CLOUD_POINTS = 60_000
"""The fused cloud is sampled down to this many points: enough to see it, a few MB at most."""
DOWNLOADS = (("mesh.ply", "Mesh, PLY with vertex colours"),
             ("mesh.obj", "Mesh, OBJ"), ("mesh.mtl", "its material, MTL"),
             ("texture.png", "its texture, PNG"),
             ("mesh.glb", "Mesh, binary glTF (Blender, Windows 3D Viewer)"),
             ("report.json", "Report, JSON: every figure of the run"))
"""The files of the results folder the page links for download, those the run made:
relative links, to the files beside ``index.html``."""


def mesh_glb(mesh_ply: Path) -> bytes:
    """The mesh as binary glTF (Blender, three.js, Windows 3D Viewer): the fitting stage's
    textured ``mesh.glb`` beside ``mesh_ply`` where it made one (split at the UV seams, the
    template's vertices first), else the mesh with its vertex colours."""
    textured = Path(mesh_ply).with_name(GLB_NAME)
    if textured.is_file():
        return textured.read_bytes()
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


def _keyframe_images(frames: Path | None, indices: list[int]) -> list[str | None]:
    """:func:`_keyframe_image` of each keyframe, decoded and encoded on two threads (OpenCV
    lets go of the GIL): 45 keyframes of a 720p capture take 0.8 s on one."""
    with ThreadPoolExecutor(2) as pool:
        return list(pool.map(lambda index: _keyframe_image(frames, index), indices))


def _cameras(cameras_json: Path, centre: np.ndarray, frames: Path | None = None
             ) -> tuple[dict, list, list]:
    """Frusta (line segments, mm) of the keyframe cameras with their centres and images (a
    click on a camera shows what it saw), and the direction and up vector from which they saw
    the head (the viewer starts there)."""
    cams = Cameras.read(cameras_json)
    intr, keyframes = cams.intrinsics, cams.keyframes
    rotations = np.array([k.R for k in keyframes], float)
    centres = np.array([camera_center(k.R, k.t) for k in keyframes], float)
    depth = 0.15 * float(np.median(np.linalg.norm(centres - centre, axis=1)))
    w, h, fx, fy = intr.width, intr.height, intr.fx, intr.fy
    cx, cy = intr.cx, intr.cy
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
            "frames": [k.frame_index for k in keyframes],
            "images": _keyframe_images(frames, [k.frame_index for k in keyframes])}
    return data, direction.tolist(), up.tolist()


def _cloud(cloud_ply: Path, seed: int = 0) -> dict:
    vertices = ply_vertices(cloud_ply)  # the fusion's own file: no open3d to load
    if vertices is not None:
        points = np.stack([vertices[k] for k in "xyz"], 1).astype(np.float32)
        colours = (np.stack([vertices[k] for k in ("red", "green", "blue")], 1)
                   .astype(np.uint8) if {"red", "green", "blue"} <= set(vertices.dtype.names)
                   else np.full((len(points), 3), 160, np.uint8))
    else:
        cloud = o3d.io.read_point_cloud(str(cloud_ply))
        points = np.asarray(cloud.points, np.float32)
        colours = (np.clip(np.asarray(cloud.colors), 0, 1) * 255).astype(np.uint8) \
            if cloud.has_colors() else np.full((len(points), 3), 160, np.uint8)
    if len(points) > MAX_CLOUD_POINTS:
        keep = np.sort(np.random.default_rng(seed).choice(len(points), MAX_CLOUD_POINTS,
                                                           replace=False))
        points, colours = points[keep], colours[keep]
    return {"positions": _b64(points), "colours": _b64(colours), "count": int(len(points))}


def _stage_rows(report: dict) -> tuple[list[dict], dict | None]:
    """The stage table's rows: each stage computed by this run with its seconds, or reused
    (with the seconds it took when it was computed, which this run did not spend); and the
    depth maps as one row (how many this run computed of how many, and their seconds summed)
    if the run has any."""
    rows, depth = [], []
    for name, info in report.get("stages", {}).items():
        if is_keyframe_row(name):
            depth.append(info)
            continue
        rows.append({"name": name, "cached": bool(info.get("cached")),
                     "seconds": f"{info.get('seconds') or 0:.1f}"})
    if not depth:
        return rows, None
    computed = [i for i in depth if not i.get("cached")]
    seconds = sum(i.get("seconds") or 0 for i in computed)
    return rows, {"computed": len(computed), "maps": len(depth), "seconds": f"{seconds:.1f}"}


def _ticks() -> list[tuple[str, str]]:
    """The colour bar's labels: every mm from 0 to :data:`HEAT_MAX_MM`, the last one "and
    more", each with its place on the bar (% of its width)."""
    count = int(HEAT_MAX_MM)
    return [(f"{100 * k / count:g}", f"≥ {k} mm" if k == count else str(k))
            for k in range(count + 1)]


def _downloads(results: dict[str, Path]) -> list[dict]:
    """The download links: each of :data:`DOWNLOADS` the run made (``report.json``, written
    beside the page, always), with its size where known."""
    links = []
    for name, label in DOWNLOADS:
        if name == "report.json" or (name in results and Path(results[name]).is_file()):
            size = Path(results[name]).stat().st_size if name in results else None
            links.append({"name": name, "label": label,
                          "size": f"{size / 2**20:.1f} MB" if size and size >= 2**20
                          else f"{size / 2**10:.0f} kB" if size else ""})
    return links


def _scan(vertices: np.ndarray, faces: np.ndarray) -> dict:
    return {"positions": _b64(np.asarray(vertices, np.float32)),
            "index": _b64(np.asarray(faces, np.uint32)), "faces": int(len(faces))}


def page_parts(report: dict, results: dict[str, Path], has_mesh: bool,
               frames: Path | None = None,
               scan: tuple[np.ndarray, np.ndarray] | None = None) -> dict:
    """What the page shows that the run's artifacts alone decide, as JSON-ready data: the
    fused cloud's sample, the scan (given, or the one the run was scored against), the
    keyframe cameras with their images and the view they saw the head from. The slow part
    of a page (the keyframes decoded, the cloud sampled): a rerun of the same artifacts
    takes it from the store (:func:`facecap.pages.stored.stored_parts`)."""
    parts: dict = {}
    if not has_mesh:
        return parts
    if "cloud.ply" in results:
        parts["cloud"] = _cloud(results["cloud.ply"])
    scan = scan if scan is not None else stored_scan(report)
    if scan is not None:
        parts["scan"] = _scan(*scan)
    if "cameras.json" in results:
        parts["cameras"], parts["view_direction"], parts["view_up"] = _cameras(
            results["cameras.json"], _box_centre(results["mesh.ply"]), frames)
    return parts


def parts_complete(report: dict, parts: dict, frames: Path | None) -> bool:
    """Whether ``parts`` (:func:`page_parts`) hold all that the run's page shows: the scan of
    a scored run and the image of every keyframe. Only such parts are worth keeping for a
    rerun: a store that failed for a moment must not leave its holes in every later page."""
    if parts and "evaluation" in report.get("stages", {}) and "scan" not in parts:
        return False
    return frames is None or all(parts.get("cameras", {}).get("images", []))


def build_page(report: dict, results: dict[str, Path], glb: bytes | None,
               accuracy_mm: np.ndarray | None = None, frames: Path | None = None,
               scan: tuple[np.ndarray, np.ndarray] | None = None,
               parts: dict | None = None) -> bytes:
    """The page of one capture run: ``report`` (as in ``report.json``), ``results`` (name ->
    this run's file: cameras.json, cloud.ply, ...), the mesh's glTF bytes (None without a
    mesh), the per-vertex accuracy in mm (metric protocol; nan outside the scored regions)
    if scored, the frames stage's folder (the keyframe images) if there is one, and the scan
    (vertices in the mesh's frame, triangles) to show beside the mesh: by default the one
    the run was scored against, from its store (:func:`facecap.pages.scan.stored_scan`).
    ``parts``: :func:`page_parts` of the same, made already. Without a mesh the page has no
    3D view: it says where the run stopped and what it made."""
    if parts is None:
        parts = page_parts(report, results, bool(glb), frames, scan)
    data: dict = {"mesh_glb": base64.b64encode(glb).decode("ascii") if glb else None}
    if glb and accuracy_mm is not None:
        data["accuracy"] = {"colours": _b64(turbo(accuracy_mm, HEAT_MAX_MM)),
                            "max_mm": HEAT_MAX_MM}
    if glb:
        data.update({name: parts[name] for name in ("cloud",) if name in parts})
        data["measure"] = _measure_data(report)
        data.update({name: parts[name] for name in ("scan", "cameras", "view_direction",
                                                    "view_up") if name in parts})
    made = [name for name in report.get("stages", {}) if not is_keyframe_row(name)]
    if any(is_keyframe_row(name) for name in report.get("stages", {})):
        made.append("depth")
    stages, depth = _stage_rows(report)
    viewer = resources.files("facecap.pages") / "viewer"
    return render(
        "capture.html.j2", glb=bool(glb),
        title=f"{report.get('subject', '')} / {report.get('capture', '')}",
        summary=run_summary(report), until=str(report.get("until", "")), made=made,
        warnings=warnings(report), figures=figure_rows(report), stages=stages, depth=depth,
        accuracy="accuracy" in data, cloud="cloud" in data, cameras="cameras" in data,
        scan="scan" in data, downloads=_downloads(results),
        presets=data["measure"]["presets"] if glb else [], ticks=_ticks(), bar=_colour_bar(),
        data=data,
        # The page's own scripts, markup by construction.
        three=Markup((viewer / "three.bundle.min.js").read_text()) if glb else "",
        viewer=Markup((viewer / "viewer.js").read_text()) if glb else "")


def _box_centre(mesh_ply: Path) -> np.ndarray:
    """The centre of the mesh's bounding box (read without trimesh where the file allows)."""
    vertices = ply_vertices(mesh_ply)
    if vertices is not None and len(vertices):
        xyz = np.stack([vertices[k] for k in "xyz"], 1).astype(float)
    else:
        xyz = np.asarray(trimesh.load(mesh_ply, process=False, force="mesh").vertices, float)
    return (xyz.min(0) + xyz.max(0)) / 2


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
                            "surface": m.get("surface"), "anatomical": m.get("anatomical")})
    return {"sigma_pct": sigma if isinstance(sigma, (int, float)) else None,
            "presets": presets}
