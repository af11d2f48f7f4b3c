"""What a run of the shared service may touch.

Whoever starts a run of a served flow (the Prefect UI or API) names its paths and its store
as parameters. On a worker those must not reach beyond what the deployment allows: else a
run could read any file the worker can (``video: /etc/shadow``, a config, a scan), write its
results wherever the worker may write, or make the worker send requests to any host (a
``store`` URL). The worker's environment fixes the limits:

``FACECAP_INPUT_ROOTS``
    The folders inputs may come from (videos, photo folders, scans, landmarks, configs,
    dataset folders), separated by ``:``.
``FACECAP_OUTPUT_ROOT``
    The folder results go to (``out`` of every flow).
``FACECAP_STORE``
    The artifact store; a run may repeat it as ``store`` but not name another.

Paths are resolved (``..`` and symbolic links followed) before they are compared, so a link
inside a root that points out of it is refused too; ``~`` is not expanded, as the flows do
not expand it when they open a path. A hard link has no target to follow, so an input file
with other hard links is refused. The limits apply to a run that comes from a deployment,
and to any flow run in a process whose environment sets
``FACECAP_INPUT_ROOTS`` or ``FACECAP_OUTPUT_ROOT`` (a worker); a deployment run without
them reads and writes nothing. The ``facecap`` command on one's own machine is not
limited: it marks its own flow runs as local (:data:`LOCAL_COMMAND`).
"""

from __future__ import annotations

import os
import stat
from contextvars import ContextVar
from dataclasses import dataclass
from pathlib import Path

from prefect.context import FlowRunContext

from facecap.tasks.runner import default_store_url
from facecap.tasks.store import open_store
from facecap.tasks.store.base import redact
from facecap_core.errors import InputError
from facecap_core.photos import list_photos
from facecap_core.settings import settings

LOCAL_COMMAND: ContextVar[bool] = ContextVar("facecap_local_command", default=False)
"""Set by the ``facecap`` command for the flows it runs in its own process: a user on their
own machine may name any path and store."""

INPUT_ROOTS_ENV = "FACECAP_INPUT_ROOTS"
OUTPUT_ROOT_ENV = "FACECAP_OUTPUT_ROOT"


def _from_deployment() -> bool:
    context = FlowRunContext.get()
    return bool(context and context.flow_run and context.flow_run.deployment_id)


@dataclass(frozen=True)
class ServicePolicy:
    """The roots and the store a served run is held to."""

    input_roots: tuple[Path, ...]
    output_root: Path | None
    store: str

    @classmethod
    def from_env(cls) -> ServicePolicy:
        configured = settings()
        output = configured.output_root
        return cls(tuple(root.resolve() for root in configured.input_roots),
                   output.resolve() if output else None, default_store_url())

    def input(self, path: str | os.PathLike | None, what: str) -> None:
        """Refuse an input outside every input root."""
        if path is None:
            return
        opened = _as_path(path, what)
        if not any(_contains(root, opened) for root in self.input_roots):
            allowed = ", ".join(map(str, self.input_roots)) or f"none ({INPUT_ROOTS_ENV} is unset)"
            raise InputError(f"the {what} {path} is outside the folders this service reads "
                             f"from ({allowed}); put it inside one of them")
        _check_single_link(opened, what)

    def output(self, path: str | os.PathLike, what: str = "output folder") -> None:
        """Refuse an output folder outside the output root."""
        if self.output_root is None or not _contains(self.output_root, _as_path(path, what)):
            allowed = self.output_root or f"none ({OUTPUT_ROOT_ENV} is unset)"
            raise InputError(f"the {what} {path} is outside the folder this service writes "
                             f"to ({allowed}); give a folder inside it")

    def check_store(self, store: str | None) -> str:
        """The deployment's store: a run may name it again, but no other (another URL,
        another scheme, another bucket)."""
        if store is not None and store != self.store:
            raise InputError(f"this service keeps its artifacts in its own store; leave "
                             f"'store' empty instead of {redact(repr(store))}")
        return self.store


def _as_path(path: object, what: str) -> Path:
    """``path`` as the flow opens it; what cannot name a file is refused in one line, not
    with the TypeError or ValueError of resolving it."""
    try:
        text = os.fspath(path)
    except TypeError:
        raise InputError(f"the {what} {path!r} is not a path; give the path as text") from None
    if isinstance(text, bytes):  # the flows take text: the bytes may name another file
        raise InputError(f"the {what} {path!r} is bytes, not a path; give the path as text")
    if "\0" in text:
        raise InputError(f"the {what} path {text!r} holds a NUL byte; give the path without it")
    return Path(text)


def _contains(root: Path, path: Path) -> bool:
    # No expanduser: the flow opens '~/x' as a folder named '~'; what is compared is what
    # is opened.
    resolved = path.resolve()
    return resolved == root or root in resolved.parents


def _check_single_link(path: Path, what: str) -> None:
    """Refuse an input file with other hard links: each is the file itself, and one may lie
    outside the input roots (where no path leads that could be compared)."""
    try:
        info = path.stat()
    except OSError:
        return  # missing or unreadable: the flow's own checks say so
    if stat.S_ISREG(info.st_mode) and info.st_nlink > 1:
        raise InputError(f"the {what} {path} has other hard links; copy it into the input "
                         "folder instead")


def service_policy() -> ServicePolicy | None:
    """The limits of this flow run, or None when it is not a served run (the ``facecap``
    command, or a process whose environment sets no limits, outside any deployment)."""
    if LOCAL_COMMAND.get():
        return None
    # Set at all (even to ':', which names no folder) makes a worker: it reads nothing.
    limited = {"input_roots", "output_root"} & settings().model_fields_set
    if not limited and not _from_deployment():
        return None
    return ServicePolicy.from_env()


def guard(out: str | os.PathLike, store: str | None,
          **inputs: str | os.PathLike | None) -> str:
    """Check a flow's parameters against the service's limits (when served); returns the
    store to use. ``inputs`` are named by what they are (``video``, ``config``, ...)."""

    policy = service_policy()
    if policy is None:
        store = store or default_store_url()
    else:
        for what, path in inputs.items():
            policy.input(path, what.replace("_", " "))
            if what == "video" and path is not None and Path(path).is_dir():
                for photo in list_photos(path):  # a photo folder: a linked photo is read too
                    policy.input(photo, "photo")
        policy.output(out)
        store = policy.check_store(store)
    open_store(store)  # an unsupported protocol or a file for a folder: refused here
    return store
