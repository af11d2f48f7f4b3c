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

import os
import socket
import subprocess
import sys
import time
from pathlib import Path

from facecap.tasks.scratch import start_ticks
from facecap_core.assets import facecap_home

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
_adopted: _Server | None = None
"""This process's server: its lifeline stays open for as long as this process lives."""


def server_log() -> Path:
    folder = facecap_home() / "logs"
    folder.mkdir(parents=True, exist_ok=True)
    log = folder / LOG_NAME
    if log.is_file() and log.stat().st_size > MAX_LOG_BYTES:
        log.unlink(missing_ok=True)
    return log


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _uvicorn(port: int, quiet: bool) -> subprocess.Popen:
    """Prefect's own ephemeral server (``SubprocessASGIServer``'s command and environment),
    on ``port``."""
    command = [sys.executable, "-m", "uvicorn", "--factory",
               "prefect.server.api.server:create_app", "--host", "127.0.0.1", "--port",
               str(port), "--log-level", "error", "--lifespan", "on"]
    env = {**os.environ, "PREFECT_UI_ENABLED": "0", "PREFECT__SERVER_EPHEMERAL": "1",
           "PREFECT__SERVER_FINAL": "1"}
    if "prefect.settings" in sys.modules:  # settings changed in this process, as Prefect does
        from prefect.settings import get_current_settings

        env.update(get_current_settings().to_environment_variables(exclude_unset=True))
    if not quiet:
        return subprocess.Popen(command, env=env)
    with open(server_log(), "ab") as log:
        return subprocess.Popen(command, env=env, stdout=log, stderr=log)


class _Server:
    """A server process of this command's, on a free port, with the watchdog that stops it
    when the command ends (the watchdog holds the reading end of ``lifeline``)."""

    def __init__(self, quiet: bool):
        self.port = _free_port()
        self.process = _uvicorn(self.port, quiet)
        reading, self.lifeline = os.pipe()
        pid = self.process.pid
        try:
            subprocess.Popen([sys.executable, "-c", WATCHDOG, str(pid), start_ticks(pid)],
                             stdin=reading, stdout=subprocess.DEVNULL,
                             stderr=subprocess.DEVNULL,
                             start_new_session=True)  # a Ctrl-C of the terminal reaches it not
        finally:
            os.close(reading)

    def stop(self) -> None:
        self.process.terminate()
        os.close(self.lifeline)

    def wait_until_answering(self, timeout_s: float, quiet: bool) -> _Server:
        """This server once its health check answers, or another on a new port should
        this one's be taken meanwhile (uvicorn's exit code 3)."""
        import httpx

        deadline = time.monotonic() + timeout_s
        with httpx.Client() as client:
            while time.monotonic() < deadline:
                code = self.process.poll()
                if code == 3:
                    self.stop()
                    return _Server(quiet).wait_until_answering(deadline - time.monotonic(),
                                                               quiet)
                if code is not None:
                    break
                try:
                    if client.get(f"http://127.0.0.1:{self.port}/api/health").status_code == 200:
                        return self
                except httpx.TransportError:
                    pass
                time.sleep(0.05)
        self.stop()
        where = f"; its log: {server_log()}" if quiet else ""
        raise RuntimeError(f"the local Prefect server did not start (exit code "
                           f"{self.process.poll()}) within {timeout_s:g} s{where}")


def spawn_local_server(quiet: bool = True) -> None:
    """Start the server's process now, before this process imports Prefect: the two start
    at once (the server takes seconds to answer). :func:`start_local_server` adopts it, or
    stops it when Prefect's settings name a server of their own; the watchdog stops it when
    this process ends (bad input, before any flow)."""
    global _spawned
    if _spawned is None and os.environ.get("PREFECT_API_URL") is None:
        _spawned = _Server(quiet)


def start_local_server(quiet: bool = True) -> int | None:
    """Start this process's Prefect server and its watchdog (or adopt the one
    :func:`spawn_local_server` started) unless Prefect's settings name a server; returns the
    server's pid when it started it. The server's address becomes this process's
    ``PREFECT_API_URL`` (and its children's)."""
    from prefect.context import refresh_global_settings_context
    from prefect.settings import get_current_settings

    global _spawned, _adopted
    settings = get_current_settings()
    if settings.api.url or not settings.server.ephemeral.enabled:
        if _spawned is not None:
            _spawned.stop()
            _spawned = None
        return None
    server, _spawned = _spawned or _Server(quiet), None
    _adopted = server.wait_until_answering(settings.server.ephemeral.startup_timeout_seconds,
                                           quiet)
    # As a server of one's own: Prefect's client then neither imports nor starts its
    # ephemeral server (seconds of loading that the command does not need).
    os.environ["PREFECT_API_URL"] = f"http://127.0.0.1:{_adopted.port}/api"
    refresh_global_settings_context()
    return _adopted.process.pid
