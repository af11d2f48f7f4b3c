"""The one way facecap writes into a user's output folder.

A results folder is a place other things live in too: the user's photos (``--out`` the photo
folder), links someone planted there (a served run's output folder is shared), the store
(``--out`` inside it), files of the user's own that happen to have a result's name. So every
result goes through :class:`ResultWriter`, which

* writes each file under a fresh temporary name in its final folder and renames it into
  place only when every file of the batch is written (``os.replace``): a full disk or a kill
  leaves the earlier results whole, never a half-written set;
* walks the folders below ``--out`` through file descriptors that refuse links
  (``O_NOFOLLOW``), and creates files with ``O_EXCL``: nothing is written through a link,
  and a link in the folder is replaced by the file rather than followed;
* refuses to replace a file that is one of the run's inputs (same inode: the same directory
  entry or a hard link to it);
* removes a result an earlier run wrote and this run did not make only when the folder's
  record (:data:`RECORD_NAME`) says facecap wrote that very content.

:func:`check_output_place` refuses an output folder inside the artifact store or
facecap's own folders, or equal to an input folder, before anything runs.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import re
import secrets
import stat
import time
from collections.abc import Iterable
from pathlib import Path, PurePosixPath

from facecap.tasks.own_files import OwnFileError, open_regular, read_json
from facecap.tasks.store.remote import cache_root
from facecap_core.errors import FacecapError, InputError
from facecap_core.settings import settings

RECORD_NAME = ".facecap-results.json"
"""What facecap last wrote into the folder (name -> sha256): the only files it removes."""

_DIR_FLAGS = os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | getattr(os, "O_CLOEXEC", 0)
_NEW_FILE_FLAGS = (os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW
                   | getattr(os, "O_CLOEXEC", 0))
_DISK_FULL = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG}
MAX_RECORD_BYTES = 16 * 2**20
"""A record larger than this is not facecap's: it is read as empty (nothing is removed)."""
_TEMPORARY = re.compile(r"^\..+\.[0-9a-f]{12}\.part$")
"""The name a result is staged under (:meth:`ResultWriter.add`)."""
ABANDONED_S = 3600
"""A staged file this old was left by a writer that was killed (a batch takes seconds)."""


class OutputWriteError(FacecapError):
    """The output folder cannot take the results (full, read-only, gone)."""


def _relative(name: str) -> PurePosixPath:
    path = PurePosixPath(name)
    if path.is_absolute() or not path.parts or any(p in ("", ".", "..") for p in path.parts):
        raise ValueError(f"a result's name must be a plain relative path, not {name!r}")
    return path


def _inode(found: os.stat_result) -> tuple[int, int]:
    return found.st_dev, found.st_ino


def input_inodes(paths: Iterable[str | os.PathLike | None]) -> dict[tuple[int, int], str]:
    """(device, inode) of every existing input file (each photo of a photo folder)."""
    found = {}
    for path in paths:
        if path is None:
            continue
        path = Path(path)
        files = sorted(p for p in path.iterdir() if p.is_file()) if path.is_dir() else [path]
        for file in files:
            try:
                found[_inode(file.stat())] = str(file)
            except OSError:
                continue
    return found


class ResultWriter:
    """A batch of results for one output folder: :meth:`add` each, then :meth:`commit`
    (or leave the ``with`` block by an exception: nothing is replaced)."""

    def __init__(self, folder: str | os.PathLike, inputs: Iterable[str | os.PathLike | None] = ()):
        self.folder = Path(folder)
        self._inputs = input_inodes(inputs)
        self._staged: list[tuple[PurePosixPath, str, str]] = []  # (name, temporary, sha256)
        self._fds: dict[PurePosixPath, int] = {}

    # ------------------------------------------------------------------ folders

    def _dir_fd(self, parent: PurePosixPath, create: bool = True) -> int:
        """An open descriptor of ``folder/parent``, created as needed (``create``), never
        through a link."""
        if parent in self._fds:
            return self._fds[parent]
        if parent == PurePosixPath("."):
            self.folder.mkdir(parents=True, exist_ok=True)
            fd = os.open(self.folder, os.O_RDONLY | os.O_DIRECTORY | getattr(os, "O_CLOEXEC", 0))
        else:
            above = self._dir_fd(parent.parent, create)
            try:
                if create:
                    os.mkdir(parent.name, dir_fd=above)
            except FileExistsError:
                pass
            try:
                fd = os.open(parent.name, _DIR_FLAGS, dir_fd=above)
            except OSError as exc:
                if exc.errno in (errno.ELOOP, errno.ENOTDIR):
                    raise InputError(f"{self.folder / parent} is a link or a file where facecap "
                                     "writes a folder of results; remove it or give another "
                                     "--out") from None
                raise
        self._fds[parent] = fd
        _remove_abandoned(fd)
        return fd

    # ------------------------------------------------------------------ writing

    def add(self, name: str, data: bytes | None = None, source: str | os.PathLike | None = None
            ) -> None:
        """Stage the result ``name`` (relative to the folder) from ``data`` or a file."""
        path = _relative(name)
        if (data is None) == (source is None):
            raise ValueError("give a result's data or its source file, not both or neither")
        try:
            if source is not None:
                data = Path(source).read_bytes()
            fd = self._dir_fd(path.parent)
            self._check_target(fd, path)
            temporary = f".{path.name}.{secrets.token_hex(6)}.part"
            handle = os.open(temporary, _NEW_FILE_FLAGS, 0o644, dir_fd=fd)
            self._staged.append((path, temporary, hashlib.sha256(data).hexdigest()))
            with os.fdopen(handle, "wb") as target:
                target.write(data)
        except BaseException as exc:  # nothing of a batch that failed is left behind
            self.abort()
            if isinstance(exc, OSError):
                raise self._write_error(exc) from None
            raise

    def _check_target(self, fd: int, path: PurePosixPath) -> None:
        """What the result will replace: never an input, never a folder."""
        try:
            existing = os.stat(path.name, dir_fd=fd, follow_symlinks=False)
        except FileNotFoundError:
            return
        if stat.S_ISDIR(existing.st_mode):
            raise InputError(f"{self.folder / path} is a folder where facecap writes a result "
                             "file; move it away or give another --out")
        if _inode(existing) in self._inputs:
            raise InputError(f"the result {self.folder / path} would replace the input "
                             f"{self._inputs[_inode(existing)]}; give another --out")

    def _write_error(self, exc: OSError) -> FacecapError:
        reason = exc.strerror or type(exc).__name__
        what = ("free space there" if exc.errno in _DISK_FULL
                else "choose a writable folder (--out)")
        return OutputWriteError(f"could not write the results into {self.folder} ({reason}); "
                                f"{what} and run again")

    def commit(self, stale: Iterable[str] = ()) -> None:
        """Rename every staged file into place; then remove those of ``stale`` that the
        folder's record says an earlier run wrote (and that still hold what it wrote). A
        folder without a record (results of a version before the record) loses every plain
        file of ``stale`` that is not an input, as it did then."""
        record = self._read_record()
        for path, temporary, _ in self._staged:
            fd = self._fds[path.parent]
            try:
                os.replace(temporary, path.name, src_dir_fd=fd, dst_dir_fd=fd)
            except OSError as exc:  # changed since it was checked: what is left is dropped
                self.abort()
                raise self._write_error(exc) from None
        written = {str(path) for path, _, _ in self._staged}
        for name in sorted(set(stale) - written):
            if record is None or name in record:
                self._remove_if_ours(_relative(name), None if record is None else record[name])
        record = {} if record is None else {k: v for k, v in record.items() if k not in stale}
        record.update({str(path): digest for path, _, digest in self._staged})
        self._staged = []
        self._write_record(record)
        self.close()

    def _remove_if_ours(self, path: PurePosixPath, digest: str | None) -> None:
        """Remove an earlier result: the file the record names with these bytes, or with no
        record at all (``digest`` None) a plain file that is not an input."""
        try:
            fd = self._dir_fd(path.parent, create=False)
            found = os.stat(path.name, dir_fd=fd, follow_symlinks=False)
            if not stat.S_ISREG(found.st_mode) or _inode(found) in self._inputs:
                return
            if digest is None or _sha256_at(fd, path.name) == digest:
                os.unlink(path.name, dir_fd=fd)
        except (OSError, InputError):
            pass

    def _read_record(self) -> dict[str, str] | None:
        """The folder's record; None where it has none (a folder an earlier version wrote,
        or a new one)."""
        return _read_record_at(self._dir_fd(PurePosixPath(".")))

    def _write_record(self, record: dict[str, str]) -> None:
        fd = self._dir_fd(PurePosixPath("."))
        temporary = f".{RECORD_NAME}.{secrets.token_hex(6)}.part"
        try:
            handle = os.open(temporary, _NEW_FILE_FLAGS, 0o644, dir_fd=fd)
            with os.fdopen(handle, "w") as target:
                json.dump(record, target, indent=1, sort_keys=True)
            os.replace(temporary, RECORD_NAME, src_dir_fd=fd, dst_dir_fd=fd)
        except OSError:  # the results are in place; without a record nothing is removed later
            _unlink_quietly(temporary, fd)

    def abort(self) -> None:
        """Remove the staged files; the folder keeps what it held."""
        for path, temporary, _ in self._staged:
            _unlink_quietly(temporary, self._fds.get(path.parent))
        self._staged = []
        self.close()

    def close(self) -> None:
        for fd in self._fds.values():
            os.close(fd)
        self._fds = {}

    def __enter__(self) -> ResultWriter:
        return self

    def __exit__(self, kind, exc, tb) -> None:
        if self._staged:
            self.abort()
        self.close()


def _read_record_at(fd: int) -> dict[str, str] | None:
    """The record in the folder open as ``fd``; None where it has none, empty where it
    cannot be read or is not facecap's (nothing it names is then removed)."""
    try:
        # A link, a FIFO or a JSON bomb planted there is no record: read as empty.
        record = read_json(RECORD_NAME, MAX_RECORD_BYTES, dir_fd=fd)
    except FileNotFoundError:
        return None
    except (OSError, OwnFileError):
        return {}
    if not isinstance(record, dict):
        return {}
    return {k: v for k, v in record.items() if isinstance(k, str) and isinstance(v, str)}


def recorded_files(folder: str | os.PathLike) -> dict[PurePosixPath, str | None]:
    """Every file under ``folder`` (never through a link) that a results record there names,
    relative to ``folder``, with the sha256 the record gives; the records themselves with
    None. Only what the records name: what facecap can prove it wrote."""
    found: dict[PurePosixPath, str | None] = {}
    for root, _, files, fd in os.fwalk(folder, follow_symlinks=False):
        if RECORD_NAME not in files:
            continue
        here = PurePosixPath(Path(root).relative_to(folder).as_posix())
        for name, digest in (_read_record_at(fd) or {}).items():
            try:
                found[here / _relative(name)] = digest
            except ValueError:
                continue  # not a name facecap writes: the record is not trusted for it
        found[here / RECORD_NAME] = None
    return found


def _ours_at(fd: int, name: PurePosixPath, recorded: dict[PurePosixPath, str | None]) -> bool:
    """Whether ``name`` (in the folder open as ``fd``) is a plain file facecap wrote and
    nobody changed since: a record names it with its very content (or it is a record, or a
    file a killed writer staged: one left for ``ABANDONED_S``, so a running writer's is
    not taken)."""
    staged = name not in recorded and _TEMPORARY.match(name.name)
    if name not in recorded and not staged:
        return False
    try:
        found = os.stat(name.name, dir_fd=fd, follow_symlinks=False)
        if not stat.S_ISREG(found.st_mode):
            return False
        if staged and time.time() - found.st_mtime <= ABANDONED_S:
            return False
        digest = recorded.get(name)
        return digest is None or _sha256_at(fd, name.name) == digest
    except (OSError, OwnFileError):  # replaced by a link or a FIFO since its stat
        return False


def remove_results(folder: str | os.PathLike, dry_run: bool = False
                   ) -> tuple[list[Path], list[Path]]:
    """Remove what facecap wrote under ``folder`` (a subject's results folder): the files
    its records name that still hold what was recorded, the records, what a killed writer
    staged, and the folders that leaves empty, ``folder`` too. Nothing else: a file of the
    user's, a file changed since, a link (never followed) stay. Returns the files removed
    (with ``dry_run``: that would be) and the entries kept."""
    folder = Path(folder)
    recorded = recorded_files(folder)
    removed: list[Path] = []
    kept: list[Path] = []
    holding: set[PurePosixPath] = set()  # folders that keep something

    def keep(name: PurePosixPath) -> None:
        kept.append(folder / name)
        holding.update(name.parents)

    for root, dirs, files, fd in os.fwalk(folder, topdown=False, follow_symlinks=False):
        here = PurePosixPath(Path(root).relative_to(folder).as_posix())
        for file in sorted(files):
            name = here / file
            if not _ours_at(fd, name, recorded):
                keep(name)
                continue
            removed.append(folder / name)
            if not dry_run:
                try:
                    os.unlink(file, dir_fd=fd)
                except FileNotFoundError:
                    pass
        for sub in sorted(dirs):
            name = here / sub
            if name in holding:
                continue
            if os.path.islink(folder / name):
                keep(name)
                continue
            if not dry_run:
                try:
                    os.rmdir(sub, dir_fd=fd)
                except OSError:  # something appeared in it meanwhile: it stays
                    keep(name)
    if PurePosixPath(".") not in holding and not dry_run:
        try:
            os.rmdir(folder)
        except OSError:
            kept.append(folder)
    return removed, sorted(kept)


def _sha256_at(fd: int, name: str) -> str:
    handle = open_regular(name, dir_fd=fd)
    digest = hashlib.sha256()
    with os.fdopen(handle, "rb") as source:
        for chunk in iter(lambda: source.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def _remove_abandoned(fd: int) -> None:
    """Remove the staged files a killed writer left in the folder (they may hold a mesh)."""

    try:
        names = os.listdir(fd)
    except OSError:
        return
    for name in names:
        if not _TEMPORARY.match(name):
            continue
        try:
            found = os.stat(name, dir_fd=fd, follow_symlinks=False)
            if stat.S_ISREG(found.st_mode) and time.time() - found.st_mtime > ABANDONED_S:
                os.unlink(name, dir_fd=fd)
        except OSError:
            continue


def _unlink_quietly(name: str, fd: int | None) -> None:
    if fd is None:
        return
    try:
        os.unlink(name, dir_fd=fd)
    except OSError:
        pass


def write_results(folder: str | os.PathLike, files: dict[str, bytes],
                  inputs: Iterable[str | os.PathLike | None] = ()) -> None:
    """Write a few results into ``folder`` as one batch (see :class:`ResultWriter`)."""
    with ResultWriter(folder, inputs) as writer:
        for name, data in files.items():
            writer.add(name, data)
        writer.commit()


def _inside(path: Path, folder: Path) -> bool:
    return path == folder or folder in path.parents


def check_result_names(out: str | os.PathLike, names: Iterable[str],
                       inputs: Iterable[str | os.PathLike | None] = (),
                       option: str = "--out") -> None:
    """Refuse, before any work, an output folder where one of the result ``names`` (relative
    paths) is a folder, or the very file of an input (a hard link to it; a link there is
    replaced, not followed): the writer would refuse it only once the work is done, and the
    work would be lost. ``option`` is what the user gave the place as."""
    out = Path(out)
    sources = []
    for source in inputs:
        try:
            sources.append((source, os.stat(source)))
        except (OSError, TypeError):
            continue
    for name in names:
        try:
            found = os.lstat(out / name)
        except OSError:
            continue
        if stat.S_ISDIR(found.st_mode):
            raise InputError(f"{out / name} is a folder where facecap writes a result; remove "
                             f"it or give another {option}")
        for source, source_stat in sources:
            if os.path.samestat(found, source_stat):
                raise InputError(f"the result {out / name} would replace the input {source}; "
                                 f"give another {option}")


def check_results_folder(out: str | os.PathLike, store: str | None, names: Iterable[str],
                         inputs: Iterable[str | os.PathLike | None] = (),
                         option: str = "--out") -> None:
    """Refuse, before any work, a folder that results ``names`` cannot be written into:
    one :func:`check_output_place` refuses, a file, or one where a result's name is a
    folder or an input (:func:`check_result_names`)."""
    inputs = list(inputs)
    check_output_place(out, store, inputs, option)
    if Path(out).exists() and not Path(out).is_dir():
        raise InputError(f"the output folder {out} is a file; give the path of a folder "
                         f"({option})")
    check_result_names(out, names, inputs, option)


def check_output_place(out: str | os.PathLike, store: str | None,
                       inputs: Iterable[str | os.PathLike | None] = (),
                       option: str = "--out") -> None:
    """Refuse an output folder that lies in the artifact store or in facecap's own folders
    (results would replace committed files), or that is an input folder (a photo folder);
    ``option`` is what the user gave it as."""

    try:
        target = Path(out).resolve()
    except RuntimeError:  # pathlib's word for a link that leads back to itself
        raise InputError(f"the output folder {out} is a link that leads back to itself; give "
                         f"the path of a folder ({option})") from None
    except OSError as exc:
        raise InputError(f"the output folder {out} cannot be looked up ({exc.strerror}); give "
                         f"the path of a folder ({option})") from None
    home = settings().home.resolve()
    own = [home / "store", home / "store-cache", cache_root().resolve(), home / "work",
           home / "scratch", home / "assets", home / "locks", home / "logs"]
    if store and ("://" not in store or store.startswith("file://")):
        folder = Path(store.removeprefix("file://")).expanduser()
        try:
            own.append(folder.resolve())
        except (RuntimeError, OSError):  # a link loop: the store says what it is
            # Could be at the top: the store's package is loaded already (tasks.store.remote,
            # above).
            from facecap.tasks.store import open_store

            open_store(store)
            raise InputError(f"the store {store} cannot be looked up; give the path of a "
                             "folder (--store or FACECAP_STORE)") from None
    for folder in own:
        if _inside(target, folder):
            raise InputError(f"the output folder {out} lies inside {folder}, which facecap "
                             "keeps for itself (the artifact store or its own files); give "
                             f"another {option}")
    for path in inputs:
        if path is None or not Path(path).is_dir():
            continue
        folder = Path(path).resolve()
        if folder == target:
            raise InputError(f"the output folder {out} is the input folder {path}, whose files "
                             f"results could replace; give another {option}")
        if folder in target.parents:  # a dataset's next scan would take results for captures
            raise InputError(f"the output folder {out} lies inside the input folder {path}; "
                             f"results never go among the inputs: give a folder outside it "
                             f"({option})")
