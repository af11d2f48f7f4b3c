"""How a ``facecap`` command that runs flows sets up its process: Prefect's defaults, its
scratch folder, quiet consoles (unless ``--verbose``) and its own Prefect server."""

from __future__ import annotations

import errno
import logging
import logging.config
import os
import sys
from pathlib import Path

from facecap.flows.local_server import start_local_server
from facecap.tasks.own_files import NAME_MAX
from facecap.tasks.scratch import process_scratch, remove_orphans
from facecap_core.assets import facecap_home
from facecap_core.settings import folder_problem

# Imported where used: Prefect reads its settings when first imported; prefect_defaults() sets
# them first.


def prefect_defaults() -> None:
    """Defaults for running flows on the embedded server of a 2-core machine. Prefect reads
    its settings when it is first imported, so :func:`main` sets them before anything else."""
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "180")
    # No PREFECT_LOGGING_LEVEL: the UI keeps every log line; the console is quieted by a
    # logging configuration (see _quiet_console).


def prefect_home_value() -> str:
    """``PREFECT_HOME`` as set, or Prefect's default ``~/.prefect``."""
    return os.environ.get("PREFECT_HOME") or "~/.prefect"


def prefect_home_problem() -> str | None:
    """Why the folder Prefect keeps its files in (``PREFECT_HOME``, default ``~/.prefect``)
    cannot be one, as the one line of a refusal, or None. Prefect itself only warns
    when it cannot make it, and its server then fails to start: found here, before Prefect
    is imported, the variable is named."""
    value = prefect_home_value()
    problem = folder_problem(Path(value).expanduser())
    if problem is None:
        return None
    where = (f"invalid PREFECT_HOME={value!r} in the environment" if "PREFECT_HOME" in os.environ
             and os.environ["PREFECT_HOME"] else f"Prefect's default folder {value}")
    return (f"{where}: {problem}; set PREFECT_HOME to a writable folder, or unset it for "
            "Prefect's default (~/.prefect)")


FULL_BYTES = 2**20
"""Free space under which a disk counts as full: a write of Prefect's database or of a
stage's scratch file fails there."""


def full_disk_error(exc: BaseException) -> str | None:
    """The error line of ``exc`` when the disk of facecap's or Prefect's files is full, or
    None: what an unexpected error is put down to before it is called a bug (Prefect's
    server answers a write to its full database with "500 Internal Server Error")."""
    full = full_disk()
    if full is None:
        return None
    return (f"no space left on the disk of {full} ({type(exc).__name__}: "
            f"{' '.join(str(exc).split())[:80]}); free space there and run again (what was "
            "computed before is kept)")


def name_too_long_error(exc: BaseException) -> str | None:
    """The error line of ``exc`` when a path is longer than the file system allows
    (ENAMETOOLONG: a name of the user's over 255 bytes, or the whole path too long), or
    None: the user's names, not a bug of facecap's."""
    if not (isinstance(exc, OSError) and exc.errno == errno.ENAMETOOLONG):
        return None
    path = os.fsencode(exc.filename or "")
    longest = max(path.split(b"/"), key=len)
    if len(longest) > NAME_MAX:
        return (f"the name {os.fsdecode(longest[:24])!r}... is {len(longest)} bytes long, longer "
                f"than a file or folder name can be ({NAME_MAX}); give a shorter name")
    return (f"the path {os.fsdecode(path[:48])!r}... is {len(path)} bytes long, longer than the "
            "file system allows; give a shorter path")


def full_disk() -> str | None:
    """The folders of facecap's and Prefect's files (``FACECAP_HOME``, ``PREFECT_HOME``) whose
    disk is full, in words, or None."""
    folders = {"FACECAP_HOME": facecap_home(),
               "PREFECT_HOME": Path(prefect_home_value()).expanduser()}
    full = []
    for name, folder in folders.items():
        try:
            stats = os.statvfs(folder)
        except OSError:
            continue
        if stats.f_bavail * stats.f_frsize < FULL_BYTES:
            full.append(f"{name} {folder}")
    return " and ".join(full) or None


VERBOSE = False
"""``facecap --verbose``: third-party logs (COLMAP, Prefect) and facecap's own debug log
on the console."""


def prefect_env(console_level: str = "WARNING", heartbeats: bool = False) -> None:
    """What a command that runs flows sets up first: its scratch folder under FACECAP_HOME
    (the folders of killed commands removed), quiet consoles (unless ``--verbose``) and its
    own Prefect server unless PREFECT_API_URL names one.

    On a server of its own, the command's flow runs send no heartbeats unless
    ``heartbeats`` (a served deployment's runs do): a heartbeat tells a server that a run
    whose process died has crashed, and this server dies with the process. Prefect's
    heartbeat thread wakes once a second to see whether its run ended, so every flow run
    waited up to a second at its end for it (a capture whose stages are all stored takes
    seconds)."""
    remove_orphans()
    process_scratch()  # before COLMAP loads: its glog files go there too
    _logging(console_level)
    if start_local_server(quiet=not VERBOSE) is not None and not heartbeats:
        _without_heartbeats()


def _without_heartbeats() -> None:
    """No flow run heartbeats for the rest of this process (its main thread, where the flow
    engine reads the setting)."""
    from prefect.context import SettingsContext, get_settings_context
    from prefect.settings import PREFECT_FLOWS_HEARTBEAT_FREQUENCY

    context = get_settings_context()
    settings = context.settings.copy_with_update(updates={PREFECT_FLOWS_HEARTBEAT_FREQUENCY: None})
    # Entered for good: the command ends with its process.
    SettingsContext(profile=context.profile, settings=settings).__enter__()


def _logging(console_level: str) -> None:
    """Quiet consoles for a command that runs flows (unless ``--verbose``)."""
    prefect_defaults()
    if VERBOSE:
        core = logging.getLogger("facecap_core")
        if not core.handlers:
            handler = logging.StreamHandler()
            handler.setFormatter(logging.Formatter("%(asctime)s %(name)s: %(message)s",
                                                   "%H:%M:%S"))
            core.addHandler(handler)
        core.setLevel(logging.DEBUG)
        _quiet_console("DEBUG")
        return
    # COLMAP (pose stage) logs through glog straight to stderr; its failures reach the user
    # as the pose stage's one-line message.
    os.environ.setdefault("GLOG_minloglevel", "3")
    if "pycolmap" in sys.modules:  # already loaded: glog read its environment then
        sys.modules["pycolmap"].logging.minloglevel = int(os.environ["GLOG_minloglevel"])
    _quiet_console(console_level)


RUN_LOGGERS = ("prefect.flow_runs", "prefect.task_runs")
"""Prefect's loggers of flow and task runs (what the run pages of the UI show)."""

DRAIN_LOGGERS = ("EventsWorker", "APILogWorker")
"""The loggers of Prefect's background senders of events and logs, named after their class:
at a command's exit each says "Still processing items: N items remaining..." (a WARNING)
while it sends what the run left queued, which a slow server leaves behind on any exit."""


def _not_drain_progress(record: logging.LogRecord) -> bool:
    """A filter of :data:`DRAIN_LOGGERS`: their exit progress is not the user's business;
    what they lose (a full queue) or fail to send still shows."""
    return not str(record.msg).startswith("Still processing items")


def console_logging(level: str, runs_on_console: bool = False) -> dict:
    """The command line's logging configuration, applied over Prefect's own (``logging.yml``,
    whose console handler is named ``console``) with :func:`logging.config.dictConfig`: the
    runs' logs go to the API alone unless ``runs_on_console``, and the console shows
    ``level`` and above of the other loggers."""
    from prefect.logging.configuration import PROCESS_LOGGING_CONFIG

    console = "console" in PROCESS_LOGGING_CONFIG.get("handlers", {})  # a logging.yml of
    handlers = {"console": {"level": level}} if console else {}  # one's own may lack it
    return {"version": 1, "incremental": True, "handlers": handlers,
            "loggers": {name: {"propagate": runs_on_console} for name in RUN_LOGGERS}}


def _quiet_console(level: str = "WARNING") -> None:
    """A failed run reaches the user once, from :func:`main`: bad input as one line, a bug
    as one line naming the log file with its traceback. So the runs' logs (the failed state,
    the traceback) go to the API and the UI alone, not to the console, unless ``--verbose``
    asks for them; and below ``level`` nothing reaches the console (the API logs still get
    everything). Prefect is imported before the environment defaults are set, so this is
    applied over its logging setup rather than through ``PREFECT_LOGGING_*`` settings."""
    from prefect.logging.configuration import ensure_logging_setup

    ensure_logging_setup()
    logging.config.dictConfig(console_logging(level, runs_on_console=VERBOSE))
    for name in DRAIN_LOGGERS:
        drain = logging.getLogger(name)
        if not VERBOSE and _not_drain_progress not in drain.filters:
            drain.addFilter(_not_drain_progress)


