"""facecap_core's log in the runs: every record of the ``facecap_core`` logger hierarchy at
INFO and above goes to the API log of the flow or task run it happens in (the run's page in
the UI), depth maps computed in the task runner's threads included.

facecap_core knows nothing of Prefect: it logs with ``logging.getLogger(__name__)``. The
handler is attached here, by the code that runs the stages (:mod:`facecap.tasks.stages` on import,
so a worker started with Prefect's default settings has it), and it does not depend on
``PREFECT_LOGGING_EXTRA_LOGGERS``: where that setting names facecap_core (or one of its
modules) the handler Prefect put there is replaced, so that each record is sent once.

Outside a run (benchmarks, plain Python) the records have no run to go to and are left to
the other handlers: the API handler neither warns nor fails there, whatever
``PREFECT_LOGGING_TO_API_WHEN_MISSING_FLOW`` says.
"""

from __future__ import annotations

import logging
import threading

from prefect.context import FlowRunContext, TaskRunContext
from prefect.logging.handlers import APILogHandler

CORE_LOGGER = "facecap_core"
"""The logger hierarchy of facecap_core's modules."""
CORE_LEVEL = logging.INFO
"""The least level of a facecap_core record sent to the run's log."""
_ATTACH = threading.Lock()  # tasks in several threads may attach at once


def in_run() -> bool:
    """Whether this code runs inside a flow or task run (a task's thread included: the task
    runner copies the context into it)."""

    task = TaskRunContext.get()
    flow = FlowRunContext.get()
    return bool((task and task.task_run) or (flow and flow.flow_run))


class RunLogHandler(APILogHandler):
    """Prefect's API log handler for records that may come outside any run: those are not
    the API's (the base handler would give a MissingContextError to ``handleError``, which
    warns or raises as ``PREFECT_LOGGING_TO_API_WHEN_MISSING_FLOW`` says) and are skipped."""

    def emit(self, record: logging.LogRecord) -> None:
        if getattr(record, "flow_run_id", None) is None and not in_run():
            return
        super().emit(record)


def send_core_logs_to_runs() -> RunLogHandler:
    """Attach the run log handler to the ``facecap_core`` logger (once per process) and let
    its INFO records through; returns the handler."""
    with _ATTACH:
        return _attach()


def _attach() -> RunLogHandler:
    core = logging.getLogger(CORE_LOGGER)
    modules = [logger for name, logger in list(logging.Logger.manager.loggerDict.items())
               if name.startswith(f"{CORE_LOGGER}.") and isinstance(logger, logging.Logger)]
    for logger in [core, *modules]:
        for handler in list(logger.handlers):  # PREFECT_LOGGING_EXTRA_LOGGERS put them there
            if isinstance(handler, APILogHandler) and not isinstance(handler, RunLogHandler):
                logger.removeHandler(handler)
    handler = next((h for h in core.handlers if isinstance(h, RunLogHandler)), None)
    if handler is None:
        handler = RunLogHandler(level=CORE_LEVEL)
        core.addHandler(handler)
    if core.getEffectiveLevel() > CORE_LEVEL:
        core.setLevel(CORE_LEVEL)
    return handler
