"""The one way facecap opens a file of its own trees: the store's locks and leases, the
results' records, run reports, evaluations and dataset summaries.

Those trees are anyone's to plant things in (a results folder is shared, a store may be a
team's folder): a link there would have facecap read or truncate whatever it leads to, a
FIFO would have it wait forever for a writer, and a JSON file nested 100,000 deep would
exhaust Python's parser (it recurses once per level). So :func:`open_regular` opens without
following a link (``O_NOFOLLOW``) and without waiting on a FIFO (``O_NONBLOCK``, cleared once
the file is open), and checks with ``fstat`` that it is a regular file before a byte is read
or written; :func:`read_json` reads such a file as JSON within a size and a nesting-depth
bound. The folders facecap makes for itself inside a tree that is not its own
(``FACECAP_HOME/logs``, a store's ``.tmp``) are made and opened by :func:`own_folder`, never
through a link, and a log in one is opened by :func:`open_log` or written whole by
:func:`write_new`. Each refusal is an :class:`OwnFileError`: one line naming the file, what
it is, and what to do.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import re
import stat
from itertools import accumulate

from facecap_core.errors import InputError

NAME_MAX = 255
"""The longest name of a file or folder, in bytes (Linux's and macOS's file systems): a
longer one is refused before the file system is asked (ENAMETOOLONG)."""
MAX_JSON_BYTES = 16 * 2**20
"""The most a JSON file of facecap's may hold: an evaluation of a dataset of 10,000
captures is some 4 MB; anything larger is not one of its files."""
MAX_JSON_DEPTH = 64
"""The deepest a JSON file of facecap's may nest (its reports nest five or six levels);
Python's parser recurses once per level and fails past about a thousand."""

_FLAGS = os.O_NOFOLLOW | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0)
_STRING = re.compile(rb'"[^"\\]*(?:\\.[^"\\]*)*"')
"""A JSON string (its brackets are text, not nesting)."""
_NOT_BRACKETS = bytes(sorted(set(range(256)) - set(b"[]{}")))
_STEP = [{ord("["): 1, ord("{"): 1, ord("]"): -1, ord("}"): -1}.get(b, 0) for b in range(256)]
"""What each byte does to the nesting depth."""


class OwnFileError(InputError):
    """A file of facecap's own trees is not what facecap keeps there (a link, a FIFO, a
    folder, a device; for JSON: too large, too deep, not JSON)."""

    def __init__(self, path: str | os.PathLike, problem: str, what: str = "file") -> None:
        self.path, self.problem = os.fspath(path), problem
        super().__init__(f"{self.path} is {problem}, where facecap keeps a {what} of its own; "
                         "move it out of the way or delete it, then run facecap again")


def _kind(mode: int) -> str:
    """What a file that is not a regular one is, in words."""
    for test, name in ((stat.S_ISLNK, "a link"), (stat.S_ISDIR, "a folder"),
                       (stat.S_ISFIFO, "a FIFO"), (stat.S_ISSOCK, "a socket"),
                       (stat.S_ISCHR, "a device"), (stat.S_ISBLK, "a device")):
        if test(mode):
            return name
    return "not a regular file"


def _open_checked(path: str | os.PathLike, flags: int, dir_fd: int | None,
                  shown: str | os.PathLike | None = None) -> int:
    """``os.open`` with ``flags`` never through a link nor waiting on a FIFO, kept only
    where ``fstat`` says it opened a regular file (an :class:`OwnFileError` naming
    ``shown``, or ``path``, otherwise)."""
    try:
        fd = os.open(path, flags | _FLAGS, 0o644, dir_fd=dir_fd)
    except OSError as exc:
        # ELOOP: the name is a link (O_NOFOLLOW); EISDIR: a folder opened to write; ENXIO:
        # a FIFO or a socket no one reads, opened to write; EEXIST: a link, with O_EXCL.
        if exc.errno not in (errno.ELOOP, errno.EISDIR, errno.ENXIO, errno.EOPNOTSUPP,
                             errno.EEXIST):
            raise
        try:
            found = os.stat(path, dir_fd=dir_fd, follow_symlinks=False)
        except FileNotFoundError:
            raise exc from None
        if exc.errno == errno.EEXIST and stat.S_ISREG(found.st_mode):
            raise
        raise OwnFileError(shown or path, _kind(found.st_mode)) from None
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            raise OwnFileError(shown or path, _kind(mode))
        fcntl.fcntl(fd, fcntl.F_SETFL, fcntl.fcntl(fd, fcntl.F_GETFL) & ~os.O_NONBLOCK)
    except BaseException:
        os.close(fd)
        raise
    return fd


def open_regular(path: str | os.PathLike, create: bool = False, dir_fd: int | None = None,
                 shown: str | os.PathLike | None = None) -> int:
    """A descriptor of the regular file at ``path`` (relative to ``dir_fd`` if given), open
    for reading, or with ``create`` for reading and writing, made if missing (never
    truncated: a lock's or a lease's content is not its point). A link, a FIFO, a folder or
    a device there is an :class:`OwnFileError` (naming ``shown``, or ``path``); other
    failures are the ``OSError`` they are (a missing file, a read-only folder)."""
    return _open_checked(path, os.O_RDWR | os.O_CREAT if create else os.O_RDONLY, dir_fd,
                         shown)


def open_folder(path: str | os.PathLike, dir_fd: int | None = None) -> int:
    """A descriptor of the folder at ``path``, never through a link (an
    :class:`OwnFileError` for a link or a file there)."""
    try:
        return os.open(path, os.O_RDONLY | os.O_DIRECTORY | _FLAGS, dir_fd=dir_fd)
    except OSError as exc:
        if exc.errno not in (errno.ELOOP, errno.ENOTDIR):
            raise
        found = os.stat(path, dir_fd=dir_fd, follow_symlinks=False)
        raise OwnFileError(path, _kind(found.st_mode) if not stat.S_ISREG(found.st_mode)
                           else "a file", what="folder") from None


def own_folder(path: str | os.PathLike) -> int:
    """A descriptor of facecap's own folder at ``path`` (``FACECAP_HOME/logs``, a store's
    ``.tmp``), made if missing (the folders above it too), never through a link: a link,
    a file or a FIFO planted under its name is an :class:`OwnFileError`, and nothing is
    made behind it. The folders above it are the user's to choose, links or not."""
    path = os.fspath(path)
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    with contextlib.suppress(FileExistsError):  # mkdir never follows a link: EEXIST
        os.mkdir(path)
    return open_folder(path)


def open_log(folder: str | os.PathLike, name: str, max_bytes: int | None = None) -> int:
    """A descriptor of the log ``folder/name``, open for appending (made if missing; started
    again from empty once past ``max_bytes``); ``folder`` is :func:`own_folder`'s. A link
    or a FIFO under either name is an :class:`OwnFileError`, nothing written behind it."""
    folder_fd = own_folder(folder)
    try:
        if max_bytes is not None:
            with contextlib.suppress(FileNotFoundError):
                found = os.stat(name, dir_fd=folder_fd, follow_symlinks=False)
                if stat.S_ISREG(found.st_mode) and found.st_size > max_bytes:
                    os.unlink(name, dir_fd=folder_fd)
        return _open_checked(name, os.O_WRONLY | os.O_APPEND | os.O_CREAT, folder_fd,
                             shown=os.path.join(folder, name))
    finally:
        os.close(folder_fd)


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view):]


def write_new(folder: str | os.PathLike, name: str, data: bytes) -> str:
    """Write ``data`` to the new file ``folder/name`` (``folder`` is :func:`own_folder`'s)
    and return its path; a file that could not be written whole is removed (a cut one
    would pass for the whole), and what kept it from being written raised."""
    folder_fd = own_folder(folder)
    try:
        fd = _open_checked(name, os.O_WRONLY | os.O_CREAT | os.O_EXCL, folder_fd,
                           shown=os.path.join(folder, name))
        try:
            _write_all(fd, data)
        except BaseException:
            with contextlib.suppress(OSError):
                os.unlink(name, dir_fd=folder_fd)
            raise
        finally:
            os.close(fd)
    finally:
        os.close(folder_fd)
    return os.path.join(folder, name)


def nesting_depth(data: bytes) -> int:
    """How deep the arrays and objects of a JSON text nest (brackets inside strings are
    not counted), found without parsing it."""
    brackets = _STRING.sub(b"", data).translate(None, _NOT_BRACKETS)
    return max(accumulate(map(_STEP.__getitem__, brackets)), default=0)


def read_json(path: str | os.PathLike, max_bytes: int = MAX_JSON_BYTES,
              dir_fd: int | None = None):
    """The JSON document of the regular file at ``path`` (see :func:`open_regular`); an
    :class:`OwnFileError` where it is larger than ``max_bytes``, nests deeper than
    :data:`MAX_JSON_DEPTH`, is not UTF-8 or not JSON."""
    with os.fdopen(open_regular(path, dir_fd=dir_fd), "rb") as source:
        data = source.read(max_bytes + 1)
    if len(data) > max_bytes:
        raise OwnFileError(path, f"larger than {max_bytes} bytes, more than facecap writes")
    # Fewer brackets than the bound cannot nest deeper than it: most files need no count.
    opened = data.count(b"[") + data.count(b"{")
    depth = nesting_depth(data) if opened > MAX_JSON_DEPTH else opened
    if depth > MAX_JSON_DEPTH:
        raise OwnFileError(path, f"JSON nested {depth} deep, deeper than facecap writes "
                                 f"(at most {MAX_JSON_DEPTH})")
    try:
        return json.loads(data.decode("utf-8"))
    except UnicodeDecodeError:
        raise OwnFileError(path, "not UTF-8 text") from None
    except ValueError as exc:
        raise OwnFileError(path, f"not JSON ({getattr(exc, 'msg', exc)})") from None
