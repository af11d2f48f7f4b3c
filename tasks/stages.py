"""One thin Prefect task per stage: read inputs from the store, call facecap_core, store the
outputs, return the artifact key.

Every task has the signature ``(store, inputs, config) -> key``: ``inputs`` maps input names
to artifact keys and ``config`` is the stage's config as JSON data. The Prefect cache key is
the artifact key (:func:`tasks.runner.stage_key`); flows call tasks through
:func:`call_stage`, which forces a recompute when the artifact has left the store.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from prefect import task
from prefect.futures import PrefectFuture

from tasks.runner import (
    default_store_url, ingest, is_transient, open_store, retry_condition, run_stage, stage_key,
)

VIDEO = "video.mp4"
PHOTOS = "photos"


def capture_input_name(path: str | Path) -> str:
    """Name of a capture in its input artifact: ``video.mp4``, or ``photos`` for a folder."""
    return PHOTOS if Path(path).is_dir() else VIDEO


def _capture(folder: Path) -> Path:
    """The capture inside its input artifact: the video file or the photo folder."""
    return folder / PHOTOS if (folder / PHOTOS).is_dir() else folder / VIDEO


def _cfg(model_name: str, data: dict):
    """A stage config model from its JSON data (strict: unknown keys fail)."""
    from facecap_core import config as cfg

    return cfg.build(getattr(cfg, model_name), {k: v for k, v in data.items()
                                                if not k.startswith("_")},
                     source=model_name)


# -- stage bodies: (folders, out_dir, config) -> None ---------------------------------------


def compute_keyframes(f: dict[str, Path], out: Path, config: dict) -> None:
    from facecap_core import keyframes

    keyframes.main(_capture(f["video"]), out, _cfg("KeyframeConfig", config))


def compute_poses(f: dict[str, Path], out: Path, config: dict) -> None:
    from facecap_core import pose

    pose.main(_capture(f["video"]), f["keyframes"] / "keyframes.json", out,
              _cfg("PoseConfig", config))


def compute_frames(f: dict[str, Path], out: Path, config: dict) -> None:
    from facecap_core import frames

    frames.main(_capture(f["video"]), f["poses"] / "cameras.json", out)


def compute_landmarks(f: dict[str, Path], out: Path, config: dict) -> None:
    from facecap_core.landmarks import stage

    stage.main(_capture(f["video"]), f["poses"] / "cameras.json", out,
               _cfg("LandmarkConfig", config))


def compute_coarse(f: dict[str, Path], out: Path, config: dict) -> None:
    from facecap_core import coarse

    coarse.main(f["landmarks"], f["poses"] / "cameras.json", out,
                config=_cfg("CoarseConfig", config))


def compute_views(f: dict[str, Path], out: Path, config: dict) -> None:
    from facecap_core.mvs.stage import views_main

    views_main(f["frames"], f["coarse"] / "cameras.json", f["coarse"] / "coarse.ply", out,
               _cfg("MVSConfig", config), f["poses"] / "sparse.npz")


def compute_depth(f: dict[str, Path], out: Path, config: dict) -> None:
    from facecap_core.mvs.stage import depth_main

    depth_main(config["_index"], f["frames"], f["coarse"] / "cameras.json",
               f["views"] / "views.json", f["coarse"] / "coarse.ply", out,
               _cfg("MVSConfig", config))


def compute_fusion(f: dict[str, Path], out: Path, config: dict) -> None:
    from facecap_core.mvs.stage import fusion_main

    maps = sorted(p for name, folder in f.items() if name.startswith("depth_")
                  for p in folder.glob("depth_*.npz"))
    fusion_main(maps, f["frames"], f["coarse"] / "cameras.json", out,
                _cfg("MVSConfig", config))


def compute_fitting(f: dict[str, Path], out: Path, config: dict) -> None:
    from facecap_core.fitting.stage import main

    cloud = f["fusion"] / "cloud.ply" if "fusion" in f else None
    main(cloud, f["coarse"], f["frames"], out, _cfg("FittingConfig", config))


def compute_evaluation(f: dict[str, Path], out: Path, config: dict) -> None:
    from facecap_core.evaluation import evaluate_stage

    evaluate_stage(f["mesh"], f["scan"], out, scan_landmarks=f.get("scan_landmarks"))


COMPUTE = {
    "keyframes": compute_keyframes, "poses": compute_poses, "frames": compute_frames,
    "landmarks": compute_landmarks, "coarse": compute_coarse, "views": compute_views,
    "depth": compute_depth, "fusion": compute_fusion, "fitting": compute_fitting,
    "evaluation": compute_evaluation,
}


# -- Prefect tasks ---------------------------------------------------------------------------


def _cache_key(context, parameters: dict[str, Any]) -> str:
    return stage_key(context.task.name, parameters["inputs"], parameters["config"])


def _run_name(template: str):
    def name() -> str:
        from prefect.runtime import task_run

        params = task_run.parameters
        index = (params.get("config") or {}).get("_index")
        label = params.get("label") or ""
        return template.format(index=index, label=label).strip()
    return name


def _stage_task(stage: str, run_name: str | None = None, retries: int = 2):
    def body(store: str, inputs: dict[str, str], config: dict, label: str = "") -> str:
        key, computed = run_stage(store, stage, inputs, config, COMPUTE[stage])
        return key

    body.__name__ = f"{stage}_task"
    return task(
        body, name=stage, cache_key_fn=_cache_key, persist_result=True,
        result_serializer="json", retries=retries, retry_delay_seconds=[2, 10, 30],
        retry_jitter_factor=0.5, retry_condition_fn=retry_condition,
        task_run_name=_run_name(run_name or f"{stage} {{label}}"),
    )


keyframes_task = _stage_task("keyframes")
poses_task = _stage_task("poses")
frames_task = _stage_task("frames")
landmarks_task = _stage_task("landmarks")
coarse_task = _stage_task("coarse")
views_task = _stage_task("views")
depth_task = _stage_task("depth", "depth[{index}] {label}")
fusion_task = _stage_task("fusion")
fitting_task = _stage_task("fitting")
evaluation_task = _stage_task("evaluation")


def _ingest_key(context, parameters: dict[str, Any]) -> str:
    from facecap_core.store import input_key

    return input_key(parameters["path"])


@task(name="ingest", cache_key_fn=_ingest_key, persist_result=True, result_serializer="json",
      retries=2, retry_delay_seconds=[2, 10], retry_condition_fn=retry_condition,
      task_run_name=_run_name("ingest {label}"))
def ingest_task(store: str, path: str, name: str, label: str = "") -> str:
    """Copy a raw input (video, scan) into the store; returns its content key."""
    return ingest(store, path, name)


def _in_store(store: str, key: str) -> bool:
    """Whether the artifact is stored; an unreachable store counts as "no", so the task
    runs and meets the fault where its retries apply (a flow body has none)."""
    try:
        return open_store(store).exists(key)
    except Exception as exc:  # noqa: BLE001 - only transient faults are let through
        if is_transient(exc):
            return False
        raise


def call_stage(stage_task, store: str, inputs: dict[str, str], config: dict | None,
               label: str = "", submit: bool = False) -> str | PrefectFuture:
    """Run (or ``submit``) a stage task. The Prefect cache is trusted only while the artifact
    is in the store: a deleted or lost artifact is recomputed, not served from the cache."""
    key = stage_key(stage_task.name, inputs, config)
    fresh = not _in_store(store, key)
    runner = stage_task.with_options(refresh_cache=fresh)
    if submit:
        return runner.submit(store, inputs, config, label)
    return runner(store, inputs, config, label)


def call_ingest(store: str, path: str | Path, name: str, label: str = "") -> str:
    from facecap_core.store import input_key

    fresh = not _in_store(store, input_key(path))
    return ingest_task.with_options(refresh_cache=fresh)(store, str(path), name, label)


__all__ = ["call_stage", "call_ingest", "default_store_url", "COMPUTE"]
