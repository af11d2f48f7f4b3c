"""How every stage task runs: content-addressed, locked, stored atomically, retried only
when the fault is transient.

A stage call is identified by its row in the stage graph (:mod:`facecap.tasks.graph`: name and
version), the keys of its input artifacts, its config section (JSON) and its params. Together
they make the artifact key. The store is the only cache: a stage whose artifact is stored is
never computed again, by any run on any worker, and :func:`run_stage` says whether it
computed.

A stage body writes its files into a scratch folder, which is then put into the store in one
atomic step.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import errno
import fcntl
import os
import resource
import shutil
import tempfile
import threading
import time
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path

from pydantic import BaseModel

from facecap.tasks.graph import INPUT_VERSION, Stage, config_data, stage_key
from facecap.tasks.own_files import OwnFileError, open_folder, open_regular
from facecap.tasks.scratch import process_scratch
from facecap.tasks.store import (
    ArtifactStore,
    CorruptArtifactError,
    StoreWriteError,
    input_key,
    open_store,
)
from facecap.tasks.store.base import redact
from facecap_core.assets import facecap_home
from facecap_core.errors import FacecapError, InputError
from facecap_core.photos import list_photos
from facecap_core.settings import settings

# Imported where used: botocore only with an S3 store; Prefect's task engine only once a stage
# runs (the command line's checks answer without it).


def default_store_url() -> str:
    """``$FACECAP_STORE`` (a folder or ``s3://bucket/prefix``), else ``$FACECAP_HOME/store``."""
    configured = settings()
    return configured.store or str(configured.home / "store")


def check_store(url: str) -> ArtifactStore:
    """The store a command line run uses: opened and reached once (a remote store: one
    request), so that a missing credential or a server that is down is reported before any
    work starts, and refused if its artifacts would not outlast the command."""
    store = open_store(url)
    if not store.outlives_process:  # memory:// is for tests, through the Python API
        raise InputError(f"the store {redact(url)} is held in this process's memory, so its "
                         "artifacts would vanish when facecap exits; give a folder or an "
                         "s3://bucket/prefix URL (--store or FACECAP_STORE)")
    try:
        store.exists("input-" + "0" * 32)
    except FacecapError:
        raise
    except Exception as exc:  # noqa: BLE001 - every way of not reaching it, told in one line
        raise store_unreachable(url, exc) from None
    return store


def store_unreachable(url: str, exc: BaseException) -> FacecapError:
    """One line for a store that cannot be reached or refuses access (its password hidden,
    also where the library's message quotes it)."""
    reason = redact(" ".join(str(exc).split())[:160]) or type(exc).__name__
    url = redact(url)
    if type(exc).__name__ in ("NoCredentialsError", "PartialCredentialsError"):
        return InputError(f"no credentials for the store {url} ({reason}); set "
                          "AWS_ACCESS_KEY_ID and AWS_SECRET_ACCESS_KEY")
    if isinstance(exc, PermissionError):
        return InputError(f"the store {url} refuses access ({reason}); check the credentials "
                          "and the bucket's policy")
    return FacecapError(f"the store {url} cannot be reached ({type(exc).__name__}: {reason}); "
                        "check its endpoint (AWS_ENDPOINT_URL_S3) and that it is up, then "
                        "retry")


def _lock_dir(store: ArtifactStore) -> Path:
    # A local store holds its own locks, so every process using it sees them; a remote store
    # is locked per machine (several machines may compute the same artifact at worst once
    # each, and the store's atomic put keeps the first).
    if store.url.startswith(("/", "file://")) or "://" not in store.url:
        root = Path(store.url.removeprefix("file://"))
        return root / ".locks"
    return facecap_home() / "locks"


def _lock_file(store: ArtifactStore, name: str):
    """The lock or lease file ``name`` of the store's lock folder, open for reading and
    writing and made if missing, never truncated; a link, a FIFO or a folder planted for
    the folder or the file is refused (:func:`facecap.tasks.own_files.open_regular`): a lock
    opened through a link would truncate or make what it leads to."""
    folder = _lock_dir(store)
    if folder.exists() and not folder.is_dir():  # mkdir would say EEXIST, which may pass
        raise NotADirectoryError(errno.ENOTDIR, os.strerror(errno.ENOTDIR), str(folder))
    folder.mkdir(parents=True, exist_ok=True)
    folder_fd = open_folder(folder)  # a link to a folder: refused
    try:
        return os.fdopen(open_regular(name, create=True, dir_fd=folder_fd), "r+b")
    except OwnFileError as exc:
        raise OwnFileError(folder / name, exc.problem) from None
    finally:
        os.close(folder_fd)


@contextmanager
def key_lock(store: ArtifactStore, key: str):
    """Exclusive lock on one artifact key: a second run on the same capture waits here, then
    finds the artifact committed and computes nothing."""
    try:
        handle = _lock_file(store, f"{key}.lock")
    except OSError as exc:  # a read-only store: the lasting errno keeps it from retries
        raise StoreWriteError(f"cannot lock artifact {key} in store {store.shown_url} "
                              f"({exc.strerror or type(exc).__name__}); check that the "
                              "location is writable, then retry") from exc
    with handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


_LEASES: ContextVar[dict | None] = ContextVar("facecap_leases", default=None)
"""The lease files a run holds open, by key (:func:`run_leases`)."""
UNLEASABLE = frozenset({errno.EROFS, errno.EACCES, errno.EPERM})
"""A store folder no lease can be written in: nothing can prune it either."""


def _lease_file(store: ArtifactStore, key: str):
    return _lock_file(store, f"{key}.lease")


@contextmanager
def run_leases():
    """A run's leases: every artifact the run reads or makes (:func:`lease`) is held until
    the block ends, or the process does (a killed run's leases go with it), so that
    ``store prune`` and ``forget`` leave them alone (:func:`unleased`)."""
    held: dict = {}
    token = _LEASES.set(held)
    try:
        yield
    finally:
        _LEASES.reset(token)
        for handle in held.values():
            handle.close()


def lease(store: ArtifactStore, key: str) -> None:
    """Hold a shared lease on ``key`` for the rest of the run (nothing outside a run)."""
    held = _LEASES.get()
    if held is None or key in held:
        return
    try:
        handle = _lease_file(store, key)
    except OSError as exc:
        if exc.errno in UNLEASABLE:
            return
        raise StoreWriteError(f"cannot take a lease on artifact {key} in store "
                              f"{store.shown_url} ({exc.strerror}); check that the location "
                              "is writable, then retry") from exc
    try:  # waits only while a prune removes this very key (a fraction of a second)
        fcntl.flock(handle, fcntl.LOCK_SH)
    except BaseException:
        handle.close()
        raise
    held[key] = handle


@contextmanager
def unleased(store: ArtifactStore, key: str):
    """Yields whether no run holds ``key``; while the block runs no run can take it (a
    run that wants it waits, then finds it gone and makes it again)."""
    try:
        handle = _lease_file(store, key)
    except OSError:
        yield True
        return
    with handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            yield False
            return
        try:
            yield True
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


SCRATCH_FULL = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS})
"""A stage's scratch folder (under FACECAP_HOME) that cannot take its files: the user's
disk to free, not a bug."""


def _scratch() -> Path:
    folder = process_scratch() / "work"
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def run_stage(store_url: str, stage: Stage, inputs: dict[str, str], config: BaseModel | None,
              params: dict | None = None) -> tuple[str, bool]:
    """Make the stage's artifact unless it is stored; returns ``(key, computed)``.
    ``config`` is the stage's settings, validated where the run's config was read."""
    store = open_store(store_url)
    key = stage_key(stage, inputs, config, params)
    for held in [*inputs.values(), key]:
        lease(store, held)
    if store.exists(key):
        return key, False
    with key_lock(store, key):
        if store.exists(key):  # another run made it while we waited
            return key, False
        folders = {name: store.get(k) for name, k in inputs.items()}
        work = Path(tempfile.mkdtemp(prefix=f"{stage.name}-", dir=_scratch()))
        try:
            wall, cpu = time.perf_counter(), time.process_time()
            try:
                stage.run(folders, work, config, params or {})
            except OSError as exc:
                if exc.errno not in SCRATCH_FULL:
                    raise
                fix = ("make it writable" if exc.errno == errno.EROFS
                       else "free space there")
                raise StoreWriteError(
                    f"the {stage.name} stage could not write its files into FACECAP_HOME "
                    f"({facecap_home()}: {exc.strerror}); {fix}, or set FACECAP_HOME to "
                    "another folder, and run again") from exc
            meta = {"seconds": round(time.perf_counter() - wall, 3),
                    "cpu_seconds": round(time.process_time() - cpu, 3),
                    "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
                                         / 1024, 1)}
            files = {p.relative_to(work).as_posix(): p
                     for p in sorted(work.rglob("*")) if p.is_file()}
            if not files:
                raise FacecapError(f"stage {stage.name} wrote no files")
            stage.check_outputs(files, params)
            inject_fault(stage.name, work)
            store.put(key, files, stage=stage.name, inputs=inputs, config=config_data(config, stage.key_neutral),
                      version=stage.full_version(), meta={**meta, **(params or {})})
        finally:
            shutil.rmtree(work, ignore_errors=True)
            release_freed_memory()
    return key, True


def _libc_malloc_trim():
    """glibc's ``malloc_trim``, or None (another C library, another system)."""
    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim
    except (OSError, AttributeError):
        return None


_MALLOC_TRIM = _libc_malloc_trim()


def release_freed_memory() -> None:
    """Give the heap's free pages back to the system. The stages run one after another in
    one process, and glibc keeps what a stage's arrays freed: 330 MB still resident after the
    fusion stage of a 640x360 capture, held by the process between stages
    (docs/benchmarks.md). Freed memory only: no array changes."""
    if _MALLOC_TRIM is not None:
        _MALLOC_TRIM(0)


_FAULT_COUNTS: dict[str, int] = {}
_FAULT_LOCK = threading.Lock()


def inject_fault(stage: str, work: Path) -> None:
    """Fault injection for the robustness tests: ``FACECAP_FAULT=STAGE[:N[:HOW]]`` makes the
    N-th computation (default 1) of STAGE in this process fail after its files are written
    and before they are committed, the moment that loses the most work. HOW is ``exit``
    (default: the process dies at once with code 137, as if killed by SIGKILL, no cleanup),
    ``interrupt`` (KeyboardInterrupt, as Ctrl-C) or ``oserror`` (a transient I/O error that
    the task's retries absorb)."""
    spec = settings().fault  # validated: STAGE[:N[:HOW]]
    if not spec:
        return
    parts = spec.split(":")
    if parts[0] != stage:
        return
    count = int(parts[1]) if len(parts) > 1 else 1
    how = parts[2] if len(parts) > 2 else "exit"
    with _FAULT_LOCK:
        _FAULT_COUNTS[stage] = _FAULT_COUNTS.get(stage, 0) + 1
        if _FAULT_COUNTS[stage] != count:
            return
    if how == "interrupt":
        raise KeyboardInterrupt(f"fault injected in stage {stage}")
    if how == "oserror":
        raise OSError(errno.EIO, f"fault injected in stage {stage}")
    os.write(2, f"facecap fault: {stage} killed before its commit; its files are in {work}\n"
             .encode())
    os._exit(137)


def ingest(store_url: str, path: str | os.PathLike, name: str) -> str:
    """Put a raw input (video, scan: one file stored as ``name``; a capture's photo folder:
    its photos stored under ``name/``) into the store under its content key."""
    path = Path(path)
    if path.is_dir():
        files = {f"{name}/{photo.name}": photo for photo in list_photos(path)}
    elif path.is_file():
        files = {name: path}
    else:
        raise InputError(f"input file not found: {path}")
    store = open_store(store_url)
    key = input_key(path)
    lease(store, key)
    if not store.exists(key):
        with key_lock(store, key):
            inject_fault("input", path)
            store.put(key, files, stage="input", inputs={}, config=None,
                      version=INPUT_VERSION, meta={"source": path.name})
    return key


# -- retries ---------------------------------------------------------------------------------

TRANSIENT = (StoreWriteError, CorruptArtifactError, ConnectionError, TimeoutError)
"""Faults worth retrying: the store or the network failed, not the input."""


def network_errors() -> tuple[type[BaseException], ...]:
    # s3fs surfaces an unreachable endpoint as botocore's own exceptions, which are neither
    # OSError nor Python's ConnectionError.
    try:
        from botocore.exceptions import ConnectionError as BotoConnectionError
        from botocore.exceptions import HTTPClientError
    except ImportError:
        return ()
    return (BotoConnectionError, HTTPClientError)


LASTING_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM,
                            errno.ENOTDIR, errno.EISDIR})
"""A full disk, a read-only or forbidden location, a file where a folder must be (or the
reverse): retrying seconds later cannot help."""


def is_transient(exc: BaseException) -> bool:
    """Bad input is never retried; store, network and OS faults are, unless the disk is
    full or the location is read-only or forbidden."""
    from prefect.task_engine import TaskRunTimeoutError

    if isinstance(exc, TaskRunTimeoutError):  # over its time limit: it would be again
        return False
    cause = exc.__cause__ if isinstance(exc, StoreWriteError) else exc
    if isinstance(cause, OSError) and cause.errno in LASTING_ERRNOS:
        return False
    if isinstance(exc, TRANSIENT + network_errors()):
        return True
    if isinstance(exc, FacecapError):
        return False
    return isinstance(exc, OSError)


def retry_condition(task, task_run, state) -> bool:
    """Prefect ``retry_condition_fn``: retry only transient faults."""
    try:
        state.result()
    except BaseException as exc:  # the task's own exception, re-raised by result()
        return is_transient(exc)
    return False
