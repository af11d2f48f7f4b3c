"""``reconstruct-capture``: one video in, a metric mesh in template topology out.

The flow runs the rows of the stage graph (:mod:`facecap.tasks.graph`) over the artifact store
(every stage cached by content: rerunning computes nothing, a changed setting recomputes
only the stages that read it and those after them), fans the depth maps out over threads
(the PatchMatch kernels release the GIL, so ``mvs.workers`` threads use that many cores of
a worker without a second process or API server), and exports the results to ``out``::

    index.html              the results as one page to look at in a browser (pages.capture)
    mesh.ply, mesh.obj      fitted mesh (mm, template topology, per-vertex colour);
    mesh.glb                the same as binary glTF (Blender, three.js, 3D viewers)
    cameras.json            metric cameras (mm) of the keyframes; colmap/ the pose stage's
                            COLMAP text model (its own units)
    cloud.ply               fused point cloud with normals and colours
    landmarks3d.json        68 3D landmarks (mm); ears3d.json the ear points
    report.json             per-stage seconds (computed or cached), figures, evaluation
    preview.png             three views of the mesh (the heat map with a scan)
    evaluation.json, heatmap_*.png   with a scan
"""

from __future__ import annotations

import json
import re
import shutil
import tempfile
import time
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Literal

import numpy as np
import prefect.artifacts
from prefect import flow, get_run_logger
from prefect.runtime import flow_run
from prefect.task_runners import ThreadPoolTaskRunner
from pydantic import BaseModel
from tqdm import tqdm

from facecap.flows.service import guard
from facecap.flows.ui import mesh_preview, publish_capture
from facecap.pages.capture import GLB_NAME, build_page, mesh_glb, page_parts, parts_complete
from facecap.pages.figures import run_summary
from facecap.pages.stored import keep_parts, store_page, stored_parts
from facecap.tasks.graph import (
    BY_NAME,
    EXPORTED,
    OUTPUT_NAMES,
    PHOTOS,
    STAGES,
    STEPS,
    UNTIL_ALIASES,
    VIDEO,
    Stage,
    capture_input_name,
    stages_until,
)
from facecap.tasks.outputs import ResultWriter, check_output_place
from facecap.tasks.runner import default_store_url, run_leases
from facecap.tasks.scratch import process_scratch
from facecap.tasks.stages import (
    all_stored,
    call_ingest,
    call_stage,
    call_stored_maps,
    first_finished,
    stage_result,
)
from facecap.tasks.store import open_store
from facecap_core import assets
from facecap_core.coarse import CoarseConfig
from facecap_core.config import build
from facecap_core.errors import InputError
from facecap_core.evaluation.stage import ACCURACY_NPY
from facecap_core.measure import under_scale
from facecap_core.photos import list_photos
from facecap_core.pipeline import PipelineConfig, load_pipeline_config
from facecap_core.settings import settings, time_limit
from facecap_core.video import probe, stored_frame_count

Step = Literal[STEPS + tuple(UNTIL_ALIASES)]
"""What ``until`` can stop after, in order: the stages of the graph (``mvs`` is fusion)."""
ConfigParameter = PipelineConfig | str | None
"""A run's pipeline settings: given as such (the UI's Run form shows every field with its
description, and the server refuses an out-of-range value before the run is created), or the
path of a YAML file of them, or nothing for the defaults."""
BACKSTOP_S = 60.0
"""Prefect's own limit on a capture run comes this long after FACECAP_CAPTURE_TIMEOUT_S,
which the stages keep themselves: it stops a run stuck outside any stage."""

MAX_WORKERS = 16
"""Threads of a capture run's task runner: the most depth maps ``mvs.workers`` can ask for
at once."""


def capture_name(video: str | Path) -> tuple[str, str]:
    """(subject, capture) of a video: the parent folder and the file stem."""
    p = Path(video)
    return p.parent.name or "capture", p.stem


def _run_name() -> str:
    subject, capture = capture_name(flow_run.parameters.get("video", "capture"))
    return f"{subject}/{capture}"


class _StoredFolders(Mapping):
    """Input folders fetched from the store only when read (a fan-out reads one of them)."""

    def __init__(self, store: str, inputs: dict[str, str]):
        self._store, self._inputs = open_store(store), inputs

    def __getitem__(self, name: str) -> Path:
        return self._store.get(self._inputs[name])

    def __iter__(self):
        return iter(self._inputs)

    def __len__(self) -> int:
        return len(self._inputs)


def _inputs(stage: Stage, keys: dict[str, str]) -> dict[str, str] | None:
    """The stage's input keys, or None when a required input is missing (no scan given)."""
    inputs = {}
    for name in stage.inputs + stage.optional:
        source = stage.source(name)
        fanned = source in BY_NAME and BY_NAME[source].per_keyframe
        items = {k: v for k, v in keys.items() if fanned and BY_NAME[source].is_row(k)}
        if source in keys:
            inputs[name] = keys[source]
        elif items:  # a per-keyframe stage: every keyframe's artifact
            inputs.update(items)
        elif name in stage.inputs:
            return None
    return inputs


class _RunProgress:
    """The capture run's progress artifact in the UI, one per run: advanced after every stage
    (its share of the work, a skipped stage's too) and after every depth map (the fan-out's
    share split among its maps), in whole percents, its description naming the capture and
    the last step."""

    EVERY_S = 1.0
    """The least time between two updates within a stage (each is a call to the API; a
    stage's end is always sent)."""

    def __init__(self, label: str, stages: list[str]):
        self.label, self.stages, self.done = label, len(stages), 0
        # Each stage's share: its seconds on an 8 s 720p capture on 2 cores (its row's
        # work_seconds), the depth maps and the poses most of a capture.
        self.weights = [BY_NAME[name].work_seconds if name in BY_NAME else 1.0
                        for name in stages]
        self.total = sum(self.weights) or 1.0
        self.id = prefect.artifacts.create_progress_artifact(0.0, description=f"{label}: started")
        self.sent = time.monotonic()

    def update(self, what: str, fraction: float = 0.0, every_s: float | None = None) -> None:
        """``what`` happened; ``fraction`` of the stage in progress is done. Not sent if
        the last update was less than ``every_s`` ago."""
        if every_s is not None and time.monotonic() - self.sent < every_s:
            return
        self.sent = time.monotonic()
        current = self.weights[self.done] if self.done < self.stages else 0.0
        work = sum(self.weights[: self.done]) + fraction * current
        percent = float(min(100, round(100.0 * work / self.total)))
        prefect.artifacts.update_progress_artifact(self.id, percent, description=f"{self.label}: {what}")

    def stage_done(self, name: str, outcome: str = "done") -> None:
        self.done += 1
        self.update(f"{name} {outcome} ({self.done} of {self.stages} stages)")


def _fan_out(stage: Stage, store: str, inputs: dict[str, str], config: BaseModel | None,
             label: str, workers: int, progress: bool, run_progress: _RunProgress,
             deadline: float | None = None) -> dict[str, tuple[str, bool]]:
    """One task per keyframe, at most ``workers`` at once; the run's progress artifact (and
    with ``progress`` a console bar) advanced after each. Maps all stored already: one task
    run for the stage."""

    indices = stage.per_keyframe(_StoredFolders(store, inputs))
    bar = tqdm(total=len(indices), desc=f"{stage.name} maps", unit="map",
               disable=not progress)
    if indices and all_stored(stage.name, store, inputs, config, indices):
        runs = call_stored_maps(stage.name, store, inputs, config, indices, label, deadline)
        bar.update(len(indices))
        bar.close()
        return {stage.row_name({"index": i}): tuple(run) for i, run in zip(indices, runs,
                                                                           strict=True)}
    pending, results, started = list(indices), {}, time.monotonic()
    running: list[tuple[int, object]] = []
    while pending or running:
        while pending and len(running) < workers:
            i = pending.pop(0)
            running.append((i, call_stage(stage.name, store, inputs, config, label,
                                          params={"index": i}, submit=True,
                                          deadline=deadline, started=started)))
        i, future = running.pop(first_finished([f for _, f in running], started, deadline))
        results[stage.row_name({"index": i})] = stage_result(stage.name, future, label,
                                                             started, deadline)
        bar.update()
        if len(results) < len(indices):  # the last one completes the stage
            run_progress.update(f"{stage.name} map {len(results)} of {len(indices)}",
                                len(results) / len(indices), every_s=run_progress.EVERY_S)
    bar.close()
    return {stage.row_name({"index": i}): results[stage.row_name({"index": i})]
            for i in indices}


def run_stages(store: str, keys: dict[str, str], cfg: PipelineConfig, label: str,
               stages: Iterable[Stage], progress: bool = False,
               deadline: float | None = None) -> dict[str, tuple[str, bool]]:
    """Run ``stages`` in graph order (inside a flow). ``keys`` holds the artifacts at hand
    (raw inputs by name, earlier stages) and receives the new ones; a stage whose required
    input is missing (the evaluation without a scan) is skipped. Returns ``{report row:
    (key, computed)}``. The run's progress artifact follows the stages and the depth maps.
    Every stage ends by the capture's ``deadline`` (``time.monotonic()``) too.

    A stage starts as soon as the stages it reads have finished, beside the one before it
    when it does not read that one (the frames are decoded while the landmarks are found);
    a fanned-out stage starts alone, its maps on every worker."""
    stages = list(stages)
    run_progress = _RunProgress(label, [stage.name for stage in stages])
    runs: dict[str, tuple[str, bool]] = {}
    running: dict[str, tuple[object, float]] = {}  # stage -> (its task's future, started)

    def finish(names: Iterable[str]) -> None:
        names = set(names)
        for name in [n for n in running if n in names]:
            future, started = running.pop(name)
            runs[name] = stage_result(name, future, label, started, deadline)
            keys[name] = runs[name][0]
            run_progress.stage_done(name)

    for stage in stages:
        finish([stage.source(i) for i in (*stage.inputs, *stage.optional)])
        if stage.per_keyframe:
            finish(list(running))
        inputs = _inputs(stage, keys)
        if inputs is None:
            run_progress.stage_done(stage.name, "skipped")
            continue
        config = stage.settings(cfg)
        if stage.per_keyframe:
            items = _fan_out(stage, store, inputs, config, label, cfg.mvs.workers, progress,
                             run_progress, deadline)
            keys.update({row: key for row, (key, _) in items.items()})
            runs.update(items)
            run_progress.stage_done(stage.name)
        else:
            running[stage.name] = (call_stage(stage.name, store, inputs, config, label,
                                              submit=True, deadline=deadline),
                                   time.monotonic())
    finish(list(running))
    # The report's rows in graph order, whatever order the stages finished in.
    return {row: runs[row] for stage in stages for row in runs if stage.is_row(row)}


def _export(store: str, keys: dict[str, str], writer: ResultWriter, scratch: Path
            ) -> dict[str, Path]:
    """Stage the user-facing files of the finished stages and a preview rendered from them
    (``writer`` commits them with the report, so that the folder shows this run alone:
    results an earlier run left there that this run did not make go; they stay in the
    store). Returns what was staged, name -> the file it came from."""
    st, staged = open_store(store), {}
    for stage, names in EXPORTED.items():
        if stage not in keys:
            continue
        folder = st.get(keys[stage])  # checked: a file changed after its commit is refused
        for name in names:
            if (folder / name).is_file():
                writer.add(name, source=folder / name)
                staged[name] = folder / name

    made = {"preview.png": mesh_preview(staged, scratch / "preview.png")}
    if "mesh.ply" in staged:
        made[GLB_NAME] = scratch / GLB_NAME
        made[GLB_NAME].write_bytes(mesh_glb(staged["mesh.ply"]))
    for name, path in made.items():
        if path is not None:
            writer.add(name, source=path)
            staged[name] = path
    return staged


def _page(store: str, keys: dict[str, str], report: dict, results: dict[str, Path]
          ) -> tuple[bytes, str | None]:
    """``index.html`` of the run (:mod:`facecap.pages.capture`), the heat map on the mesh from the
    evaluation's metric protocol, and the key of its parts in the store (None where they could
    not be kept there): parts a run of the same artifacts kept are taken as they are."""
    st, accuracy = open_store(store), None
    if "evaluation" in keys:
        path = st.get(keys["evaluation"]) / ACCURACY_NPY.format(protocol="metric")
        accuracy = np.load(path) if path.is_file() else None
    glb = results[GLB_NAME].read_bytes() if GLB_NAME in results else None
    parts_key, parts = stored_parts(st, report)
    if parts is None:
        frames = st.get(keys["frames"]) if "frames" in keys else None
        parts = page_parts(report, results, bool(glb), frames)
        parts_key = _kept_parts(st, report, parts, frames)
    return build_page(report, results, glb, accuracy, parts=parts), parts_key


def _kept_parts(st, report: dict, parts: dict, frames: Path | None) -> str | None:
    """The key under which the store keeps ``parts`` for a rerun of the same artifacts;
    None where they are incomplete (a rerun makes them again) or could not be kept."""
    if not parts_complete(report, parts, frames):
        return None
    try:
        return keep_parts(st, report, parts)
    except Exception as exc:  # noqa: BLE001 - a rerun makes them again; the run is made
        get_run_logger().warning("the page's parts were not kept in the store, so a rerun "
                                 "makes them again: %s", str(exc).splitlines()[0] if str(exc)
                                 else type(exc).__name__)
        return None


def _stage_report(store: str, runs: dict[str, tuple[str, bool]]) -> dict:
    """Per stage: its key, whether this run reused it (the task's own word) and the seconds
    its computation took (whichever run computed it)."""
    st, report = open_store(store), {}
    for name, (key, computed) in runs.items():
        meta = st.manifest(key).meta
        report[name] = {"key": key, "cached": not computed, "seconds": meta.get("seconds"),
                        "cpu_seconds": meta.get("cpu_seconds")}
    return report


@flow(name="reconstruct-capture", flow_run_name=_run_name, log_prints=True,
      task_runner=ThreadPoolTaskRunner(max_workers=MAX_WORKERS),
      timeout_seconds=time_limit("capture_timeout_s") + BACKSTOP_S)
def reconstruct_capture(video: str, out: str, config: ConfigParameter = None,
                        scan: str | None = None, scan_landmarks: str | None = None,
                        until: Step = "evaluation", store: str | None = None,
                        progress: bool = False, ipd_mm: float | None = None) -> dict:
    """Reconstruct one capture; returns the report (also written to ``out/report.json``).

    Args:
        video: The capture: a video file, or a folder of photos.
        out: The folder the mesh, cameras, cloud, report and preview are written to.
        config: The pipeline's settings (any subset; the rest keep their defaults), or the
            path of a YAML file of them.
        scan: A ground-truth scan in mm to score the mesh against.
        scan_landmarks: The scan's 68 3D landmarks (iBUG order, JSON), needed with a scan.
        until: The last stage to run.
        store: The artifact store (a folder or s3://bucket/prefix); default the
            deployment's, FACECAP_STORE.
        progress: Show progress bars on the console.
        ipd_mm: The subject's interpupillary distance (far PD, mm) if measured: a scale cue.
    """
    logger = get_run_logger()
    start = time.perf_counter()
    store = guard(out, store, video=video, config=config_file(config), scan=scan,
                  scan_landmarks=scan_landmarks)  # a served run: only what it may touch
    cfg = with_ipd(preflight(video, config, scan, scan_landmarks, out, store), ipd_mm)
    out_dir = Path(out)
    out_dir.mkdir(parents=True, exist_ok=True)
    inputs = (video, scan, scan_landmarks, config_file(config))
    subject, capture = capture_name(video)
    label = f"{subject}/{capture}"
    with run_leases():  # what the run reads stays in the store until it ends
        keys = {"video": call_ingest(store, video, capture_input_name(video), label)}
        for name, path in (("scan", scan), ("scan_landmarks", scan_landmarks)):
            if path:
                keys[name] = call_ingest(store, path, Path(path).name, label)
        # The capture's time limit, kept by the stages themselves: Prefect's own limit on the
        # flow (BACKSTOP_S later) is a signal in the main thread, which Prefect holds off while
        # it talks to its API and which can land in any code.
        deadline = time.monotonic() + settings().capture_timeout_s - (time.perf_counter() - start)
        runs = run_stages(store, keys, cfg, label, stages_until(until), progress, deadline)
        stages = _stage_report(store, runs)
        cached = sum(info["cached"] for info in stages.values())
        report = {
            "subject": subject, "capture": capture, "video": str(video), "store": store,
            "until": until, "wall_seconds": round(time.perf_counter() - start, 2),
            "computed": len(stages) - cached, "cached": cached, "stages": stages,
        }
        figures = _figures(store, runs)
        if figures:
            report["figures"] = figures
        scratch = Path(tempfile.mkdtemp(prefix="export-", dir=process_scratch()))
        try:
            with ResultWriter(out_dir, inputs) as writer:
                results = _export(store, keys, writer, scratch)

                page, parts = _page(store, keys, report, results)
                try:
                    report["page"] = {"key": store_page(open_store(store), report, page),
                                      **({"parts": parts} if parts else {})}
                except Exception as exc:  # noqa: BLE001 - the results are made; the UI's link is not worth losing them for
                    logger.warning(f"{label}: the page was not kept in the store, so the UI's "
                                   f"link opens it only from disk: {exc}")
                writer.add("report.json", json.dumps(report, indent=1).encode())
                writer.add("index.html", page)
                writer.commit(stale=OUTPUT_NAMES)
            _publish(report, out_dir, label, results)
        finally:
            shutil.rmtree(scratch, ignore_errors=True)

    logger.info(f"{label}: {run_summary(report)}; results in {out_dir}")
    return report


def _figures(store: str, runs: dict[str, tuple[str, bool]]) -> dict:
    """Headline figures of the run's artifacts, in graph order (what the UI table and the
    report show); each stage module reads its own files."""
    st, fig = open_store(store), {}
    for stage in STAGES:
        if stage.figures and stage.name in runs:
            fig.update(stage.figures(st.get(runs[stage.name][0])))
    if fig.get("measurements"):  # the anatomical distances, under the metric scale's 1σ
        fig["measurements"] = under_scale(fig["measurements"],
                                          (fig.get("scale") or {}).get("sigma_pct"))
    return fig


def _publish(report: dict, out: Path, label: str, results: dict[str, Path]) -> None:
    """UI artifacts (stage table, preview images) and a completion event."""

    publish_capture(report, out, label, results)


MIN_VIDEO_SIDE_PX = 120
"""Shortest video side accepted: below it a face is too few pixels to find landmarks on."""


def preflight(video: str | Path, config: ConfigParameter | Path = None, scan: str | None = None,
              scan_landmarks: str | None = None, out: str | Path | None = None,
              store: str | None = None) -> PipelineConfig:
    """Checks that need no stage: the files exist, the video decodes, is long and large
    enough and within the input limits (``FACECAP_MAX_*``, :mod:`facecap_core.settings`), the
    config is valid, the output folder is writable. Run before anything is started so bad
    input fails in a second with one line."""

    limits = settings()  # the environment's limits, never the run's config
    photos = Path(video).is_dir()
    if not photos and not Path(video).is_file():
        raise InputError(f"capture not found: {video}; give a video file or a folder of photos")
    check_file_size(video, limits.max_file_mb)
    info = probe(video)  # a photo folder: too few photos or mixed sizes fail here
    if info.duration_s > limits.max_duration_s:
        raise InputError(f"{video} lasts {info.duration_s:.0f} s, longer than the limit of "
                         f"{limits.max_duration_s:g} s; cut it to the sweep around the head")
    if info.frame_count > limits.max_frames:  # the header's count: before reading them all
        raise InputError(f"{video} has {info.frame_count} frames, more than the limit of "
                         f"{limits.max_frames}; cut it to the sweep around the head")
    size = f"{info.width}x{info.height}"
    if max(info.width, info.height) > limits.max_side_px:  # the header's size, too
        raise InputError(f"{video} is {size} pixels, larger than the limit of "
                         f"{limits.max_side_px} on the long side; record at 8K or less (4K is "
                         "plenty)")
    stored = stored_frame_count(video)
    if stored > limits.max_frames:
        raise InputError(f"{video} has {stored} frames, more than the limit of "
                         f"{limits.max_frames}; cut it to the sweep around the head")
    if not photos and stored <= 1:
        raise InputError(f"{video} is a single image ({info.codec}), not a video; give the "
                         "capture's video file, or a folder of photos")
    if not photos and info.frame_count and stored < info.frame_count:
        raise InputError(f"{video} is truncated: it holds {stored} of its {info.frame_count} "
                         "frames; copy the whole file again")
    cfg = load_pipeline_config(config)
    if min(info.width, info.height) < MIN_VIDEO_SIDE_PX:
        raise InputError(f"{video} is {size} pixels, too small to find a face in; record at "
                         f"least {MIN_VIDEO_SIDE_PX} pixels on the short side (720p or more)")
    if not photos and stored < cfg.keyframes.min_frames:
        raise InputError(f"{video} has {stored} frames; an ear-to-ear capture needs "
                         f"at least {cfg.keyframes.min_frames} (record a slow sweep of several "
                         "seconds)")
    for what, path in (("scan", scan), ("scan landmarks", scan_landmarks)):
        if path and not Path(path).is_file():
            raise InputError(f"{what} not found: {path}")
    if scan and not scan_landmarks:
        raise InputError(f"scan {scan} needs its 68 3D landmarks (--scan-landmarks) to cut the "
                         "face region it is scored on")

    assets.default_template_files()  # fetched once; a damaged copy fails here, not at fitting
    if out is not None:
        check_output_place(out, store or default_store_url(),
                           (video, scan, scan_landmarks, config_file(config)))
        check_output_folder(Path(out))
        results = {(Path(out) / n).resolve() for n in OUTPUT_NAMES}
        for what, path in (("capture", video), ("scan", scan), ("scan landmarks", scan_landmarks),
                           ("config", config_file(config))):
            if path and Path(path).resolve() in results:
                raise InputError(f"the {what} {path} would be overwritten by a result of the same "
                                 f"name in the output folder {out}; give another --out")
    return cfg


def config_file(config: ConfigParameter) -> str | None:
    """The file a run reads its settings from, if it names one (a path is an input a served
    run may only take from inside its input roots)."""
    return config if isinstance(config, str) else None


def check_file_size(capture: str | Path, max_mb: float) -> None:
    """A video file, or a photo folder's photos together, at most ``max_mb`` MiB: checked
    before anything opens them."""
    path = Path(capture)
    if path.is_dir():
        size = sum(p.stat().st_size for p in list_photos(path))
    else:
        size = path.stat().st_size
    if size > max_mb * 2**20:
        raise InputError(f"{capture} is {size / 2**20:.1f} MiB, more than the limit of "
                         f"{max_mb:g} MiB; cut it to the sweep around the head")


def with_ipd(cfg: PipelineConfig, ipd_mm: float | None) -> PipelineConfig:
    """The config with the subject's interpupillary distance as a scale cue (validated like
    the config file's ``coarse.ipd_mm``)."""
    if ipd_mm is None:
        return cfg

    coarse = build(CoarseConfig, {**cfg.coarse.model_dump(), "ipd_mm": ipd_mm},
                   source="--ipd-mm")
    return cfg.model_copy(update={"coarse": coarse})


def as_user_sees_it(message: str, video: str | Path) -> str:
    """A stage's message with the store's copy of the capture named as the user gave it
    (stages read the capture from the artifact store, so they name the stored copy): the
    stored video file, or the stored photo folder, whose photos keep their names
    (``.../input-<key>/photos/IMG_2.jpg`` is ``<the user's folder>/IMG_2.jpg``)."""


    # Not a stored scan whose name begins like them (photos.ply).
    stored = re.compile(rf"\S*/input-[0-9a-f]{{32}}/(?:{re.escape(VIDEO)}|{re.escape(PHOTOS)})"
                        r"(?![\w.-])")
    return " ".join(stored.sub(lambda _: str(video), message).split())


def check_output_folder(folder: Path) -> None:
    """Create the output folder if needed and write a scratch file into it."""

    if folder.exists() and not folder.is_dir():
        raise InputError(f"the output folder {folder} is a file; give the path of a folder "
                         "(--out)")
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        reason = exc.strerror or type(exc).__name__
        raise InputError(f"cannot write to the output folder {folder} ({reason}); choose a "
                         "writable folder with free space (--out)") from None
