"""The Prefect server a ``facecap`` command starts for itself when no ``PREFECT_API_URL`` is
set, held to the command's life.

Prefect would start that server as a child process (uvicorn) when its client is first used,
after seconds of loading its server code, and stop it at exit; a command that is killed
(SIGKILL, the OOM killer) cannot stop it, and the server would live on. So the command starts
Prefect's server itself, first thing (while it loads the pipeline and Prefect, on the other
core), names it as its ``PREFECT_API_URL`` once it answers, and starts with it a watchdog: a
tiny process that holds the reading end of a pipe whose writing end only the command holds.
When the command ends, however it ends, the kernel closes that end, the watchdog reads
end-of-file and stops the server.

The server's own output (its shutdown can print a traceback of a cancelled database query)
goes to ``$FACECAP_HOME/logs/server.log``, not to the command's console.
"""

from __future__ import annotations

import atexit
import contextlib
import importlib.util
import os
import re
import socket
import subprocess
import sys
import time
from pathlib import Path

from facecap.tasks.own_files import OwnFileError, open_log, open_regular
from facecap.tasks.scratch import process_scratch, start_ticks
from facecap_core.assets import facecap_home
from facecap_core.errors import InputError

# Imported where used: Prefect reads its settings when first imported; the command line sets them
# first (facecap/console.py). httpx (Prefect loads it) after the server's start, not before.

LOG_NAME = "server.log"
MAX_LOG_BYTES = 4 * 2**20
"""The server log starts again from empty past this size."""

WATCHDOG = """
import os, select, signal, sys, time
pid, ticks = int(sys.argv[1]), sys.argv[2]
def same():
    try:
        os.kill(pid, 0)
        if ticks == "0":
            return True
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().rsplit(")", 1)[1].split()[19] == ticks
    except OSError:
        return False
signal.signal(signal.SIGINT, signal.SIG_IGN)
while same():
    ready, _, _ = select.select([0], [], [], 1.0)
    if ready and not os.read(0, 1):
        break
else:
    sys.exit(0)
os.kill(pid, signal.SIGTERM)
for _ in range(50):
    time.sleep(0.1)
    if not same():
        sys.exit(0)
os.kill(pid, signal.SIGKILL)
"""
"""The watchdog: stops the server (SIGTERM, then SIGKILL after 5 s) once its standard input
ends, and exits by itself when the server ends first. The server is identified by its pid and
start time, so a reused pid is never signalled."""

_spawned: _Server | None = None
"""The server started by :func:`spawn_local_server` and not yet adopted."""


def server_log() -> Path:
    return facecap_home() / "logs" / LOG_NAME


def open_server_log() -> int:
    """The server log, open for appending (:func:`tasks.own_files.open_log`: ``logs`` or
    ``server.log`` planted as a link or a FIFO is refused in one line, nothing written
    behind it)."""
    return open_log(server_log().parent, LOG_NAME, MAX_LOG_BYTES)


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _uvicorn(port: int, log: int | None) -> subprocess.Popen:
    """Prefect's own ephemeral server (``SubprocessASGIServer``'s command and environment),
    on ``port``, its temporary files in this command's scratch folder, its output to the
    descriptor ``log`` (or this command's console)."""
    prefect_dir = Path(importlib.util.find_spec("prefect").origin).parent  # not imported
    command = [sys.executable, "-m", "uvicorn", "--app-dir", str(prefect_dir.parent),
               "--factory", "prefect.server.api.server:create_app", "--host", "127.0.0.1",
               "--port", str(port), "--log-level", "error", "--lifespan", "on"]
    env = {**os.environ, "PREFECT_UI_ENABLED": "0", "PREFECT__SERVER_EPHEMERAL": "1",
           "PREFECT__SERVER_FINAL": "1", "TMPDIR": str(process_scratch())}
    if "prefect.settings" in sys.modules:  # settings changed in this process, as Prefect does
        from prefect.settings import get_current_settings

        env.update(get_current_settings().to_environment_variables(exclude_unset=True))
    return subprocess.Popen(command, env=env, stdout=log, stderr=log)


DATABASE_ERROR = re.compile(r"^sqlalchemy\.exc\.\w+: \((?:\w+\.)*\w+\) (.+)$", re.MULTILINE)
"""How the server's log names the database error its start-up failed on."""


def database_problem(log: Path, offset: int) -> str | None:
    """The database error a failed start wrote into ``log`` past byte ``offset`` (its
    last), or None."""
    try:
        with os.fdopen(open_regular(log), "rb") as file:
            file.seek(offset)
            text = file.read(MAX_LOG_BYTES).decode("utf-8", "replace")
    except (OSError, OwnFileError):
        return None
    found = DATABASE_ERROR.findall(text)
    return found[-1].strip() if found else None


def database_error(problem: str) -> InputError:
    """The line for a server that cannot open its database: not facecap's bug, and not
    mended by another try (a start stopped while it set a new database up, a damaged file,
    another program's file)."""
    from prefect.settings import get_current_settings

    url = get_current_settings().server.database.connection_url
    where = (url.get_secret_value() if hasattr(url, "get_secret_value") else str(url or ""))
    where = where.split(":///", 1)[-1] or "its database"
    return InputError(f"the local Prefect server cannot open its database {where} ({problem}); "
                      "move that file aside (it holds only the local run history) or set "
                      "PREFECT_API_URL to a running server, then run again")


class _Server:
    """A server process of this command's, on a free port, with the watchdog that stops it
    when the command ends (the watchdog holds the reading end of ``lifeline``)."""

    STARTS = 3
    """Tries at starting, should uvicorn exit with its start-up failure code (3: the port
    taken meanwhile, or the application's start failed)."""

    def __init__(self, quiet: bool):
        self.port = _free_port()
        log = open_server_log() if quiet else None
        try:
            self.log_offset = os.fstat(log).st_size if log is not None else None
            self.process = _uvicorn(self.port, log)
        finally:
            if log is not None:
                os.close(log)
        reading, self.lifeline = os.pipe()
        pid = self.process.pid
        try:
            self.watchdog = subprocess.Popen(
                [sys.executable, "-c", WATCHDOG, str(pid), start_ticks(pid)], stdin=reading,
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                start_new_session=True)  # a Ctrl-C of the terminal reaches it not
        except BaseException:
            self.process.kill()
            os.close(self.lifeline)
            raise
        finally:
            os.close(reading)

    def stop(self, wait_s: float = 0.0) -> None:
        """Stop the server (and with it the watchdog), waiting ``wait_s`` for its
        shutdown."""
        self.process.terminate()
        try:
            self.process.wait(wait_s)
        except subprocess.TimeoutExpired:
            if wait_s:
                self.process.kill()
        os.close(self.lifeline)

    def wait_until_answering(self, timeout_s: float, quiet: bool) -> _Server:
        """This server once its health check answers, or another should this one exit with
        uvicorn's start-up failure code (at most :attr:`STARTS` in all)."""
        import httpx

        deadline, server = time.monotonic() + timeout_s, self
        with httpx.Client() as client:
            for start in range(self.STARTS):
                if start:
                    server = _Server(quiet)
                while time.monotonic() < deadline and server.process.poll() is None:
                    try:
                        if client.get(f"http://127.0.0.1:{server.port}/api/health"
                                      ).status_code == 200:
                            return server
                    except httpx.TransportError:
                        pass
                    time.sleep(0.05)
                server.stop()
                if server.process.returncode != 3:
                    break
        problem = (database_problem(server_log(), server.log_offset)
                   if server.log_offset is not None else None)
        if problem is not None:
            raise database_error(problem)
        where = f"; its log: {server_log()}" if quiet else ""
        code = server.process.returncode
        raise RuntimeError(f"the local Prefect server exited with code {code} before it answered"
                           + where if code is not None else
                           f"the local Prefect server did not answer within {timeout_s:g} s" + where)


def spawn_local_server(quiet: bool = True) -> None:
    """Start the server's process now, before this process imports Prefect: the two start
    at once (the server takes seconds to answer). :func:`start_local_server` adopts it, or
    stops it when Prefect's settings name a server of their own; the watchdog stops it when
    this process ends (bad input, before any flow). Only a head start: a server that cannot
    be started here is started, or reported, by :func:`start_local_server`."""
    global _spawned
    if _spawned is None and os.environ.get("PREFECT_API_URL") is None:
        with contextlib.suppress(Exception):
            _spawned = _Server(quiet)


def start_local_server(quiet: bool = True) -> int | None:
    """Start this process's Prefect server and its watchdog (or adopt the one
    :func:`spawn_local_server` started) unless Prefect's settings name a server; returns the
    server's pid when it started it. The server's address becomes this process's
    ``PREFECT_API_URL`` (and its children's)."""
    from prefect.context import refresh_global_settings_context
    from prefect.settings import get_current_settings

    global _spawned
    settings = get_current_settings()
    if settings.api.url or not settings.server.ephemeral.enabled:
        if _spawned is not None:
            _spawned.stop()
            _spawned = None
        return None
    server, _spawned = _spawned or _Server(quiet), None
    server = server.wait_until_answering(settings.server.ephemeral.startup_timeout_seconds,
                                         quiet)
    # Its lifeline stays open until then; stopped and waited for, the next command may start
    # at once.
    atexit.register(server.stop, wait_s=5.0)
    # As a server of one's own: Prefect's client then neither imports nor starts its
    # ephemeral server (seconds of loading that the command does not need). It serves no
    # UI: Prefect must not link to one.
    os.environ["PREFECT_API_URL"] = f"http://127.0.0.1:{server.port}/api"
    os.environ.setdefault("PREFECT_UI_URL", "")
    refresh_global_settings_context()
    return server.process.pid
