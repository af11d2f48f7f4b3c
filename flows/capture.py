"""``reconstruct-capture``: one video in, a metric mesh in template topology out.

The flow chains the stage tasks over the artifact store (every stage cached by content:
rerunning computes nothing, a changed parameter recomputes only the stages after it), fans
the depth maps out over a thread pool (the PatchMatch kernels release the GIL, so two
threads use both cores of a worker without a second process or API server), and exports
the results to ``out``::

    mesh.ply, mesh.obj      fitted mesh (mm, template topology, per-vertex colour)
    cameras.json            metric cameras (mm) of the keyframes; colmap/ the pose stage's
                            COLMAP text model (its own units)
    cloud.ply               fused point cloud with normals and colours
    landmarks3d.json        68 3D landmarks (mm); ears3d.json the ear points
    report.json             per-stage seconds (computed or cached), figures, evaluation
    evaluation.json, heatmap_*.png   with a scan
"""

from __future__ import annotations

import json
import shutil
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Literal

from prefect import flow, get_run_logger
from prefect.task_runners import ThreadPoolTaskRunner

from facecap_core.config import PipelineConfig, load_pipeline_config
from facecap_core.errors import InputError
from facecap_core.mvs.stage import (
    DEPTH_FIELDS, FUSION_FIELDS, VIEW_FIELDS, config_part, read_views,
)
from tasks.runner import default_store_url, open_store
from tasks.stages import (
    call_ingest, call_stage, capture_input_name, coarse_task, depth_task, evaluation_task, fitting_task,
    frames_task, fusion_task, keyframes_task, landmarks_task, poses_task, views_task,
)

STAGES = ("keyframes", "poses", "landmarks", "coarse", "mvs", "fitting", "evaluation")
"""Stages ``until`` can stop after, in order."""
Stage = Literal["keyframes", "poses", "landmarks", "coarse", "mvs", "fitting", "evaluation"]


def capture_name(video: str | Path) -> tuple[str, str]:
    """(subject, capture) of a video: the parent folder and the file stem."""
    p = Path(video)
    return p.parent.name or "capture", p.stem


def _run_name() -> str:
    from prefect.runtime import flow_run

    subject, capture = capture_name(flow_run.parameters.get("video", "capture"))
    return f"{subject}/{capture}"


def _mvs_fan_out(store: str, inputs: dict, config: dict, indices: list[int], label: str,
                 progress: bool) -> dict[int, str]:
    """One depth task per keyframe, ``workers`` at a time; a progress artifact in the UI."""
    from prefect.artifacts import create_progress_artifact, update_progress_artifact
    from tqdm import tqdm

    artifact = create_progress_artifact(0.0, description=f"depth maps of {label}")
    futures = {i: call_stage(depth_task, store, inputs, {**config, "_index": i}, label,
                             submit=True) for i in indices}
    keys = {}
    bar = tqdm(total=len(indices), desc="depth maps", unit="map", disable=not progress)
    for i, future in futures.items():
        keys[i] = future.result()
        bar.update()
        update_progress_artifact(artifact, 100.0 * len(keys) / len(indices))
    bar.close()
    return keys


EXPORTED = {
    "poses": ["cameras.json", "points.ply", "colmap/cameras.txt", "colmap/images.txt",
              "colmap/points3D.txt"],
    "coarse": ["cameras.json", "landmarks3d.json", "ears3d.json", "coarse.ply", "coarse.json"],
    "fusion": ["cloud.ply"],
    "fitting": ["mesh.ply", "mesh.obj", "fit.json"],
    "evaluation": ["evaluation.json", "heatmap_similarity.png", "heatmap_metric.png"],
}
"""The files of each stage copied into the output folder (besides report.json, preview.png)."""
OUTPUT_NAMES = {n for names in EXPORTED.values() for n in names} | {"report.json", "preview.png"}


def _export(store: str, keys: dict[str, str], out: Path) -> None:
    """Copy the user-facing files of the finished stages into ``out``; results an earlier
    run left there that this run did not make (a heat map when no scan is given now, a mesh
    after ``--until coarse``) are removed, so that the folder shows this run alone (they stay
    in the store)."""
    st = open_store(store)
    written = {"report.json"}  # rewritten after the export
    for stage, names in EXPORTED.items():
        if stage not in keys:
            continue
        folder = st.get(keys[stage])  # checked: a file changed after its commit is refused
        for name in names:
            src = folder / name
            if src.is_file():
                dst = out / name
                dst.parent.mkdir(parents=True, exist_ok=True)
                tmp = dst.with_name(f".{dst.name}.part")
                shutil.copyfile(src, tmp)
                tmp.replace(dst)
                written.add(name)
    for name in sorted(OUTPUT_NAMES - written):
        (out / name).unlink(missing_ok=True)


def _stage_report(store: str, keys: dict[str, str], started: datetime) -> dict:
    """Per stage: its key, whether this run found it in the store (committed before the run
    started), and the seconds its computation took."""
    st, report = open_store(store), {}
    for name, key in keys.items():
        manifest = st.manifest(key)
        report[name] = {"key": key,
                        "cached": datetime.fromisoformat(manifest.created) < started,
                        "seconds": manifest.meta.get("seconds"),
                        "cpu_seconds": manifest.meta.get("cpu_seconds")}
    return report


@flow(name="reconstruct-capture", flow_run_name=_run_name, log_prints=True,
      task_runner=ThreadPoolTaskRunner(max_workers=2))
def reconstruct_capture(video: str, out: str, config: str | None = None,
                        scan: str | None = None, scan_landmarks: str | None = None,
                        until: Stage = "evaluation", store: str | None = None,
                        progress: bool = False, ipd_mm: float | None = None) -> dict:
    """Reconstruct one capture; returns the report (also written to ``out/report.json``).

    ``config``: a PipelineConfig YAML; ``scan``/``scan_landmarks``: ground truth to score
    against; ``store``: artifact store URL (default ``$FACECAP_STORE``); ``ipd_mm``: the
    subject's interpupillary distance (far PD, mm), a scale cue (``coarse.ipd_mm``).
    """
    logger = get_run_logger()
    start = time.perf_counter()
    cfg = with_ipd(preflight(video, config, scan, scan_landmarks, out), ipd_mm)
    store = store or default_store_url()
    out_dir = Path(out)
    out_dir.mkdir(parents=True, exist_ok=True)
    subject, capture = capture_name(video)
    label = f"{subject}/{capture}"
    keys: dict[str, str] = {}
    now = datetime.now(timezone.utc)
    started = now.replace(microsecond=now.microsecond // 1000 * 1000)  # manifests keep ms

    def stop(stage: str) -> bool:
        return STAGES.index(stage) >= STAGES.index(until)

    v = call_ingest(store, video, capture_input_name(video), label)
    keys["keyframes"] = call_stage(keyframes_task, store, {"video": v},
                                   cfg.keyframes.model_dump(mode="json"), label)
    if not stop("keyframes"):
        keys["poses"] = call_stage(poses_task, store, {"video": v, "keyframes": keys["keyframes"]},
                                   cfg.poses.model_dump(mode="json"), label)
    if not stop("poses"):
        keys["frames"] = call_stage(frames_task, store, {"video": v, "poses": keys["poses"]}, {},
                                    label)
        keys["landmarks"] = call_stage(landmarks_task, store, {"video": v, "poses": keys["poses"]},
                                       cfg.landmarks.model_dump(mode="json"), label)
    if not stop("landmarks"):
        keys["coarse"] = call_stage(coarse_task, store, {"landmarks": keys["landmarks"],
                                                         "poses": keys["poses"]},
                                    cfg.coarse.model_dump(mode="json"), label)
    if not stop("coarse"):
        dense_and_fit(store, keys, cfg, label, until, scan, scan_landmarks, progress)
    _export(store, keys, out_dir)
    stages = _stage_report(store, keys, started)
    cached = sum(info["cached"] for info in stages.values())
    report = {
        "subject": subject, "capture": capture, "video": str(video), "store": store,
        "until": until, "wall_seconds": round(time.perf_counter() - start, 2),
        "computed": len(stages) - cached, "cached": cached, "stages": stages,
    }
    figures = _figures(out_dir)
    if figures:
        report["figures"] = figures
    (out_dir / "report.json").write_text(json.dumps(report, indent=1))
    _publish(report, out_dir, label)
    logger.info(f"{label}: {report['computed']} artifacts computed, {report['cached']} reused; "
                f"results in {out_dir}")
    return report


def _figures(out: Path) -> dict:
    """Headline figures of the exported files (what the UI table and the report show)."""
    fig = {}
    if (out / "cameras.json").is_file():
        doc = json.loads((out / "cameras.json").read_text())
        fig["keyframes"] = len(doc["keyframes"])
        fig["focal_px"] = round(doc["intrinsics"]["fx"], 2)
        if doc.get("metric_scale") is not None:
            fig["metric_scale"] = doc["metric_scale"]
        fig["dropped_keyframes"] = doc.get("dropped", [])
    if (out / "coarse.json").is_file():
        scale = json.loads((out / "coarse.json").read_text())["scale"]
        fig["scale"] = {k: scale.get(k) for k in ("metric_scale", "sigma_pct", "used", "cues",
                                                   "dropped", "how")}
    if (out / "landmarks3d.json").is_file():
        doc = json.loads((out / "landmarks3d.json").read_text())
        if doc.get("coverage"):
            fig["coverage"] = doc["coverage"]
    if (out / "fit.json").is_file():
        fit = json.loads((out / "fit.json").read_text())
        fig["fit_seconds"] = round(fit["timing"].get("wall_s", 0.0), 2)
        if fit.get("sanity"):
            fig["mesh_sanity"] = fit["sanity"]
    if (out / "evaluation.json").is_file():
        fig["evaluation"] = json.loads((out / "evaluation.json").read_text())
    return fig


def _publish(report: dict, out: Path, label: str) -> None:
    """UI artifacts (stage table, preview images) and a completion event."""
    from flows.ui import publish_capture

    publish_capture(report, out, label)


MIN_VIDEO_SIDE_PX = 120
"""Shortest video side accepted: below it a face is too few pixels to find landmarks on."""
MAX_VIDEO_SIDE_PX = 8192
"""Longest video side accepted (8K); the stages work on downscaled frames, but the keyframe
images are kept at full resolution."""


def preflight(video: str | Path, config: str | Path | None = None, scan: str | None = None,
              scan_landmarks: str | None = None, out: str | Path | None = None
              ) -> PipelineConfig:
    """Checks that need no stage: the files exist, the video decodes and is long and large
    enough, the config is valid, the output folder is writable. Run before anything is
    started so bad input fails in a second with one line."""
    from facecap_core.video import probe, stored_frame_count

    photos = Path(video).is_dir()
    if not photos and not Path(video).is_file():
        raise InputError(f"capture not found: {video}; give a video file or a folder of photos")
    info = probe(video)  # a photo folder: too few photos or mixed sizes fail here
    stored = stored_frame_count(video)
    if not photos and stored <= 1:
        raise InputError(f"{video} is a single image ({info.codec}), not a video; give the "
                         "capture's video file, or a folder of photos")
    if not photos and info.frame_count and stored < info.frame_count:
        raise InputError(f"{video} is truncated: it holds {stored} of its {info.frame_count} "
                         "frames; copy the whole file again")
    cfg = load_pipeline_config(config)
    size = f"{info.width}x{info.height}"
    if min(info.width, info.height) < MIN_VIDEO_SIDE_PX:
        raise InputError(f"{video} is {size} pixels, too small to find a face in; record at "
                         f"least {MIN_VIDEO_SIDE_PX} pixels on the short side (720p or more)")
    if max(info.width, info.height) > MAX_VIDEO_SIDE_PX:
        raise InputError(f"{video} is {size} pixels, larger than 8K ({MAX_VIDEO_SIDE_PX}); "
                         "record at 8K or less (4K is plenty)")
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
    from facecap_core import assets

    assets.default_template_files()  # fetched once; a damaged copy fails here, not at fitting
    if out is not None:
        check_output_folder(Path(out))
        results = {(Path(out) / n).resolve() for n in OUTPUT_NAMES}
        for what, path in (("capture", video), ("scan", scan), ("scan landmarks", scan_landmarks)):
            if path and Path(path).resolve() in results:
                raise InputError(f"the {what} {path} would be overwritten by a result of the same "
                                 f"name in the output folder {out}; give another --out")
    return cfg


def with_ipd(cfg: PipelineConfig, ipd_mm: float | None) -> PipelineConfig:
    """The config with the subject's interpupillary distance as a scale cue (validated like
    the config file's ``coarse.ipd_mm``)."""
    if ipd_mm is None:
        return cfg
    from facecap_core.config import CoarseConfig, build

    coarse = build(CoarseConfig, {**cfg.coarse.model_dump(), "ipd_mm": ipd_mm},
                   source="--ipd-mm")
    return cfg.model_copy(update={"coarse": coarse})


def as_user_sees_it(message: str, video: str | Path) -> str:
    """A stage's message with the store's copy of the video named as the user gave it
    (stages read the video from the artifact store, so they name the stored copy)."""
    import re

    stored = re.compile(r"\S*/input-[0-9a-f]{32}/video\.mp4")
    return " ".join(stored.sub(lambda _: str(video), message).split())


def check_output_folder(folder: Path) -> None:
    """Create the output folder if needed and write a scratch file into it."""
    import tempfile

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


def dense_and_fit(store: str, keys: dict[str, str], cfg: PipelineConfig, label: str,
                  until: str = "evaluation", scan: str | None = None,
                  scan_landmarks: str | None = None, progress: bool = False) -> dict[str, str]:
    """The stages after the coarse mesh (inside a flow): views, depth maps (fanned out),
    fusion, fitting, evaluation. ``keys`` holds the ``frames``, ``poses`` and ``coarse``
    artifacts and receives the new ones."""
    st = open_store(store)

    def stop(stage: str) -> bool:
        return STAGES.index(stage) >= STAGES.index(until)

    base = {"frames": keys["frames"], "coarse": keys["coarse"]}
    keys["views"] = call_stage(views_task, store, {**base, "poses": keys["poses"]},
                               config_part(cfg.mvs, VIEW_FIELDS), label)
    indices = sorted(read_views(st.get(keys["views"]) / "views.json"))
    depth = _mvs_fan_out(store, {**base, "views": keys["views"]},
                         config_part(cfg.mvs, DEPTH_FIELDS), indices, label, progress)
    keys.update({f"depth_{i:05d}": k for i, k in depth.items()})
    keys["fusion"] = call_stage(
        fusion_task, store, {**base, **{f"depth_{i:05d}": k for i, k in depth.items()}},
        config_part(cfg.mvs, FUSION_FIELDS), label)
    if stop("mvs"):
        return keys
    keys["fitting"] = call_stage(fitting_task, store, {
        "fusion": keys["fusion"], "coarse": keys["coarse"], "frames": keys["frames"]},
        cfg.fitting.model_dump(mode="json"), label)
    if stop("fitting") or not scan:
        return keys
    inputs = {"mesh": keys["fitting"], "scan": call_ingest(store, scan, Path(scan).name)}
    if scan_landmarks:
        inputs["scan_landmarks"] = call_ingest(store, scan_landmarks, Path(scan_landmarks).name)
    keys["evaluation"] = call_stage(evaluation_task, store, inputs, {}, label)
    return keys
