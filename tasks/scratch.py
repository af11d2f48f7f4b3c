"""Where a facecap process keeps its temporary files: one folder of its own under
``$FACECAP_HOME/scratch``, never the system's temp folder.

A capture's scratch holds faces (the pose stage's frames, COLMAP's database, depth maps in
the making), so it must stay inside what ``forget`` and ``prune`` look after. Each process
gets ``$FACECAP_HOME/scratch/<host>-<pid>-<start>/``: Python's :mod:`tempfile`, COLMAP's
glog files and the stages' work folders all go there; it is removed when the process exits,
and a folder whose process is gone (killed: its lock on the folder went with it) is removed
by the next ``facecap`` command that runs flows, ``forget`` or ``prune``
(:func:`remove_orphans`). The name says whose folder it is (host, pid, start), for people.
"""

from __future__ import annotations

import atexit
import fcntl
import os
import shutil
import socket
import sys
import tempfile
import threading
import time
from pathlib import Path

from facecap.tasks.own_files import OwnFileError, open_regular, own_folder
from facecap_core.assets import facecap_home

SCRATCH = "scratch"
ALIVE = ".alive"
GRACE_S = 60.0
"""A scratch folder younger than this is left alone: its process may not hold its lock yet."""

_folder: Path | None = None
_alive_lock = None
_making = threading.Lock()  # the tasks' threads may ask for the folder first at once


def start_ticks(pid: int) -> str:
    """When the process started (clock ticks since boot): a pid that was reused has other
    ticks. '0' where ``/proc`` is not there to say."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return "0"
    return stat.rsplit(")", 1)[1].split()[19]


def _host() -> str:
    return "".join(c if c.isalnum() or c in "-." else "_" for c in socket.gethostname())


def process_scratch() -> Path:
    """This process's scratch folder, created (and made the temp folder of Python and of
    COLMAP's glog) on first use, removed at exit. The process holds an exclusive lock on
    its ``.alive`` file for as long as it lives: that lock, not the folder's name, tells a
    live process's folder from a killed one's."""
    if _folder is not None and _folder.is_dir():
        return _folder
    with _making:
        # A second thread's lock on the same .alive would wait for the first's for ever.
        return _folder if _folder is not None and _folder.is_dir() else _make_scratch()


def _make_scratch() -> Path:
    global _folder, _alive_lock
    pid = os.getpid()
    folder = facecap_home() / SCRATCH / f"{_host()}-{pid}-{start_ticks(pid)}"
    # Never through a link planted under its name or as its .alive, never waiting on a FIFO.
    folder_fd = own_folder(folder)
    try:
        alive = open_regular(ALIVE, create=True, dir_fd=folder_fd, shown=folder / ALIVE)
    finally:
        os.close(folder_fd)
    fcntl.flock(alive, fcntl.LOCK_EX)  # held until the process ends
    if _alive_lock is not None:  # the folder was removed under the process: its old lock
        os.close(_alive_lock)
    _alive_lock = alive
    os.environ["TMPDIR"] = str(folder)  # child processes, and libraries that read it
    os.environ.setdefault("GLOG_log_dir", str(folder))  # read when glog first loads
    tempfile.tempdir = str(folder)
    if "pycolmap" in sys.modules:  # loaded already: its log files are opened at first use
        sys.modules["pycolmap"].logging.log_dir = str(folder)
    if _folder is None:
        atexit.register(shutil.rmtree, folder, True)
    _folder = folder
    return folder


def _abandoned(folder: Path) -> bool:
    """No process holds the folder's ``.alive`` lock, and it is older than a process needs
    to take it after making the folder."""
    try:
        if time.time() - folder.stat().st_mtime < GRACE_S:
            return False
        # A link, a FIFO or a folder planted as .alive: not a folder of facecap's, kept.
        alive = open_regular(folder / ALIVE, create=True)
    except (OSError, OwnFileError):
        return False
    try:
        fcntl.flock(alive, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        return False
    finally:
        os.close(alive)
    return True


def remove_orphans(home: Path | None = None) -> list[Path]:
    """Remove the scratch folders whose process is gone (killed); returns them."""
    root = (home or facecap_home()) / SCRATCH
    try:
        entries = sorted(p for p in root.iterdir() if p.is_dir() and not p.is_symlink())
    except OSError:
        return []
    removed = []
    for entry in entries:
        if _abandoned(entry):
            shutil.rmtree(entry, ignore_errors=True)
            removed.append(entry)
    return removed
