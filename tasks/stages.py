"""One thin Prefect task per row of the stage graph (:mod:`facecap.tasks.graph`): read the inputs
from the store, compute, store the outputs.

Every task has the signature ``(store, inputs, config, params, label) -> (key, computed)``:
``inputs`` maps input names to artifact keys, ``config`` is the stage's settings (its
section of the run's PipelineConfig, validated once where the config was read, or None)
and ``params`` its per-keyframe parameters. The store is the cache: a task whose
artifact is stored returns at once with ``computed`` false, and the run report takes that
flag from the tasks themselves. What facecap_core logs at INFO and above while a task runs
is in the task run's log (:mod:`facecap.tasks.logs`).
"""

from __future__ import annotations

import concurrent.futures
import time
from collections.abc import Callable
from pathlib import Path

from prefect import get_run_logger, task
from prefect.cache_policies import NO_CACHE
from prefect.futures import PrefectFuture
from prefect.runtime import task_run
from prefect.states import Completed, State
from prefect.task_engine import TaskRunTimeoutError
from pydantic import BaseModel

from facecap.tasks.graph import BY_NAME, STAGES, stage_key
from facecap.tasks.logs import send_core_logs_to_runs
from facecap.tasks.runner import default_store_url, ingest, retry_condition, run_stage
from facecap.tasks.store import open_store
from facecap_core.errors import FacecapError
from facecap_core.settings import settings

send_core_logs_to_runs()  # every process that runs a stage: facecap_core's log in its runs


def _run_name(template: str):
    def name() -> str:
        params = task_run.parameters
        index = (params.get("params") or {}).get("index")
        label = params.get("label") or ""
        return template.format(index=index, label=label).strip()
    return name


def _headline(stage, store: str, key: str) -> str:
    """The figure a stage's log line gives (its row's ``headline``: the coarse stage's metric
    scale)."""
    return stage.headline(open_store(store).get(key)) if stage.headline else ""


def _stage_task(name: str):
    stage = BY_NAME[name]

    def body(store: str, inputs: dict[str, str], config: BaseModel | None,
             params: dict | None = None,
             label: str = "") -> tuple[str, bool]:
        send_core_logs_to_runs()  # again, should a logging setup since the import have undone it
        key, computed = run_stage(store, stage, inputs, config, params)
        where = f"{name}[{params['index']}]" if params and "index" in params else name
        # The UI's log list shows messages without their task: each names its stage.
        get_run_logger().info(f"{label + ': ' if label else ''}{where} "
                              f"{'computed' if computed else 'reused'}{_headline(stage, store, key)}")
        if computed:
            return key, computed
        # A reused artifact takes no time: the task run says so in the UI ("Reused") rather
        # than looking like instant work.
        return Completed(data=(key, False), name="Reused",
                         message=f"{key} was in the store: reused, nothing computed")

    body.__name__ = f"{name}_task"
    template = f"{name}[{{index}}] {{label}}" if stage.per_keyframe else f"{name} {{label}}"
    return task(
        body, name=name, cache_policy=NO_CACHE, persist_result=False, retries=2,
        retry_delay_seconds=[2, 10, 30],
        retry_jitter_factor=0.5, retry_condition_fn=retry_condition,
        task_run_name=_run_name(template),
    )


TASKS = {stage.name: _stage_task(stage.name) for stage in STAGES}
"""The Prefect task of every stage, by name."""


def _stored_maps_task(name: str):
    stage = BY_NAME[name]

    def body(store: str, inputs: dict[str, str], config: BaseModel | None,
             indices: list[int], label: str = "") -> list[tuple[str, bool]]:
        send_core_logs_to_runs()
        # Stored when the flow looked; a map pruned since is made again here, in turn.
        runs = [run_stage(store, stage, inputs, config, {"index": i}) for i in indices]
        computed = sum(made for _, made in runs)
        get_run_logger().info(f"{label + ': ' if label else ''}{name} {len(runs) - computed} "
                              f"maps reused" + (f", {computed} computed" if computed else ""))
        if computed:
            return runs
        return Completed(data=runs, name="Reused",
                         message=f"{len(runs)} maps were in the store: reused, nothing computed")

    def run_name() -> str:
        params = task_run.parameters
        return (f"{name} ({len(params.get('indices') or [])} maps reused) "
                f"{params.get('label') or ''}").strip()

    body.__name__ = f"{name}_stored_maps_task"
    return task(body, name=name, cache_policy=NO_CACHE, persist_result=False, retries=2,
                retry_delay_seconds=[2, 10, 30], retry_jitter_factor=0.5,
                retry_condition_fn=retry_condition, task_run_name=run_name)


STORED_MAPS_TASKS = {stage.name: _stored_maps_task(stage.name) for stage in STAGES
                     if stage.per_keyframe}
"""Per fanned-out stage, the one task run that stands for all its maps when the store
holds every one: a rerun shows the stage once ("depth (40 maps reused)"), not a task run
per map, each costing the server as much as a computed one."""


def all_stored(name: str, store: str, inputs: dict[str, str], config: BaseModel | None,
               indices: list[int]) -> bool:
    """Whether the store holds the artifact of every map ``indices`` of stage ``name``."""
    st = open_store(store)
    return all(st.exists(stage_key(name, inputs, config, {"index": i})) for i in indices)


def call_stored_maps(name: str, store: str, inputs: dict[str, str], config: BaseModel | None,
                     indices: list[int], label: str = "", deadline: float | None = None
                     ) -> list[tuple[str, bool]]:
    """``(key, computed)`` of each map ``indices`` of fanned-out stage ``name``, all
    stored (:func:`all_stored`), from one task run within the stage's limits."""
    now = time.monotonic()
    end = _end(now, deadline)
    runner = _within_limits(STORED_MAPS_TASKS[name], name, label, now, end, deadline)
    runner = runner.with_options(timeout_seconds=end - now)
    return stage_result(name, lambda: runner(store, inputs, config, indices, label), label,
                        now, deadline)


@task(name="ingest", cache_policy=NO_CACHE, retries=2, retry_delay_seconds=[2, 10],
      retry_condition_fn=retry_condition, task_run_name=_run_name("ingest {label}"))
def ingest_task(store: str, path: str, name: str, label: str = "") -> str:
    """Copy a raw input (video, photos, scan) into the store; returns its content key."""
    return ingest(store, path, name)


def _within_limits(runner, name: str, label: str, now: float, end: float,
                   deadline: float | None):
    """``runner`` (a stage's task) retried only while its time lasts; refused with the
    time limit's line once that has passed (``end``: the stage's or the capture's end,
    ``time.monotonic()``)."""
    if end <= now:
        raise FacecapError(capture_time_limit_message(label or "the capture", name)
                           if deadline is not None and end == deadline
                           else stage_time_limit_message(label or "the capture", name))
    # A retry starts the attempt's time again: none once the limit has passed.
    return runner.with_options(retry_condition_fn=lambda task, run, state: (
        time.monotonic() < end and retry_condition(task, run, state)))


def call_stage(name: str, store: str, inputs: dict[str, str], config: BaseModel | None,
               label: str = "", params: dict | None = None, submit: bool = False,
               deadline: float | None = None, started: float | None = None
               ) -> tuple[str, bool] | PrefectFuture:
    """Run the task of stage ``name`` within ``FACECAP_STAGE_TIMEOUT_S`` and before the
    capture's ``deadline`` (``time.monotonic()``); returns ``(key, computed)``.

    With ``submit``, a future for :func:`stage_result`: a whole stage carries its Prefect
    timeout; one map of a fanned-out stage (``params``; ``started`` the fan-out's start)
    none, the fan-out as a whole keeps the limits by the wait in ``stage_result`` (a timeout
    per map would warn on every map)."""
    now = time.monotonic()
    end = _end(now if started is None else started, deadline)
    runner = _within_limits(TASKS[name], name, label, now, end, deadline)
    if not submit or params is None:  # a whole stage; a fanned-out map carries none
        runner = runner.with_options(timeout_seconds=end - now)
    if submit:
        return _timed(runner.submit(store, inputs, config, params, label))
    return stage_result(name, lambda: runner(store, inputs, config, params, label), label,
                        now, deadline)


def _end(started: float, deadline: float | None) -> float:
    """When a stage started at ``started`` must end: its own limit or the capture's."""
    end = started + settings().stage_timeout_s
    return end if deadline is None else min(end, deadline)


def _timed(future: PrefectFuture) -> PrefectFuture:
    """``future`` noting when its task ended (``finished_at``, ``time.monotonic()``): a
    stage waited for later, when a later stage reads it, is judged by its own end."""
    future.wrapped_future.add_done_callback(
        lambda done: setattr(done, "finished_at", time.monotonic()))
    return future


def _ended(result: PrefectFuture | Callable[[], tuple]) -> float:
    """When a stage's task ended: a future's own end, now for a call just returned."""
    if isinstance(result, PrefectFuture):
        return getattr(result.wrapped_future, "finished_at", time.monotonic())
    return time.monotonic()


def first_finished(futures: list[PrefectFuture], started: float,
                   deadline: float | None = None) -> int:
    """The position in ``futures`` (a fanned-out stage's maps, which ``started`` then) of
    one that has finished, whichever finishes first: the next map starts on the worker it
    frees. Past the stage's limit, the first (:func:`stage_result` then fails on it)."""
    wrapped = [f.wrapped_future for f in futures]
    done, _ = concurrent.futures.wait(wrapped, timeout=max(0.0, _end(started, deadline)
                                                            - time.monotonic()),
                                      return_when=concurrent.futures.FIRST_COMPLETED)
    return next((k for k, f in enumerate(wrapped) if f in done), 0)


def stage_result(name: str, result: PrefectFuture | Callable[[], tuple], label: str,
                 started: float, deadline: float | None = None) -> tuple[str, bool]:
    """``(key, computed)`` of a stage's task: a future (waited for until the stage's time
    limit from ``started``, or the capture's ``deadline``) or the call itself. A stage
    stopped at either limit raises a one-line FacecapError naming that limit; the task's
    own errors pass through."""


    end = _end(started, deadline)
    where = label or "the capture"
    over = (capture_time_limit_message(where, name) if deadline is not None and end == deadline
            else stage_time_limit_message(where, name))
    try:
        if isinstance(result, PrefectFuture):
            done, _ = concurrent.futures.wait([result.wrapped_future],
                                              timeout=max(0.0, end - time.monotonic()))
            if not done:
                raise FacecapError(over)
            value = tuple(result.result())
        else:
            value = result()
            value = tuple(value.result() if isinstance(value, State) else value)
    except Exception as exc:
        # Prefect stops a stage by raising in its thread, and code that catches and
        # rewraps errors (pycolmap's import does) can turn that into another one: an
        # error other than facecap's own, once the limit has passed, is the limit.
        if isinstance(exc, TaskRunTimeoutError) or (
                not isinstance(exc, FacecapError) and _ended(result) >= end):
            raise FacecapError(over) from None
        raise
    # Prefect interrupts a stage by raising in its thread, which a native call holds off and
    # a logging or cleanup handler can swallow: the limits hold at the latest here, with
    # the stage's artifact stored (a rerun with a higher limit reuses it).
    now = _ended(result)
    if now > end:  # past the first of the two limits: the capture's, if it is past too
        raise FacecapError(capture_time_limit_message(where, name)
                           if deadline is not None and now > deadline
                           else stage_time_limit_message(where, name))
    return value


def stage_time_limit_message(where: str, stage: str) -> str:
    """What a stage stopped at ``FACECAP_STAGE_TIMEOUT_S`` says."""
    return (f"the {stage} stage of {where} was stopped after its time limit of "
            f"{settings().stage_timeout_s:g} s (FACECAP_STAGE_TIMEOUT_S); raise the limit for "
            "a capture this large, or look for what held it up in the run's log")


def capture_time_limit_message(where: str, stage: str | None = None) -> str:
    """What a capture run stopped at ``FACECAP_CAPTURE_TIMEOUT_S`` says."""
    during = f" during the {stage} stage" if stage else ""
    return (f"{where} was stopped after the capture's time limit of "
            f"{settings().capture_timeout_s:g} s (FACECAP_CAPTURE_TIMEOUT_S){during}; raise "
            "the limit for a capture this large, or look for what held it up in the run's log")


def call_ingest(store: str, path: str | Path, name: str, label: str = "") -> str:
    return ingest_task(store, str(path), name, label)


__all__ = ["TASKS", "call_ingest", "call_stage", "capture_time_limit_message",
           "default_store_url", "ingest_task", "stage_result"]
