"""One thin Prefect task per row of the stage graph (:mod:`tasks.graph`): read the inputs
from the store, compute, store the outputs.

Every task has the signature ``(store, inputs, config, params, label) -> (key, computed)``:
``inputs`` maps input names to artifact keys, ``config`` is the stage's config section as
JSON data and ``params`` its per-keyframe parameters. The store is the cache: a task whose
artifact is stored returns at once with ``computed`` false, and the run report takes that
flag from the tasks themselves. What facecap_core logs at INFO and above while a task runs
is in the task run's log (:mod:`tasks.logs`).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from prefect import task
from prefect.cache_policies import NO_CACHE
from prefect.futures import PrefectFuture

from facecap_core.errors import FacecapError
from facecap_core.settings import settings
from tasks.graph import BY_NAME, STAGES
from tasks.logs import send_core_logs_to_runs
from tasks.runner import default_store_url, ingest, retry_condition, run_stage

send_core_logs_to_runs()  # every process that runs a stage: facecap_core's log in its runs


def _run_name(template: str):
    def name() -> str:
        from prefect.runtime import task_run

        params = task_run.parameters
        index = (params.get("params") or {}).get("index")
        label = params.get("label") or ""
        return template.format(index=index, label=label).strip()
    return name


def _stage_task(name: str):
    stage = BY_NAME[name]

    def body(store: str, inputs: dict[str, str], config: dict, params: dict | None = None,
             label: str = "") -> tuple[str, bool]:
        send_core_logs_to_runs()  # again, should a logging setup since the import have undone it
        return run_stage(store, stage, inputs, config, params)

    body.__name__ = f"{name}_task"
    template = f"{name}[{{index}}] {{label}}" if stage.per_keyframe else f"{name} {{label}}"
    return task(
        body, name=name, cache_policy=NO_CACHE, retries=2, retry_delay_seconds=[2, 10, 30],
        retry_jitter_factor=0.5, retry_condition_fn=retry_condition,
        task_run_name=_run_name(template),
    )


TASKS = {stage.name: _stage_task(stage.name) for stage in STAGES}
"""The Prefect task of every stage, by name."""


@task(name="ingest", cache_policy=NO_CACHE, retries=2, retry_delay_seconds=[2, 10],
      retry_condition_fn=retry_condition, task_run_name=_run_name("ingest {label}"))
def ingest_task(store: str, path: str, name: str, label: str = "") -> str:
    """Copy a raw input (video, photos, scan) into the store; returns its content key."""
    return ingest(store, path, name)


def call_stage(name: str, store: str, inputs: dict[str, str], config: dict | None,
               label: str = "", params: dict | None = None, submit: bool = False
               ) -> tuple[str, bool] | PrefectFuture:
    """Run (or ``submit``) the task of stage ``name``, within ``FACECAP_STAGE_TIMEOUT_S``;
    returns ``(key, computed)``, or a future for :func:`stage_result`."""
    runner = TASKS[name].with_options(timeout_seconds=settings().stage_timeout_s)
    if submit:
        return runner.submit(store, inputs, config or {}, params, label)
    return stage_result(name, lambda: runner(store, inputs, config or {}, params, label), label)


def stage_result(name: str, result: PrefectFuture | Callable[[], tuple], label: str = ""
                 ) -> tuple[str, bool]:
    """``(key, computed)`` of a stage's task (a future, or the call itself); a stage stopped
    at its time limit ends its task run TimedOut and raises a one-line FacecapError."""
    from prefect.task_engine import TaskRunTimeoutError

    try:
        return tuple(result.result() if isinstance(result, PrefectFuture) else result())
    except TaskRunTimeoutError:
        limit = settings().stage_timeout_s
        raise FacecapError(f"the {name} stage of {label or 'the capture'} was stopped after "
                           f"its time limit of {limit:g} s (FACECAP_STAGE_TIMEOUT_S); raise "
                           "the limit for a capture this large, or look for what held it up "
                           "in the run's log") from None


def call_ingest(store: str, path: str | Path, name: str, label: str = "") -> str:
    return ingest_task(store, str(path), name, label)


__all__ = ["TASKS", "call_ingest", "call_stage", "default_store_url", "ingest_task",
           "stage_result"]
