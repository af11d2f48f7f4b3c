"""The ``facecap`` commands that run no flow: assets, synthetic captures, scoring one mesh,
training the ear model, and removing a subject's data or old artifacts."""

from __future__ import annotations

import json
import logging
import shlex
import sys
import tempfile
from datetime import UTC, datetime, timedelta
from pathlib import Path

from facecap_core.errors import InputError

# Each import inside a command says why it is there.


def assets(args) -> int:
    # Could be at the top: loaded before any command runs (the runner imports it).
    from facecap_core import assets

    folder = assets.menpo3d_data()
    print(assets.PROVENANCE.format(sha=assets.MENPO3D_SHA256))
    print(f"cached in {folder}")
    for name in assets.MENPO3D_FILES:
        print(f"  {folder / name}")
    return 0


def synth_config(args):
    # The synthetic world's package (its scenes, subjects and renderer) only for `synth`;
    # facecap_core.config is loaded already.
    from facecap.synthetic.config import SynthConfig
    from facecap_core.config import build, load_yaml

    overrides = {k: v for k, v in {
        "subject": args.subject, "subject_landmarks": args.subject_landmarks,
        "ict_model": args.ict_model, "width": args.width, "height": args.height,
        "fps": args.fps, "duration_s": args.seconds, "seed": args.seed,
    }.items() if v is not None}
    if args.config:
        return load_yaml(SynthConfig, args.config, overrides)
    return build(SynthConfig, overrides, source="synth options")


def synth(args) -> int:
    # The synthetic world's package (its scenes, subjects and renderer) only for `synth`.
    from facecap.synthetic import synthesize

    config = synth_config(args)
    capture = synthesize(config, args.out, progress=not args.quiet, inputs=(args.config,))
    print(f"wrote {capture.video} ({capture.frames} frames, {capture.seconds:.1f} s, "
          f"{capture.seconds / capture.frames:.2f} s/frame) and ground truth in "
          f"{capture.folder / 'gt'}")
    return 0


def evaluate(args) -> int:
    # Could be at the top: the pipeline, loaded by the parser's stage graph, has all three.
    from facecap_core import evaluation as ev
    from facecap_core.evaluation.stage import scored_per_vertex
    from facecap_core.meshio import load_mesh

    protocols = ev.PROTOCOLS if args.protocol == "both" else (args.protocol,)
    inputs = (args.mesh, args.scan, args.scan_landmarks, args.mesh_landmarks)
    heatmaps = _heatmap_paths(args.heatmap, protocols, inputs) if args.heatmap else {}
    scores = ev.evaluate(args.mesh, args.scan, args.scan_landmarks, args.mesh_landmarks,
                         protocols=protocols)
    if heatmaps:
        # Could be at the top: light (what they import is loaded already; the scratch folder's by
        # facecap.console).
        from facecap.tasks.outputs import ResultWriter
        from facecap.tasks.scratch import process_scratch

        mesh = load_mesh(args.mesh)
        folder = Path(args.heatmap).parent
        # Rendered into this process's scratch, then written as the reconstruction writes its
        # results: never through a link, never over an input.
        with (tempfile.TemporaryDirectory(dir=process_scratch()) as scratch,
              ResultWriter(folder, inputs) as writer):
            for name, sc in scores.items():
                drawn = ev.error_heatmap(sc.alignment.apply(mesh.vertices), mesh.faces,
                                         scored_per_vertex(sc),
                                         Path(scratch) / heatmaps[name].name)
                writer.add(heatmaps[name].name, source=drawn)
            writer.commit()
        for name in scores:
            print(f"heat map: {heatmaps[name]}", file=sys.stderr)
    if args.json:
        records = {p: ev.score_json(s) for p, s in scores.items()}
        print(json.dumps(records[protocols[0]] if len(protocols) == 1 else records))
        return 0
    rows = [(f"{Path(args.mesh).name} ({p})", [ev.score_json(s)]) for p, s in scores.items()]
    print("Face region\n")
    print(ev.paper_table(rows))
    print("\nEar region\n")
    print(ev.paper_table(rows, region="ears"))
    print()
    for p, s in scores.items():
        print(f"{p}: scale {s.scale:.4f}, accuracy under 1 mm {s.accuracy.under_1mm:.1%}, "
              f"completion under 1 mm {s.completion.under_1mm:.1%}; ears: accuracy under 1 mm "
              f"{s.ears.accuracy.under_1mm:.1%}, completion under 1 mm "
              f"{s.ears.completion.under_1mm:.1%}")
    return 0


def _heatmap_paths(heatmap: str, protocols: tuple[str, ...], inputs: tuple) -> dict[str, Path]:
    """The heat map of each protocol, ``STEM_<protocol>SUFFIX`` beside ``heatmap``; refused
    before any scoring where they cannot be written: a suffix OpenCV writes no image for, a
    folder facecap keeps for itself, a name that is one of the inputs."""
    # Could be at the top: OpenCV (the pipeline's), the outputs' module (light) and the runner
    # (flows.service's) are loaded already or cost next to nothing.
    import cv2

    from facecap.tasks.outputs import check_output_place, check_result_names
    from facecap.tasks.runner import default_store_url

    given = Path(heatmap)
    paths = {p: given.with_name(f"{given.stem}_{p}{given.suffix or '.png'}") for p in protocols}
    suffix = next(iter(paths.values())).suffix
    if not cv2.haveImageWriter(f"heatmap{suffix}"):
        raise InputError(f"--heatmap {heatmap}: no image can be written with the suffix "
                         f"{suffix}; give a path ending in .png")
    _check_folder_path(given.parent, f"--heatmap {heatmap}")
    check_output_place(given.parent, default_store_url(), option="--heatmap")
    check_result_names(given.parent, [path.name for path in paths.values()], inputs,
                       option="--heatmap")
    return paths


def _check_folder_path(folder: Path, option: str) -> None:
    """The nearest existing folder on the way to ``folder`` is a folder, not a file."""
    for above in (folder, *folder.parents):
        if above.exists():
            if not above.is_dir():
                raise InputError(f"{option}: {above} is a file, not a folder; give a path in "
                                 "a folder")
            return


def print_removal(removal, dry_run: bool, in_use: bool = True) -> None:
    """What a removal removed and kept; ``in_use``: the line on what a run in progress
    holds too (``forget`` says it as its error instead)."""
    verb = "would remove" if dry_run else "removed"
    print(f"{verb} {len(removal.artifacts)} artifacts, {len(removal.folders)} results "
          f"folders and {removal.history_entries} evaluation-history entries")
    for folder in removal.folders:
        print(f"  {folder}")
    if removal.kept:
        count = len(removal.kept)
        print(f"kept {count} entr{'ies' if count > 1 else 'y'} of the results folders that "
              "facecap did not write (or that changed since); look at them and remove them "
              "yourself if they hold the subject's data:")
        for path in removal.kept:
            print(f"  {path}")
    if removal.in_use and in_use:
        count = len(removal.in_use)
        print(f"kept {count} artifact{'s' if count > 1 else ''} that a run in progress uses; "
              "run this again when it has ended")


def forget(args) -> int:
    # Could be at the top: light or loaded already (the runner by flows.service, the scratch
    # folder's by facecap.console).
    from facecap.tasks import lifecycle
    from facecap.tasks.runner import check_store, default_store_url
    from facecap.tasks.scratch import remove_orphans

    remove_orphans()  # a killed run's scratch holds frames of the face too
    store = check_store(args.store or default_store_url())
    root, out = (Path(args.root) if args.root else None), (Path(args.out) if args.out else None)
    planned = lifecycle.plan_forget(store, args.subject, root, out)
    pages = {}
    if out is not None and not args.dry_run and (out / "index.html").is_file():
        # Could be at the top: the dataset page's module is light (what it imports is loaded
        # already).
        from facecap.pages.dataset import dataset_page_without

        # Its thumbnails show the faces: made now, without the subject's rows, so that a
        # results folder whose page cannot be made stops the forget before anything goes.
        pages["index.html"] = dataset_page_without(out, args.subject)

    def ui_pages() -> None:
        # The UI pages first (the preview shows the face): a server that cannot be reached
        # then leaves everything in place for another try.
        if planned.captures:
            print(f"removed {_forget_ui(planned.captures)} UI artifacts of "
                  f"{', '.join(planned.captures)}")

    removal = lifecycle.remove(store, planned, args.subject, out, dry_run=args.dry_run,
                               results=pages, first=ui_pages)
    print_removal(removal, args.dry_run, in_use=False)
    if removal.in_use:  # a subject's data left behind is no success, whoever holds it
        count = len(removal.in_use)
        again = " ".join(["facecap forget", shlex.quote(args.subject), *(
            f"{option} {shlex.quote(value)}" for option, value in (
                ("--root", args.root), ("--out", args.out), ("--store", args.store)) if value)])
        raise InputError(f"a run in progress uses {count} artifact{'s' if count > 1 else ''} "
                         f"of {args.subject}, kept in the store; run {again} again when that "
                         "run has ended (the rest is removed)")
    return 0


def _forget_ui(captures: list[str]) -> int:
    # The UI's module imports Prefect: not at the top, which `facecap --help` loads; by now main has
    # loaded Prefect (flows.service), httpx and the console.
    import httpx

    from facecap.console import prefect_env
    from facecap.flows.ui import forget_artifacts

    prefect_env()
    try:
        return forget_artifacts(captures)
    except (httpx.HTTPError, OSError) as exc:
        # Prefect's settings: not at the top, which `facecap --help` loads; loaded by now.
        from prefect.settings import PREFECT_API_URL

        raise InputError(f"the Prefect server {PREFECT_API_URL.value() or '(local)'} cannot "
                         f"be reached ({type(exc).__name__}) to remove the UI pages of "
                         f"{', '.join(captures)}; start it or set PREFECT_API_URL, then run "
                         "facecap forget again (nothing was removed)") from None


def store_prune(args) -> int:
    # Could be at the top: light or loaded already (the runner by flows.service, the scratch
    # folder's by facecap.console).
    from facecap.tasks import lifecycle
    from facecap.tasks.runner import check_store, default_store_url
    from facecap.tasks.scratch import remove_orphans

    remove_orphans()  # what killed runs left in FACECAP_HOME
    if args.unreferenced and not args.out:
        raise InputError("--unreferenced needs the results folders whose reports keep their "
                         "artifacts; give them with --out")
    if args.older_than_days is None and not args.unreferenced:
        raise InputError("say what to prune: --older-than-days N, or --unreferenced --out OUT")
    days = args.older_than_days if args.older_than_days is not None else 1.0
    if not 0 <= days <= 36500:
        raise InputError(f"--older-than-days {days:g} is not an age; give the number of days, "
                         "0 to 36500")
    store = check_store(args.store or default_store_url())
    before = datetime.now(UTC) - timedelta(days=days)
    if args.unreferenced:
        removal = lifecycle.prune_unreferenced(store, [Path(o) for o in args.out], before,
                                               dry_run=args.dry_run)
    else:
        removal = lifecycle.prune(store, before, dry_run=args.dry_run)
    print_removal(removal, args.dry_run)
    for problem in removal.damaged.values():  # each problem says what to do
        print(f"kept a damaged artifact, whose age cannot be read: {problem}")
    return 0


def train_ears(args) -> int:
    # The ear trainer's package (its contours and renders; dlib when a model is trained) only for
    # `train-ears`.
    from facecap.ear_training import train

    path = train(args.out, progress=True)
    print(f"ear model written to {path}")
    return 0


def pages(args) -> int:
    """``facecap pages``: serve the store's pages until interrupted."""

    # Could be at the top: the page server's module is light and the runner is loaded already.
    from facecap.pages.server import address, page_server
    from facecap.tasks.runner import check_store, default_store_url

    store = check_store(args.store or default_store_url())
    if not store.is_local:
        raise InputError(f"the store {store.shown_url} is not a folder: its links are S3's "
                         "own and need no page server")
    try:
        server = page_server(store, args.host, args.port)
    except OSError as exc:
        raise InputError(f"cannot serve pages on {args.host}:{args.port} ({exc.strerror}); "
                         "choose another --port or --host") from None
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    here = address(server)
    print(f"serving the pages of {store.shown_url} at {here}; set FACECAP_PAGES_URL={here} "
          "(as the Prefect UI's browser reaches it) where runs are started; Ctrl-C stops",
          flush=True)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        server.server_close()
    return 0
