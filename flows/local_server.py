"""The Prefect server a ``facecap`` command starts for itself when no ``PREFECT_API_URL`` is
set, held to the command's life.

Prefect starts that server as a child process (uvicorn) and stops it at exit; a command that
is killed (SIGKILL, the OOM killer) cannot stop it, and the server would live on. So the
command starts the server itself, first, and with it a watchdog: a tiny process that holds the
reading end of a pipe whose writing end only the command holds. When the command ends, however
it ends, the kernel closes that end, the watchdog reads end-of-file and stops the server.

The server's own output (its shutdown can print a traceback of a cancelled database query)
goes to ``$FACECAP_HOME/logs/server.log``, not to the command's console.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from facecap.tasks.scratch import start_ticks
from facecap_core.assets import facecap_home

# Imported where used: Prefect reads its settings when first imported; the command line sets them
# first (facecap/console.py).

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

_lifeline: int | None = None
"""The pipe's writing end: open for as long as this process lives."""
_watchdog: subprocess.Popen | None = None


def server_log() -> Path:
    folder = facecap_home() / "logs"
    folder.mkdir(parents=True, exist_ok=True)
    log = folder / LOG_NAME
    if log.is_file() and log.stat().st_size > MAX_LOG_BYTES:
        log.unlink(missing_ok=True)
    return log


def start_local_server(quiet: bool = True) -> int | None:
    """Start this process's Prefect server and its watchdog unless an API URL is set (or
    the server runs already); returns the server's pid when it started it."""
    from prefect.server.api.server import SubprocessASGIServer
    from prefect.settings import PREFECT_API_URL, PREFECT_SERVER_EPHEMERAL_ENABLED

    global _lifeline
    if PREFECT_API_URL.value() or not PREFECT_SERVER_EPHEMERAL_ENABLED.value():
        return None
    server = SubprocessASGIServer()
    if server.running:
        return None
    if quiet:
        with open(server_log(), "ab") as log:
            console = os.dup(2)
            try:  # the server inherits the standard error it is started with
                os.dup2(log.fileno(), 2)
                server.start()
            finally:
                os.dup2(console, 2)
                os.close(console)
    else:
        server.start()
    pid = server.server_process.pid
    reading, _lifeline = os.pipe()
    global _watchdog
    try:
        _watchdog = subprocess.Popen(
            [sys.executable, "-c", WATCHDOG, str(pid), start_ticks(pid)], stdin=reading,
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            start_new_session=True)  # a Ctrl-C of the terminal reaches it not
    finally:
        os.close(reading)
    return pid
