"""The texture atlas against per-vertex colour, on a synthetic capture.

    python benchmarks/bench_texture.py [--subject ict:0] [--width 1280 --height 720]
        [--seconds 1.5] [--keyframes 9] [--out out/bench_texture] [--ict-model PATH]

A synthetic capture (rendered once, cached in ``OUT/captures``) gives the ground truth; the
default template is fitted as in ``bench_fitting.py`` (cloud sampled from the ground truth
with noise, holes and outliers; landmarks with 1 mm noise), and ``--keyframes`` frames
spread over the sweep (ground-truth cameras, 960 px wide as the fitting stage reads them)
colour it both ways: per-vertex (:func:`facecap_core.texture.vertex_colours`) and the
1024² atlas (:func:`facecap_core.texture.bake_texture`, timed). The fitted mesh is then
ray-cast from the cameras of the keyframes and of held-out frames (midway between
keyframes, full resolution) and each way's colour compared with the video frame over the
face region (the template's ``face`` triangles): PSNR and SSIM (grey, Gaussian window σ 1.5,
the rendering composited over the frame outside the face). Writes ``OUT/report.md`` and
``OUT/results.json``, and ``OUT/mesh/`` (the textured mesh files).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_fitting import DEFAULT_ICT, pick_keyframes  # noqa: E402
from captures import capture_for  # noqa: E402

from facecap.synthetic import load_gt_cameras  # noqa: E402
from facecap.synthetic.cloud import mvs_like_cloud  # noqa: E402
from facecap_core.fitting import FittingConfig, fit, keyframes_from_video, write_mesh  # noqa: E402
from facecap_core.meshio import load_landmarks, load_mesh  # noqa: E402
from facecap_core.render import RaycastScene, interpolate  # noqa: E402
from facecap_core.template import Template  # noqa: E402
from facecap_core.texture import bake_texture, sample_atlas, template_uv, vertex_colours  # noqa: E402
from facecap_core.video import read_frames  # noqa: E402

FRAME_WIDTH = 960
"""The keyframes' width, as the fitting stage reads them."""


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((np.asarray(a, float) - np.asarray(b, float)) ** 2))
    return 10.0 * np.log10(255.0 ** 2 / max(mse, 1e-12))


def ssim_map(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """SSIM per pixel of two grey images (0-255), Gaussian window σ 1.5 (Wang et al. 2004)."""
    a, b = a.astype(np.float64), b.astype(np.float64)
    c1, c2 = (0.01 * 255) ** 2, (0.03 * 255) ** 2

    def blur(x):
        return cv2.GaussianBlur(x, (11, 11), 1.5)

    ma, mb = blur(a), blur(b)
    va, vb, cov = blur(a * a) - ma ** 2, blur(b * b) - mb ** 2, blur(a * b) - ma * mb
    return ((2 * ma * mb + c1) * (2 * cov + c2)) / ((ma ** 2 + mb ** 2 + c1) * (va + vb + c2))


def grey(rgb: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(np.clip(np.round(rgb), 0, 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)


def compare(frame: np.ndarray, intr, R, t, scene, faces, face_tri, colours, atlas, layout
            ) -> dict:
    """PSNR and SSIM of the per-vertex and the textured rendering against ``frame`` over the
    pixels where the fitted mesh's face region is hit."""
    hits = scene.cast_camera(intr, R, t)
    mask = hits.valid & face_tri[np.maximum(hits.triangle, 0)]
    tri, bary = hits.triangle[mask], hits.bary[mask]
    out = {"pixels": int(mask.sum())}
    for name, rgb in (("vertex", interpolate(colours.astype(float), faces, tri, bary)),
                      ("atlas", sample_atlas(atlas, layout, tri, bary))):
        render = frame.astype(float).copy()
        render[mask] = rgb
        out[name] = {"psnr": round(psnr(render[mask], frame[mask]), 2),
                     "ssim": round(float(ssim_map(grey(render), grey(frame))[mask].mean()), 4)}
    return out


def run(subject: str, out: Path, width: int, height: int, seconds: float, n_keyframes: int,
        ict_model: str | None) -> dict:
    folder = capture_for(subject, out / "captures", ict_model, width=width, height=height,
                         duration_s=seconds)
    gt = load_mesh(folder / "gt" / "mesh.ply", "ground-truth mesh")
    gt_v, gt_f = np.asarray(gt.vertices, float), np.asarray(gt.faces, np.int64)
    gt_lm = load_landmarks(folder / "gt" / "landmarks.json")
    cloud, normals = mvs_like_cloud(gt_v, gt_f, density=0.7, noise_mm=0.5, holes=0.2,
                                    outliers=0.05, seed=0)
    landmarks = gt_lm + np.random.default_rng([0, 7]).normal(0.0, 1.0, gt_lm.shape)
    intr, poses = load_gt_cameras(folder / "gt" / "cameras.json")
    kf_ids = pick_keyframes(poses, n_keyframes)
    held_out = sorted(set(pick_keyframes(poses, 2 * n_keyframes - 1)) - set(kf_ids))
    keyframes = keyframes_from_video(folder / "video.mp4", intr, poses, kf_ids,
                                     width=FRAME_WIDTH)
    template = Template.default()
    print(f"{subject}: fitting ({len(keyframes)} keyframes {kf_ids}, held out {held_out})",
          flush=True)
    vertices = fit(template, cloud, landmarks, keyframes, None, normals, FittingConfig()).vertices
    faces = template.faces
    layout = template_uv(faces)
    t0, c0 = time.perf_counter(), time.process_time()
    colours, _ = vertex_colours(vertices, faces, keyframes)
    t1, c1 = time.perf_counter(), time.process_time()
    atlas, info = bake_texture(vertices, faces, keyframes, layout, fill_colours=colours)
    t2, c2 = time.perf_counter(), time.process_time()
    write_mesh(out / "mesh", vertices, faces, colours, (layout, atlas))
    scene = RaycastScene()
    scene.add(vertices, faces)
    face_tri = template.regions["face"][faces].all(1)
    by_index = {p["index"]: p for p in poses}
    rows = {"keyframes": [], "held out": []}
    for kf, i in zip(keyframes, kf_ids):
        rows["keyframes"].append({"frame": i, **compare(kf.image, kf.intrinsics, kf.R, kf.t,
                                                        scene, faces, face_tri, colours,
                                                        atlas, layout)})
    frames = read_frames(folder / "video.mp4", held_out)
    for i in held_out:
        p = by_index[i]
        rows["held out"].append({"frame": i, **compare(frames[i], intr, p["R"], p["t"], scene,
                                                       faces, face_tri, colours, atlas, layout)})
    return {"subject": subject, "capture": f"{width}x{height}, {seconds:g} s",
            "keyframes": kf_ids, "held_out": held_out, "rows": rows,
            "seconds": {"vertex_colours_wall": round(t1 - t0, 2),
                        "vertex_colours_cpu": round(c1 - c0, 2),
                        "atlas_wall": round(t2 - t1, 2), "atlas_cpu": round(c2 - c1, 2)},
            "atlas": {k: info[k] for k in ("size", "texels", "texels_seen")}}


def report(result: dict, out: Path) -> str:
    lines = [f"# Texture: UV atlas against per-vertex colour ({result['subject']}, "
             f"{result['capture']})", "",
             f"Keyframes {result['keyframes']}; held-out frames {result['held_out']}. Over the "
             "face region, mean over frames:", "",
             "| Frames | Per-vertex PSNR dB | Atlas PSNR dB | Per-vertex SSIM | Atlas SSIM |",
             "|---|---:|---:|---:|---:|"]
    for name, rows in result["rows"].items():
        def mean(way, key, rows=rows):
            return np.mean([r[way][key] for r in rows])
        lines.append(f"| {name} ({len(rows)}) | {mean('vertex', 'psnr'):.2f} | "
                     f"{mean('atlas', 'psnr'):.2f} | {mean('vertex', 'ssim'):.3f} | "
                     f"{mean('atlas', 'ssim'):.3f} |")
    s = result["seconds"]
    lines += ["", f"Atlas {result['atlas']['size']}², {result['atlas']['texels']} texels "
              f"({result['atlas']['texels_seen']} seen): baked in {s['atlas_wall']:.1f} s wall, "
              f"{s['atlas_cpu']:.1f} s CPU (per-vertex colours {s['vertex_colours_wall']:.1f} s "
              f"wall).", ""]
    text = "\n".join(lines)
    out.mkdir(parents=True, exist_ok=True)
    (out / "report.md").write_text(text)
    (out / "results.json").write_text(json.dumps(result, indent=1))
    return text


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--subject", default="ict:0")
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--height", type=int, default=720)
    ap.add_argument("--seconds", type=float, default=1.5)
    ap.add_argument("--keyframes", type=int, default=9)
    ap.add_argument("--out", type=Path, default=Path("out/bench_texture"))
    ap.add_argument("--ict-model", default=os.environ.get("FACECAP_ICT_MODEL") or
                    (str(DEFAULT_ICT) if DEFAULT_ICT.is_file() else None))
    args = ap.parse_args(argv)
    result = run(args.subject, args.out, args.width, args.height, args.seconds, args.keyframes,
                 args.ict_model)
    print(report(result, args.out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
