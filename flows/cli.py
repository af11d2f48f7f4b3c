"""The ``facecap`` command line.

Bad input ends with one line ``facecap: error: ...`` on stderr and exit code 2; anything else
that escapes is a bug and keeps its traceback.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from facecap_core.errors import FacecapError, InputError


def _cmd_assets(args) -> int:
    from facecap_core import assets

    folder = assets.menpo3d_data()
    print(assets.PROVENANCE.format(sha=assets.MENPO3D_SHA256))
    print(f"cached in {folder}")
    for name in assets.MENPO3D_FILES:
        print(f"  {folder / name}")
    return 0


def _synth_config(args):
    from facecap_core.config import SynthConfig, build, load_yaml

    overrides = {k: v for k, v in {
        "subject": args.subject, "subject_landmarks": args.subject_landmarks,
        "ict_model": args.ict_model, "width": args.width, "height": args.height,
        "fps": args.fps, "duration_s": args.seconds, "seed": args.seed,
    }.items() if v is not None}
    if args.config:
        return load_yaml(SynthConfig, args.config, overrides)
    return build(SynthConfig, overrides, source="synth options")


def _cmd_synth(args) -> int:
    from facecap_core.synthetic import synthesize

    config = _synth_config(args)
    capture = synthesize(config, args.out, progress=not args.quiet)
    print(f"wrote {capture.video} ({capture.frames} frames, {capture.seconds:.1f} s, "
          f"{capture.seconds / capture.frames:.2f} s/frame) and ground truth in "
          f"{capture.folder / 'gt'}")
    return 0


def _cmd_evaluate(args) -> int:
    from facecap_core import evaluation as ev

    protocols = ev.PROTOCOLS if args.protocol == "both" else (args.protocol,)
    scores = ev.evaluate(args.mesh, args.scan, args.scan_landmarks, args.mesh_landmarks,
                         protocols=protocols)
    if args.heatmap:
        mesh = ev.load_mesh(args.mesh)
        for name, sc in scores.items():
            out = Path(args.heatmap)
            out = out.with_name(f"{out.stem}_{name}{out.suffix or '.png'}")
            ev.error_heatmap(sc.alignment.apply(mesh.vertices), mesh.faces,
                             sc.accuracy_per_vertex, out)
            print(f"heat map: {out}", file=sys.stderr)
    if args.json:
        records = {p: ev.score_json(s) for p, s in scores.items()}
        print(json.dumps(records[protocols[0]] if len(protocols) == 1 else records))
        return 0
    rows = [(f"{Path(args.mesh).name} ({p})", [ev.score_json(s)]) for p, s in scores.items()]
    print(ev.paper_table(rows))
    for p, s in scores.items():
        print(f"{p}: scale {s.scale:.4f}, accuracy under 1 mm {s.accuracy.under_1mm:.1%}, "
              f"completion under 1 mm {s.completion.under_1mm:.1%}")
    return 0


def _cmd_reconstruct(args) -> int:
    from facecap_core.config import KeyframeConfig
    from facecap_core.keyframes import select_keyframes
    from facecap_core.pose.colmap_sfm import run_sfm
    from facecap_core.pose.io import write_outputs
    from facecap_core.video import read_frames

    out = Path(args.out)
    keyframes = select_keyframes(args.video, KeyframeConfig(), progress=True)
    print(f"{len(keyframes.indices)} keyframes of {keyframes.frames_read} frames")
    if args.until == "keyframes":
        out.mkdir(parents=True, exist_ok=True)
        (out / "keyframes.json").write_text(json.dumps({"frame_indices": keyframes.indices}))
        print(f"wrote {out / 'keyframes.json'}")
        return 0
    images = read_frames(args.video, keyframes.indices, width=960)
    poses = run_sfm(images, out / "work" / "sfm", keyframes.video_size)
    path = write_outputs(poses, out / "work" / "sfm", out)
    print(f"{len(poses.frame_indices)}/{len(keyframes.indices)} keyframes registered; "
          f"focal {poses.intrinsics.fx:.1f} px; wrote {path} and {out / 'colmap'}")
    return 0


def _cmd_demo(args) -> int:
    import os

    from facecap_core.baselines import mean_template
    from facecap_core.config import SynthConfig
    from facecap_core.evaluation import paper_table, score_json
    from facecap_core.synthetic import synthesize
    from facecap_core.template import Template

    ict_model = args.ict_model or os.environ.get("FACECAP_ICT_MODEL")
    subject = "ict:0" if ict_model else "james"
    config = SynthConfig(subject=subject, ict_model=ict_model, width=640, height=360,
                         duration_s=2.0)
    out = Path(args.out)
    print(f"synthesizing a {config.duration_s:g} s {config.width}x{config.height} capture "
          f"of {subject} into {out}")
    capture = synthesize(config, out)
    print(f"rendered {capture.frames} frames in {capture.seconds:.1f} s")
    scores = mean_template(Template.default(), capture.gt_mesh, capture.gt_landmarks,
                           heatmap_dir=out)
    print(paper_table([(f"Mean template ({p})", [score_json(s)]) for p, s in scores.items()]))
    print(f"heat maps: {out}/mean_template_*.png")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="facecap",
        description="Metric 3D face meshes from one handheld phone video, and the tools to "
                    "measure them.")
    sub = p.add_subparsers(dest="command", required=True)

    a = sub.add_parser("assets", help="fetch, verify and list the template and sample scan")
    a.set_defaults(func=_cmd_assets)

    s = sub.add_parser("synth", help="render a synthetic capture with exact ground truth")
    s.add_argument("--out", required=True, help="output folder (video.mp4 + gt/)")
    s.add_argument("--subject", help="ict:SEED, ict:mean, james, or a mesh path")
    s.add_argument("--subject-landmarks", help="68 3D landmarks of a mesh-path subject")
    s.add_argument("--ict-model", help="ICT Face Model .npz (or set FACECAP_ICT_MODEL)")
    s.add_argument("--config", help="SynthConfig YAML; the options above override it")
    s.add_argument("--width", type=int)
    s.add_argument("--height", type=int)
    s.add_argument("--fps", type=float)
    s.add_argument("--seconds", type=float, help="sweep duration")
    s.add_argument("--seed", type=int)
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    s.set_defaults(func=_cmd_synth)

    e = sub.add_parser("evaluate", help="score a mesh against a scan (accuracy/completion, mm)")
    e.add_argument("mesh", help="reconstructed mesh (PLY/OBJ, mm)")
    e.add_argument("--scan", required=True, help="ground-truth scan mesh (mm)")
    e.add_argument("--scan-landmarks", help="68 3D landmarks of the scan (defines the region)")
    e.add_argument("--mesh-landmarks", help="68 3D landmarks of the mesh (initial alignment)")
    e.add_argument("--protocol", choices=["similarity", "metric", "both"], default="both")
    e.add_argument("--json", action="store_true", help="print one JSON object")
    e.add_argument("--heatmap", help="write accuracy heat maps to this PNG path")
    e.set_defaults(func=_cmd_evaluate)

    r = sub.add_parser("reconstruct", help="reconstruct a capture (stages so far: keyframes, "
                                           "poses)")
    r.add_argument("video", help="the capture: a handheld ear-to-ear video of a still face")
    r.add_argument("--out", required=True, help="output folder")
    r.add_argument("--until", choices=["keyframes", "poses"], default="poses",
                   help="last stage to run")
    r.set_defaults(func=_cmd_reconstruct)

    d = sub.add_parser("demo", help="synthesize a capture and score the mean-template baseline")
    d.add_argument("--out", default="out/demo")
    d.add_argument("--ict-model", help="ICT Face Model .npz (or set FACECAP_ICT_MODEL)")
    d.set_defaults(func=_cmd_demo)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except FacecapError as exc:
        print(f"facecap: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("facecap: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
