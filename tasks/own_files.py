"""The one way facecap opens a file of its own trees: the store's locks and leases, the
results' records, run reports, evaluations and dataset summaries.

Those trees are anyone's to plant things in (a results folder is shared, a store may be a
team's folder): a link there would have facecap read or truncate whatever it leads to, a
FIFO would have it wait forever for a writer, and a JSON file nested 100,000 deep would
exhaust Python's parser (it recurses once per level). So :func:`open_regular` opens without
following a link (``O_NOFOLLOW``) and without waiting on a FIFO (``O_NONBLOCK``, cleared once
the file is open), and checks with ``fstat`` that it is a regular file before a byte is read
or written; :func:`read_json` reads such a file as JSON within a size and a nesting-depth
bound. Each refusal is an :class:`OwnFileError`: one line naming the file, what it is, and
what to do.
"""

from __future__ import annotations

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


def open_regular(path: str | os.PathLike, create: bool = False, dir_fd: int | None = None
                 ) -> int:
    """A descriptor of the regular file at ``path`` (relative to ``dir_fd`` if given), open
    for reading, or with ``create`` for reading and writing, made if missing (never
    truncated: a lock's or a lease's content is not its point). A link, a FIFO, a folder or
    a device there is an :class:`OwnFileError`; other failures are the ``OSError`` they
    are (a missing file, a read-only folder)."""
    flags = _FLAGS | (os.O_RDWR | os.O_CREAT if create else os.O_RDONLY)
    try:
        fd = os.open(path, flags, 0o644, dir_fd=dir_fd)
    except OSError as exc:
        # ELOOP: the name is a link (O_NOFOLLOW); EISDIR: a folder opened to write; ENXIO:
        # a FIFO or a socket no one reads, opened to write.
        if exc.errno not in (errno.ELOOP, errno.EISDIR, errno.ENXIO, errno.EOPNOTSUPP):
            raise
        found = os.stat(path, dir_fd=dir_fd, follow_symlinks=False)
        raise OwnFileError(path, _kind(found.st_mode)) from None
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            raise OwnFileError(path, _kind(mode))
        fcntl.fcntl(fd, fcntl.F_SETFL, fcntl.fcntl(fd, fcntl.F_GETFL) & ~os.O_NONBLOCK)
    except BaseException:
        os.close(fd)
        raise
    return fd


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
