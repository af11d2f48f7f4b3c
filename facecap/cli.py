"""The ``facecap`` command line.

Bad input ends with one line ``facecap: error: ...`` on stderr and exit code 2; anything else
that escapes is a bug and keeps its traceback.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import time
import traceback
from pathlib import Path

from facecap import console, tools
from facecap.flows import local_server
from facecap_core.errors import FacecapError, InputError

# Imported where used: Prefect, once the arguments are parsed (main imports flows.service),
# so that `facecap --help` and a bad argument answer without it; every other import says why.


def _print_report(report: dict, out: Path, baseline_rows: tuple = ()) -> None:
    """The stage table, the accuracy table (after ``baseline_rows``) and, last, where the
    mesh, the report and the preview are."""
    # Could be at the top: the run before this has loaded all three.
    from facecap.pages.figures import run_summary
    from facecap.tasks.graph import is_keyframe_row
    from facecap_core.evaluation import paper_table

    print(f"{report['subject']}/{report['capture']}: {run_summary(report)}")
    for name, info in report["stages"].items():
        if not is_keyframe_row(name):
            state = "reused" if info["cached"] else "computed"
            print(f"  {name:<10} {state:<8} {info['seconds'] or 0:8.1f} s")
    depth = [i for n, i in report["stages"].items() if is_keyframe_row(n)]
    if depth:
        print(f"  {'depth':<10} {sum(not i['cached'] for i in depth)} of {len(depth)} maps "
              f"computed, {sum(i['seconds'] or 0 for i in depth):.1f} s in all")
    scale = report.get("figures", {}).get("scale")
    if scale and scale.get("sigma_pct") is not None:
        dropped = "".join(f"; {d['name']} dropped: {d['reason']}"
                          + (f" ({d['disagreement_sigmas']} sigma off)"
                             if "disagreement_sigmas" in d else "") for d in scale["dropped"])
        print(f"  scale      {scale['metric_scale']:.4g} mm per camera unit, "
              f"±{scale['sigma_pct']:.1f} % (1 sigma) from {' + '.join(scale['used'])}{dropped}")
    ears = report.get("figures", {}).get("ears")
    if ears:
        # Could be at the top: the run has loaded the coarse stage.
        from facecap_core.coarse import ears_summary

        print(f"  ears       {ears_summary(ears)}")
    evaluation = report.get("figures", {}).get("evaluation")
    if evaluation:
        rows = list(baseline_rows) + [(f"facecap ({p})", [s]) for p, s in evaluation.items()]
        print(f"Face region\n\n{paper_table(rows)}\n\nEar region\n\n"
              f"{paper_table(rows, region='ears')}")
    for name, what in (("mesh.ply", "mesh"), ("report.json", "report"),
                       ("preview.png", "preview"), ("index.html", "page")):
        if (out / name).is_file():
            print(f"{what}: {out / name}")


def _check_store(args) -> None:
    """The store opens and answers before any flow starts (a bad URL, a file where its
    folder should be, missing credentials, a server that is down)."""
    # Could be at the top: main has loaded the runner (through flows.service).
    from facecap.tasks.runner import check_store, default_store_url

    check_store(args.store or default_store_url())


def _cmd_reconstruct(args) -> int:
    # Prefect's flow engine (a second or so): only for the commands that run a flow.
    from facecap.flows.capture import preflight, with_ipd

    # The config is read and validated here, once; the flow and its stages get the model.
    config = with_ipd(preflight(args.video, args.config, args.scan, args.scan_landmarks,
                                args.out, args.store), args.ipd_mm)
    _check_store(args)
    console.prefect_env()
    # Loaded above already (preflight): named again where the flow runs.
    from facecap.flows.capture import reconstruct_capture

    report = reconstruct_capture(args.video, args.out, config=config, scan=args.scan,
                                 scan_landmarks=args.scan_landmarks, until=args.until,
                                 store=args.store, progress=True)
    _print_report(report, Path(args.out))
    return 0


def _cmd_dataset(args) -> int:
    # The flows add Prefect's flow engine (a second or so); the other three are light.
    from facecap.flows.capture import check_output_folder
    from facecap.flows.dataset import check_dataset_output
    from facecap.tasks.outputs import check_output_place
    from facecap.tasks.runner import default_store_url
    from facecap_core.dataset import scan_dataset

    check_dataset_output(scan_dataset(args.root), Path(args.out))  # before any flow starts
    check_output_place(args.out, args.store or default_store_url(), (args.root,))
    check_output_folder(Path(args.out))
    _check_store(args)
    console.prefect_env()
    # Loaded above already: named again where the flow runs.
    from facecap.flows.dataset import reconstruct_dataset, summary_line

    summary = reconstruct_dataset(args.root, args.out, config=args.config, store=args.store,
                                  until=args.until)
    print(summary_line(summary, args.out))
    for row in summary["consistency"]:
        print(f"  {row['subject']}: {row['capture_a']} vs {row['capture_b']}: median "
              f"{row['median_mm']} mm, p95 {row['p95_mm']} mm")
    return 0


def _cmd_evaluate_dataset(args) -> int:
    # The flow's module adds Prefect's flow engine (a second or so).
    from facecap.flows.evaluate import preflight
    from facecap.tasks.runner import default_store_url

    preflight(args.root, args.out, args.store or default_store_url())  # before the server
    _check_store(args)
    console.prefect_env()
    # Loaded above already: named again where the flow runs.
    from facecap.flows.evaluate import _table, evaluate_dataset, scale_error_pct

    result = evaluate_dataset(args.root, args.out, store=args.store)
    if result["captures"]:
        print(_table(result["captures"]))
        print("scale error (the mesh's size against the scan's): " + ", ".join(
            f"{name} {scale_error_pct(s):+.2f} %" for name, s in sorted(result["captures"].items())))
    print(f"scored {len(result['captures'])}, skipped {len(result['skipped'])} (no scan, scan "
          "landmarks or mesh)")
    for f in result["regressions"]:
        print(f"REGRESSION {f['capture']}: {f['measure']} {f['previous_mm']} -> {f['now_mm']} mm")
    return 1 if result["regressions"] else 0


def _cmd_serve(args) -> int:
    # Loaded already: main imports flows.service (Prefect) once the arguments are parsed.
    from facecap.flows.service import INPUT_ROOTS_ENV, OUTPUT_ROOT_ENV
    from facecap_core.settings import settings

    # Served runs (processes of their own) read only under ROOT and write only under OUT
    # unless the environment sets other folders (an empty variable counts as unset, as everywhere).
    configured = settings()
    if not configured.input_roots:
        os.environ[INPUT_ROOTS_ENV] = str(Path(args.root).resolve())
    if configured.output_root is None:
        os.environ[OUTPUT_ROOT_ENV] = str(Path(args.out).resolve())
    console.prefect_env("INFO", heartbeats=True)  # a server's console is its log
    _serve_pages(args.pages_host, args.pages_port)
    from facecap.deploy.serve import serve  # Every flow, Prefect's serve: only for `serve`

    print(f"serving reconstruct-dataset, reconstruct-capture and nightly-evaluation "
          f"({args.cron}, {args.timezone}); Ctrl-C stops")
    serve(args.root, args.out, args.cron, args.timezone, args.limit)
    return 0


def _serve_pages(host: str, port: int) -> None:
    """Serve a local store's pages beside the deployments, and have the served runs link to
    them (unless FACECAP_PAGES_URL names a server already)."""

    # Could be at the top: light, or loaded already (the runner, the settings).
    from facecap.pages.server import address, page_server, serve_in_background
    from facecap.tasks.runner import check_store, default_store_url
    from facecap_core.settings import env_name, settings

    store = check_store(default_store_url())
    if port == 0 or not store.is_local:
        return
    try:
        server = page_server(store, host, port)
    except OSError as exc:
        raise InputError(f"cannot serve the results pages on {host}:{port} ({exc.strerror}); "
                         "choose another --pages-port, or 0 for none") from None
    serve_in_background(server)
    if settings().pages_url is None:
        os.environ[env_name("pages_url")] = address(server)
    print(f"results pages at {settings().pages_url}")


def _cmd_alerts(args) -> int:
    from facecap.deploy.alerts import set_up_alerts  # Prefect's automations: only `alerts`

    for line in set_up_alerts(webhook=args.webhook, block=args.block):
        print(line)
    return 0


def _cmd_demo(args) -> int:
    # The synthetic world only for `demo`; the other four the pipeline has loaded.
    from facecap.synthetic import synthesize
    from facecap.synthetic.config import SynthConfig
    from facecap_core.baselines import mean_template
    from facecap_core.evaluation import score_json
    from facecap_core.settings import settings
    from facecap_core.template import Template

    ict_model = args.ict_model or settings().ict_model
    subject = "ict:3" if ict_model else "james"
    config = SynthConfig(subject=subject, ict_model=ict_model, width=args.width,
                         height=args.height, fps=args.fps, duration_s=args.seconds)
    out = Path(args.out)
    capture_dir = out / "capture"
    if not (capture_dir / "gt" / "render.json").is_file():
        print(f"synthesizing a {config.duration_s:g} s {config.width}x{config.height} capture "
              f"of {subject} into {capture_dir}")
        capture = synthesize(config, capture_dir)
        print(f"rendered {capture.frames} frames in {capture.seconds:.1f} s")
    gt = capture_dir / "gt"
    scores = mean_template(Template.default(), gt / "mesh.ply", gt / "landmarks.json")
    rows = [(f"Mean template ({p})", [score_json(s)]) for p, s in scores.items()]
    console.prefect_env()
    # Prefect's flow engine (a second or so): only `demo` and `reconstruct` run a flow.
    from facecap.flows.capture import reconstruct_capture

    report = reconstruct_capture(str(capture_dir / "video.mp4"), str(out / "result"),
                                 config=args.config, scan=str(gt / "mesh.ply"),
                                 scan_landmarks=str(gt / "landmarks.json"), progress=True)
    _print_report(report, out / "result", tuple(rows))
    return 0


class UsageError(FacecapError):
    """A command line that does not parse: argparse's message and the help to read."""


class _Parser(argparse.ArgumentParser):
    """argparse's parser, for ``facecap`` and (``add_subparsers`` makes its own class)
    every subcommand: an error is facecap's one line, argparse's message and the help of the
    command it is about, without the usage lines; ``--help`` is argparse's own."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        # The innermost subcommand's default wins in the namespace: which help to name.
        self.set_defaults(help_command=self.prog)

    def parse_args(self, args=None, namespace=None):
        parsed, extras = self.parse_known_args(args, namespace)
        if extras:  # a subcommand's unknown options are only found out here, at the top
            raise _usage_error(f"unrecognized arguments: {' '.join(extras)}",
                               parsed.help_command)
        return parsed

    def error(self, message: str):
        raise _usage_error(message, self.prog)


def _usage_error(message: str, command: str) -> UsageError:
    return UsageError(f"{' '.join(message.split())}; see '{command} --help'")


def _port(text: str) -> int:
    """A TCP port number, 0 to 65535, as argparse's type of a port option."""
    try:
        port = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a port number; give a whole "
                                         "number from 0 to 65535") from None
    if not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"{port} is not a port number; give a whole number "
                                         "from 0 to 65535")
    return port


def build_parser() -> argparse.ArgumentParser:
    # Long on purpose: a declaration, every command and option in the order --help shows them.
    # The pipeline (open3d, OpenCV: seconds) on every command, --help too; not on import.
    from facecap.tasks.graph import STEPS, UNTIL_ALIASES

    until = [*STEPS, *UNTIL_ALIASES]

    p = _Parser(
        prog="facecap",
        description="Metric 3D face meshes from one handheld phone video, and the tools to "
                    "measure them.")
    verbose = "show third-party logs (COLMAP, Prefect) and facecap's debug log"
    p.add_argument("--verbose", action="store_true", help=verbose)
    sub = p.add_subparsers(dest="command", required=True)

    a = sub.add_parser("assets", help="fetch, verify and list the template and sample scan")
    a.set_defaults(func=tools.assets)

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
    s.set_defaults(func=tools.synth)

    e = sub.add_parser("evaluate", help="score a mesh against a scan (accuracy/completion, mm, "
                                        "in the face and the ear region)")
    e.add_argument("mesh", help="reconstructed mesh (PLY/OBJ, mm)")
    e.add_argument("--scan", required=True, help="ground-truth scan mesh (mm)")
    e.add_argument("--scan-landmarks", help="68 3D landmarks of the scan (define the regions)")
    e.add_argument("--mesh-landmarks", help="68 3D landmarks of the mesh (initial alignment)")
    e.add_argument("--protocol", choices=["similarity", "metric", "both"], default="both")
    e.add_argument("--json", action="store_true", help="print one JSON object")
    e.add_argument("--heatmap", help="write accuracy heat maps to this PNG path")
    e.set_defaults(func=tools.evaluate)

    r = sub.add_parser("reconstruct", help="reconstruct one capture: video or photos in, "
                                           "metric mesh out")
    r.add_argument("video", metavar="CAPTURE",
                   help="the capture: a handheld ear-to-ear video of a still face, or a "
                        "folder of photos of it (JPEG/PNG/HEIC, one camera, any order)")
    r.add_argument("--out", required=True, help="output folder")
    r.add_argument("--config", help="PipelineConfig YAML (any subset of the stages' settings)")
    r.add_argument("--until", choices=until, default="evaluation",
                   help="last stage to run")
    r.add_argument("--ipd-mm", type=float, help="the subject's interpupillary distance in mm "
                                                 "as an optician measures it (far PD): a scale "
                                                 "cue of about 1 %% instead of 4 %%")
    r.add_argument("--scan", help="ground-truth scan (mm) to score the mesh against")
    r.add_argument("--scan-landmarks", help="68 3D landmarks of the scan")
    r.add_argument("--store", help="artifact store: folder or s3://bucket/prefix "
                                   "(default $FACECAP_STORE, else $FACECAP_HOME/store)")
    r.set_defaults(func=_cmd_reconstruct)

    ds = sub.add_parser("dataset", help="reconstruct every capture of ROOT/<subject>/<capture>.mp4 "
                                        "(or ROOT/<subject>/<capture>/ of photos)")
    ds.add_argument("root", help="dataset folder")
    ds.add_argument("--out", required=True, help="results go to OUT/<subject>/<capture>/")
    ds.add_argument("--config", help="PipelineConfig YAML")
    ds.add_argument("--store", help="artifact store (see reconstruct)")
    ds.add_argument("--until", choices=until, default="evaluation",
                    help="last stage to run for every capture")
    ds.set_defaults(func=_cmd_dataset)

    ed = sub.add_parser("evaluate-dataset", help="score a dataset's reconstructions against its "
                                                 "scans and flag regressions")
    ed.add_argument("root", help="dataset folder (with ROOT/<subject>/scan.ply)")
    ed.add_argument("--out", required=True, help="the folder `facecap dataset` wrote")
    ed.add_argument("--store", help="artifact store (see reconstruct)")
    ed.set_defaults(func=_cmd_evaluate_dataset)

    sv = sub.add_parser("serve", help="serve the dataset, capture and nightly-evaluation "
                                      "deployments")
    sv.add_argument("--root", required=True, help="dataset folder of the nightly evaluation; "
                    "served runs read inputs only under it (unless FACECAP_INPUT_ROOTS is set)")
    sv.add_argument("--out", required=True, help="results folder of the nightly evaluation; "
                    "served runs write only under it (unless FACECAP_OUTPUT_ROOT is set)")
    sv.add_argument("--cron", default="0 2 * * *", help="nightly schedule (cron)")
    sv.add_argument("--timezone", default="UTC", help="time zone of the schedule (IANA name)")
    sv.add_argument("--limit", type=int, default=1, help="flow runs at once")
    sv.add_argument("--pages-host", default="127.0.0.1",
                    help="address the results pages of a local store are served on (default "
                         "127.0.0.1: this machine only)")
    sv.add_argument("--pages-port", type=_port, default=4280,
                    help="port of the results pages (default 4280; 0: serve none)")
    sv.set_defaults(func=_cmd_serve)

    al = sub.add_parser("alerts", help="notify a webhook when the nightly evaluation regresses "
                                       "or a facecap run fails (on the server in PREFECT_API_URL)")
    where = al.add_mutually_exclusive_group()
    where.add_argument("--webhook", help="URL the alerts are POSTed to as JSON {\"text\": ...} "
                                         "(Slack, Mattermost, any HTTP endpoint; default "
                                         "$FACECAP_ALERT_WEBHOOK)")
    where.add_argument("--block", metavar="TYPE/NAME",
                       help="send through this notification block made in the Prefect UI "
                            "instead (e.g. ms-teams-webhook/ops)")
    al.set_defaults(func=_cmd_alerts)

    fg = sub.add_parser("forget", help="remove everything derived from one subject's captures: "
                                       "the store's artifacts, the results folder and the "
                                       "subject's evaluation history")
    fg.add_argument("subject", help="the subject's folder name in the dataset")
    fg.add_argument("--root", help="dataset folder (its ROOT/<subject>/ captures and scan)")
    fg.add_argument("--out", help="results folder (OUT/<subject>/ and OUT/evaluations/)")
    fg.add_argument("--store", help="artifact store (see reconstruct)")
    fg.add_argument("--dry-run", action="store_true", help="list, remove nothing")
    fg.set_defaults(func=tools.forget)

    pg = sub.add_parser("pages", help="serve a local store's results pages over HTTP, for "
                                      "the links in the Prefect UI")
    pg.add_argument("--host", default="127.0.0.1",
                    help="address to listen on (default 127.0.0.1: this machine only)")
    pg.add_argument("--port", type=_port, default=4280,
                    help="port (default 4280; 0: one the system picks)")
    pg.add_argument("--store", help="artifact store (see reconstruct)")
    pg.set_defaults(func=tools.pages)

    st = sub.add_parser("store", help="look after the artifact store")
    st_sub = st.add_subparsers(dest="store_command", required=True)
    pr = st_sub.add_parser("prune", help="remove artifacts older than a number of days and "
                                         "every artifact made from them, or those no result "
                                         "names (--unreferenced)")
    pr.add_argument("--older-than-days", type=float,
                    help="age (days since the artifact was committed); with --unreferenced, "
                         "the age below which an unreferenced artifact is kept (default 1: "
                         "a run in progress writes its report when it ends)")
    pr.add_argument("--unreferenced", action="store_true",
                    help="remove the artifacts that no run report under the --out folders "
                         "names, nor made anything a report names")
    pr.add_argument("--out", action="append",
                    help="results folder whose reports keep their artifacts (repeatable)")
    pr.add_argument("--store", help="artifact store (see reconstruct)")
    pr.add_argument("--dry-run", action="store_true", help="list, remove nothing")
    pr.set_defaults(func=tools.store_prune)

    te = sub.add_parser("train-ears", help="render the ear training set and train the ear "
                                           "detector and predictor")
    te.add_argument("--out", required=True, help="folder for the model files")
    te.set_defaults(func=tools.train_ears)

    d = sub.add_parser("demo", help="synthesize a capture, reconstruct it, print its accuracy")
    d.add_argument("--out", default="out/demo", help="output folder (capture/ and result/)")
    d.add_argument("--ict-model", help="ICT Face Model .npz: the subject is then ICT identity 3 "
                                       "(default: $FACECAP_ICT_MODEL, else the james head scan)")
    d.add_argument("--config", help="PipelineConfig YAML")
    d.add_argument("--width", type=int, default=640, help="video width (pixels)")
    d.add_argument("--height", type=int, default=360, help="video height (pixels)")
    d.add_argument("--fps", type=float, default=30.0, help="video frame rate")
    d.add_argument("--seconds", type=float, default=6.0, help="sweep duration")
    d.set_defaults(func=_cmd_demo)
    # --verbose after the command too: facecap reconstruct ... --verbose
    for runs_flows in (sub.choices[name] for name in FLOW_COMMANDS):
        runs_flows.add_argument("--verbose", action="store_true", default=argparse.SUPPRESS,
                                help=verbose)
    return p


def _as_user_sees_it(exc: FacecapError, args) -> str:
    """One line, naming the user's video where a stage named the store's copy of it."""
    # Prefect's flow engine (a second or so), only when an error is shown.
    from facecap.flows.capture import as_user_sees_it

    return as_user_sees_it(str(exc), getattr(args, "video", None) or "the video")


FLOW_COMMANDS = ("reconstruct", "dataset", "evaluate-dataset", "serve", "demo")
"""The commands that run flows, on a Prefect server of their own unless one is named."""
PREFECT_COMMANDS = (*FLOW_COMMANDS, "forget", "alerts")
"""The commands that use Prefect (``forget``: the UI's pages), whose PREFECT_HOME must be a
folder."""


class Terminated(BaseException):
    """SIGTERM, raised in the main thread as Ctrl-C raises KeyboardInterrupt (a
    BaseException, so that no ``except Exception`` on the way takes it for an error)."""


def _terminated(signum, frame) -> None:
    raise Terminated()


def _catch_sigterm() -> None:
    """SIGTERM ends a run as Ctrl-C does: one line, exit 143. pycolmap's import puts glog's
    failure handler on SIGTERM (a native stack trace, at the C level, where Python does not
    see it): imported first, in this thread, its handler is then replaced by this one."""
    import pycolmap  # noqa: F401  # Imported where used: 0.2 s, for the commands that run flows

    signal.signal(signal.SIGTERM, _terminated)


def _runs_flows(argv: list[str]) -> bool:
    """Whether ``argv`` asks for a command that runs flows (and not for its help)."""
    words = [word for word in argv if not word.startswith("-")]
    return bool(words) and words[0] in FLOW_COMMANDS and not {"-h", "--help"} & set(argv)


def main(argv: list[str] | None = None) -> int:
    console.prefect_defaults()
    # The command's own process: its server starts while it loads the pipeline and Prefect.
    if argv is None and _runs_flows(sys.argv[1:]) and console.prefect_home_problem() is None:
        local_server.spawn_local_server(quiet="--verbose" not in sys.argv)
    try:
        args = build_parser().parse_args(argv)
    except UsageError as exc:
        print(f"facecap: error: {exc}", file=sys.stderr)
        return 2
    console.VERBOSE = args.verbose
    # Before Prefect is imported (flows.service imports it): it would warn, then fail.
    problem = console.prefect_home_problem() if args.command in PREFECT_COMMANDS else None
    if problem:
        print(f"facecap: error: {problem}", file=sys.stderr)
        return 2
    # After the home check: Prefect (flows.service imports it) warns, then fails, on a bad home.
    from facecap.flows.service import LOCAL_COMMAND

    local = LOCAL_COMMAND.set(True)  # one's own machine: any path, any store
    try:
        if args.command in FLOW_COMMANDS and argv is None:  # the command's own process
            _catch_sigterm()
        return args.func(args)
    except FacecapError as exc:
        print(f"facecap: error: {_as_user_sees_it(exc, args)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("facecap: interrupted", file=sys.stderr)
        return 130
    except Terminated:
        print("facecap: terminated", file=sys.stderr)
        return 128 + signal.SIGTERM
    except _time_limits():  # Prefect's own limit on a flow (a stage says which it hit)
        variable = ("FACECAP_EVALUATION_TIMEOUT_S" if args.func is _cmd_evaluate_dataset
                    else "FACECAP_CAPTURE_TIMEOUT_S")
        print(f"facecap: error: the run was stopped at its time limit ({variable}); raise "
              "the limit, or look for what held it up in the run's log", file=sys.stderr)
        return 2
    except _network_errors() as exc:  # the store went away mid-run, after the task's retries
        # Could be at the top: flows.service has loaded the runner.
        from facecap.tasks.runner import default_store_url, store_unreachable

        store = getattr(args, "store", None) or default_store_url()
        print(f"facecap: error: {store_unreachable(store, exc)}", file=sys.stderr)
        return 2
    except Exception as exc:  # noqa: BLE001 - anything else is a bug: say so, keep the trace
        # What failed may be the disk or the user's names, not facecap.
        full = console.full_disk_error(exc) or console.name_too_long_error(exc)
        print(f"facecap: error: {full}" if full else _internal_error(exc, argv),
              file=sys.stderr)
        return 2 if full else 1
    finally:
        LOCAL_COMMAND.reset(local)


def _time_limits() -> tuple[type[BaseException], ...]:
    from prefect.flow_engine import FlowRunTimeoutError  # Looked up only once a command has raised

    return (FlowRunTimeoutError,)


def _network_errors() -> tuple[type[BaseException], ...]:
    from facecap.tasks.runner import network_errors  # Could be at the top: flows.service loaded it

    return (ConnectionError, TimeoutError, *network_errors())


def _internal_error(exc: BaseException, argv: list[str] | None) -> str:
    """The one line of a bug: what was raised, and the log file that holds its traceback,
    or why there is none."""
    line = (f"facecap: internal error (a bug in facecap, not a problem with your input): "
            f"{type(exc).__name__}: {' '.join(str(exc).split())[:200]}")
    try:
        log = _write_crash_log(exc, argv)
    except Exception as failure:  # noqa: BLE001 - a full disk must not bury the bug's line
        return (f"{line}; the traceback could not be saved ({_why(failure)}); please report "
                "this line")
    return f"{line}; the traceback is in {log}; please report it with that file"


def _why(failure: BaseException) -> str:
    """Why a file could not be written, in a few words."""

    if isinstance(failure, OSError) and failure.errno:
        text = failure.strerror or os.strerror(failure.errno)
        return f"{text}: {failure.filename}" if failure.filename else text
    if isinstance(failure, FacecapError):  # a planted link, in its own line's words
        return str(failure)
    return f"{type(failure).__name__}: {' '.join(str(failure).split())[:120]}"


def _write_crash_log(exc: BaseException, argv: list[str] | None) -> Path:
    """The traceback of an unexpected exception, in ``$FACECAP_HOME/logs``; raises what
    kept it from being written (no partial log is left)."""

    # Could be at the top: main has loaded all four before any crash is logged.
    from facecap.tasks.own_files import write_new
    from facecap.tasks.runner import facecap_home
    from facecap_core.errors import FacecapError
    from facecap_core.settings import default_home

    try:
        home = facecap_home()
    except FacecapError:  # a bad FACECAP_* value must not hide the bug being logged
        home = default_home()
    text = (f"facecap {' '.join(sys.argv[1:] if argv is None else argv)}\n\n"
            + "".join(traceback.format_exception(exc)))
    # Never through a link planted as logs; a cut log is removed (it would pass for the trace).
    return Path(write_new(home / "logs", f"crash-{time.strftime('%Y%m%d-%H%M%S')}-"
                                         f"{os.getpid()}.log", text.encode()))


if __name__ == "__main__":
    sys.exit(main())
