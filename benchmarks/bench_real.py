"""Real captures (no ground truth): does each reconstruct, or is it refused for a true reason?

Runs every capture of ``../shared/data/real`` (or ``--root``) through ``facecap reconstruct``
as a user would (the CLI, a fresh output folder, a shared store), and prints per capture the
exit code, the one-line message or the headline figures (keyframes kept and dropped, yaw
coverage, focal length, metric scale, mesh sanity, support by part), and the seconds. For each
mesh it renders ``compare.png``: the shaded mesh seen through the reconstructed camera of a
frontal and a profile keyframe, beside those photos, lit from the camera and under a raking
light from the side, to look at.

Two measures need no reference. *Roughness* (``report.json`` ``figures.roughness``,
:mod:`facecap_core.nonrigid.roughness`): the share of the face's edges bent over 20° and the
median bend; skin is smooth, the template itself has 2 % and 1.2°. *Split-half distance*
(``--split-half``): the keyframes in sweep order are dealt alternately into two halves, the
dense reconstruction (views, depth maps, fusion, fit) is run on each with the full run's
cameras, and the two meshes are compared over the face after a similarity (median, mean and
95th percentile of the distance from each one's face vertices to the other's surface, mm):
what the halves disagree on is noise.

    python benchmarks/bench_real.py [--root ../shared/data/real] [--out out/bench_real]
        [--only photo_set_31] [--split-half] [--config CONFIG.yaml]

``--config`` is given to ``facecap reconstruct`` and to the halves' stages (e.g.
``mvs: {depth: {method: patchmatch}}`` to compare the depth searches).
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
CAPTURES = {
    # name: (capture path relative to the root, what it should do)
    "photo_set_31": ("photo_set_31/images", "reconstruct: face and the ear on the side seen"),
    "frontal_small_motion": ("frontal_small_motion/images",
                             "a frontal mesh, or refused for too little angular coverage"),
    "head_turn_fixed_camera": ("head_turn_fixed_camera/video.mp4",
                               "refused: the head moves against a still background"),
}


RAKING_LIGHT = np.array([-np.cos(np.radians(20)), -0.25, -np.sin(np.radians(20))])
RAKING_LIGHT /= np.linalg.norm(RAKING_LIGHT)
"""Towards the light, in the camera's frame (x right, y down, z forwards): from the left."""


def _grey(shade: np.ndarray, white: int, valid: np.ndarray, shape) -> np.ndarray:
    """The mesh in grey (``shade`` 0-1 times ``white``) where a ray hit it, white around it,
    as an RGB image of ``shape``."""
    image = np.where(valid[..., None], (shade[..., None] * white).astype(np.uint8), 255)
    return np.broadcast_to(image, shape).astype(np.uint8)


def render_beside(out: Path, capture: Path, picks: int = 2) -> Path | None:
    """The mesh shaded in the cameras of the most frontal and the most profile keyframe,
    each beside its photo: the photo, a blend, the grey mesh lit from the camera, and the
    grey mesh under a raking light from the side (what shows lumps and creases)."""
    from facecap_core.meshio import load_mesh
    from facecap_core.pose.cameras_json import read_cameras_json
    from facecap_core.render import RaycastScene, interpolate, vertex_normals
    from facecap_core.video import read_frames

    if not (out / "mesh.ply").is_file():
        return None
    cams = read_cameras_json(out / "cameras.json")
    mesh = load_mesh(out / "mesh.ply")
    yaws = {}
    report = json.loads((out / "report.json").read_text())
    for rec in report.get("figures", {}).get("coverage", {}).get("yaw_by_frame", []):
        yaws[rec[0]] = rec[1]
    order = sorted(range(len(cams.frame_indices)),
                   key=lambda k: abs(yaws.get(cams.frame_indices[k], 0.0)))
    chosen = [order[0], order[-1]][:picks]
    images = read_frames(capture, [cams.frame_indices[k] for k in chosen])
    scene = RaycastScene()
    scene.add(mesh.vertices, mesh.faces)
    normals = vertex_normals(mesh.vertices, mesh.faces)
    rows = []
    for k in chosen:
        photo = images[cams.frame_indices[k]]
        hits = scene.cast_camera(cams.intrinsics, cams.R[k], cams.t[k])
        n = interpolate(normals, mesh.faces, hits.triangle, hits.bary)
        n_cam = n @ np.asarray(cams.R[k]).T
        render = _grey(np.clip(-n_cam[..., 2], 0, 1) * 0.8 + 0.2, 230, hits.valid, photo.shape)
        blend = np.where(hits.valid[..., None], (0.5 * photo + 0.5 * render).astype(np.uint8),
                         photo)
        # Raking light: grey, lit from the image's left at 20° above the surface it faces,
        # so a lump or a crease of a fraction of a millimetre throws a shadow.
        raking = _grey(np.clip(n_cam @ RAKING_LIGHT, 0, 1) * 0.9 + 0.06, 235, hits.valid,
                       photo.shape)
        rows.append(np.hstack([photo, blend, render, raking]))
    path = out / "compare.png"
    cv2.imwrite(str(path), cv2.cvtColor(np.vstack(rows), cv2.COLOR_RGB2BGR))
    return path


def run(name: str, capture: Path, out: Path, store: Path, config: Path | None = None) -> dict:
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "facecap", "reconstruct", str(capture),
                           "--out", str(out), "--store", str(store)]
                          + (["--config", str(config)] if config else []),
                          cwd=ROOT, capture_output=True, text=True)
    row = {"capture": name, "exit": proc.returncode, "seconds": round(time.perf_counter()
                                                                       - start, 1)}
    errors = [line for line in proc.stderr.splitlines() if line.startswith("facecap:")]
    if errors:
        row["message"] = errors[-1]
    if proc.returncode == 0:
        report = json.loads((out / "report.json").read_text())
        fig = report.get("figures", {})
        cov = fig.get("coverage", {})
        row.update(keyframes=fig.get("keyframes"), dropped=len(fig.get("dropped_keyframes", [])),
                   yaw=f"{cov.get('yaw_min_deg')}..{cov.get('yaw_max_deg')}",
                   focal_px=fig.get("focal_px"), metric_scale=fig.get("metric_scale"),
                   sanity=fig.get("mesh_sanity"), roughness=fig.get("roughness"),
                   parts=fig.get("parts"))
        compare = render_beside(out, capture)
        row["compare"] = str(compare) if compare else None
    return row


def split_half(name: str, out: Path, store: Path, config_file: Path | None = None
               ) -> dict | None:
    """The dense reconstruction of two disjoint halves of a capture's keyframes (sweep order,
    dealt alternately), on the full run's cameras and coarse mesh: view selection, depth
    maps, fusion and fit per half; then the distance between the two meshes over the face.

    The halves share the camera solve because a half of a photo folder is often too few
    photos to solve alone (``photo_set_31``'s halves: 10 of 16 and 2 of 15 register), and
    the cameras are measured apart (against COLMAP); what differs between the halves is
    every image the surface is made from."""
    from facecap_core.evaluation import split_half_distance
    from facecap_core.fitting import stage as fitting_stage
    from facecap_core.meshio import load_mesh
    from facecap_core.mvs import depth, fusion, views
    from facecap_core.nonrigid.roughness import face_vertices
    from facecap_core.pipeline import load_pipeline_config
    from facecap_core.pose.cameras_json import Cameras
    from facecap_core.template import Template

    full = out / name
    if not (full / "report.json").is_file():
        return None
    report = json.loads((full / "report.json").read_text())
    keys = {k.split("-")[0]: store / "artifacts" / k
            for k in re.findall(r'"([a-z]+-[0-9a-f]{32})"', json.dumps(report))}
    frames, coarse, poses = keys["frames"], keys["coarse"], keys["poses"]
    config = load_pipeline_config(config_file)
    cameras = Cameras.read(coarse / "cameras.json")
    meshes, rows = [], []
    for half in (0, 1):
        work = out / f"{name}_half{half}"
        shutil.rmtree(work, ignore_errors=True)
        shutil.copytree(coarse, work / "coarse")
        mine = cameras.model_copy(update={"keyframes": cameras.keyframes[half::2]})
        cams = mine.write(work / "coarse" / "cameras.json")
        views_json = views.main(frames, cams, work / "coarse" / "coarse.ply", work / "views",
                                config.mvs.views, poses / "sparse.npz")
        maps = [depth.main(i, frames, cams, views_json, work / "coarse" / "coarse.ply",
                           work / "depth", config.mvs.depth)
                for i in views.read_views(views_json)]
        cloud = fusion.main(maps, frames, cams, work / "fusion", config.mvs.fusion)
        mesh = fitting_stage.main(cloud, work / "coarse", frames, work / "fit", config.fitting)
        meshes.append(load_mesh(mesh))
        fit = json.loads((work / "fit" / "fit.json").read_text())
        rows.append({"keyframes": len(mine.keyframes), "depth_maps": len(maps),
                     "roughness": fit["roughness"], "cloud_noise": fit["cloud_noise"]})
    template = Template.default()
    distance = split_half_distance(meshes[0].vertices, meshes[1].vertices, template.faces,
                                   face_vertices(template.vertices, template.landmarks))
    return {"halves": rows, "distance": distance}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, default=ROOT.parent / "shared" / "data" / "real")
    parser.add_argument("--out", type=Path, default=ROOT / "out" / "bench_real")
    parser.add_argument("--only", nargs="*", help="capture names to run")
    parser.add_argument("--split-half", action="store_true",
                        help="also reconstruct two disjoint halves of the keyframes of each "
                             "capture that reconstructs, and measure the distance between "
                             "their meshes")
    parser.add_argument("--config", type=Path, help="PipelineConfig YAML for every run")
    args = parser.parse_args()
    if not args.root.is_dir():
        sys.exit(f"no real captures at {args.root}")
    store = args.out / "store"
    rows = []
    for name, (rel, expected) in CAPTURES.items():
        if args.only and name not in args.only:
            continue
        row = run(name, args.root / rel, args.out / name, store, args.config)
        row["expected"] = expected
        if args.split_half and row["exit"] == 0:
            try:
                row["split_half"] = split_half(name, args.out, store, args.config)
            except Exception as exc:  # a failed half is a figure of its own, not the end
                row["split_half"] = {"error": f"{type(exc).__name__}: {exc}"}
        rows.append(row)
        print(json.dumps(row), flush=True)
    (args.out / "report.json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
