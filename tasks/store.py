"""Content-addressed artifact store for facecap's meshes, depth maps and cameras.

An artifact is a small set of files produced by one pipeline stage. Its key is a content
address: a hash of the stage name, the stage version, the keys of the stage's inputs and
its config (see :func:`artifact_key`). The same inputs always give the same key, so a
stage whose key is already in the store does not need to run again.

Layout under the store root (a local folder or any fsspec URL)::

    <root>/artifacts/<key>/manifest.json    commit marker: checksums, inputs, config, meta
    <root>/artifacts/<key>/<file name>      local backend: the artifact's files (sub-folders
                                            allowed)
    <root>/artifacts/<key>/<writer>/<file name>   remote backends: the files, in the folder of
                                            the writer that committed them (``w-<uuid4>``,
                                            named by the manifest's ``folder``)
    <root>/.tmp/<uuid4>/                    local backend only: writes in progress

``manifest.json`` is written last and is the commit marker: an artifact exists only once
its manifest does, and readers trust nothing in a folder without one. On the local backend
the whole artifact is first written to ``.tmp/<uuid4>/`` and then renamed into place in one
atomic step. Object stores such as S3 have no atomic rename, so there each writer uploads
the files into a folder of its own, then commits the manifest create-only (S3's
``If-None-Match: *``): of two writers of one key (two hosts), the first manifest wins, the
other writer removes its own folder and returns the winner's manifest. A writer that dies
midway leaves only its own folder, which no manifest names: it is never read and never
touches a committed artifact.

Backends
    * A local folder, the default: a plain path (``/data/store``, ``relative/dir``) or a
      ``file://`` URL.
    * Any fsspec URL: ``s3://bucket/prefix`` for S3 or MinIO, ``memory://name`` in tests.

Credentials are never passed to this module. For S3 and MinIO they come from the
environment only: s3fs reads ``AWS_ACCESS_KEY_ID`` and ``AWS_SECRET_ACCESS_KEY``, and
fsspec reads ``FSSPEC_S3_ENDPOINT_URL`` for a MinIO endpoint.

Remote artifacts are downloaded for local use into a cache,
``$FACECAP_HOME/store-cache/<key>/`` (``FACECAP_HOME`` defaults to ``~/.cache/facecap``).

To force an artifact to be recomputed, delete its folder ``<root>/artifacts/<key>`` (or
call :meth:`ArtifactStore.delete`).
"""

from __future__ import annotations

import errno
import functools
import hashlib
import json
import os
import re
import shutil
import uuid
from collections.abc import Callable, Iterator, Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, BinaryIO

import fsspec
from fsspec.core import url_to_fs
from fsspec.implementations.local import LocalFileSystem
from pydantic import BaseModel, Field, ValidationError

from facecap_core.assets import facecap_home
from facecap_core.errors import FacecapError, InputError

__all__ = [
    "ArtifactNotFoundError",
    "ArtifactStore",
    "CorruptArtifactError",
    "FileEntry",
    "FileSource",
    "Manifest",
    "StoreWriteError",
    "artifact_key",
    "file_digest",
    "input_key",
]

MANIFEST_NAME = "manifest.json"
CHUNK_SIZE = 1024 * 1024  # 1 MiB: keeps memory flat when hashing or copying large videos
KEY_DIGEST_LENGTH = 32  # 128 bits of sha256 is plenty to avoid collisions, and keeps paths short

_STAGE_PATTERN = re.compile(r"[a-z0-9_]+")
_WRITER_PATTERN = re.compile(r"w-[0-9a-f]{32}")
_KEY_PATTERN = re.compile(rf"([a-z0-9_]+)-[0-9a-f]{{{KEY_DIGEST_LENGTH}}}")

# What put() accepts for one file: its bytes, a path to copy, or an open binary file.
FileSource = bytes | bytearray | memoryview | str | os.PathLike[str] | BinaryIO


class ArtifactNotFoundError(FacecapError):
    """The store has no committed artifact (or no such file in an artifact) for a key."""


class CorruptArtifactError(FacecapError):
    """A stored file is missing or does not match the checksum or size in its manifest."""


class StoreWriteError(FacecapError):
    """Writing to the store (or to the local cache of a remote store) failed."""


class FileEntry(BaseModel):
    """Checksum and size of one file of an artifact."""

    sha256: str
    size: int


class Manifest(BaseModel):
    """Everything known about one committed artifact; stored as ``manifest.json``."""

    key: str
    stage: str
    version: str
    inputs: dict[str, str]
    config: dict[str, Any] | None
    files: dict[str, FileEntry]
    created: str  # ISO-8601 UTC; a string so that a manifest round-trips through JSON unchanged
    meta: dict[str, Any] = Field(default_factory=dict)
    folder: str | None = None
    """Remote stores: the writer's sub-folder of the artifact folder that holds the files;
    None where the files lie in the artifact folder itself (the local backend)."""


# --------------------------------------------------------------------------- keys


def artifact_key(
    stage: str,
    inputs: Mapping[str, str],
    config: BaseModel | Mapping[str, Any] | None,
    version: str,
    params: Mapping[str, Any] | None = None,
) -> str:
    """Content address of the artifact a stage makes from ``inputs`` with ``config``.

    The key is ``f"{stage}-{digest[:32]}"`` where ``digest`` is the sha256 of the canonical
    JSON (sorted keys, no whitespace) of ``{stage, version, inputs, config}`` and, for a
    stage run once per item (one depth map per keyframe), its ``params``. A pydantic config
    and a mapping holding the same values give the same key.
    """
    _check_stage(stage)
    description = {
        "stage": stage,
        "version": version,
        "inputs": dict(inputs),
        "config": _config_as_json(config),
    }
    if params:
        description["params"] = json.loads(_canonical_json(dict(params)))
    digest = hashlib.sha256(_canonical_json(description)).hexdigest()
    return f"{stage}-{digest[:KEY_DIGEST_LENGTH]}"


def file_digest(path: str | os.PathLike[str]) -> str:
    """sha256 (hex) of a file's bytes; an unreadable file is the caller's input error."""
    try:
        with open(path, "rb") as source:
            return hashlib.file_digest(source, "sha256").hexdigest()
    except OSError as exc:
        raise InputError(f"cannot read {os.fspath(path)}: {_reason(exc)}") from exc


def input_key(path: str | os.PathLike[str]) -> str:
    """Key of a raw input file (such as a video) or a folder of photos, derived from its
    content alone (a folder's: its photos' names and bytes)."""
    if os.path.isdir(path):
        from facecap_core.photos import list_photos

        digest = hashlib.sha256(b"photos")
        for photo in list_photos(path):
            digest.update(photo.name.encode("utf-8") + b"\0")
            digest.update(input_key(photo).encode("ascii") + b"\0")
        return f"input-{digest.hexdigest()[:KEY_DIGEST_LENGTH]}"
    try:
        stat = os.stat(path)
    except OSError:  # reading it raises the store's own error for the path
        return f"input-{file_digest(path)[:KEY_DIGEST_LENGTH]}"
    return _input_key(os.path.realpath(path), stat.st_ino, stat.st_size, stat.st_mtime_ns)


@functools.lru_cache(maxsize=256)
def _input_key(path: str, inode: int, size: int, mtime_ns: int) -> str:
    # A capture flow asks for its video's key several times; a long video takes seconds to
    # hash. A rewritten file has a new mtime (or inode), hence a new cache entry.
    return f"input-{file_digest(path)[:KEY_DIGEST_LENGTH]}"


def _canonical_json(value: Any) -> bytes:
    # Sorted keys and no whitespace make equal values hash equally whatever their order.
    return json.dumps(value, sort_keys=True, separators=(",", ":")).encode("utf-8")


def _config_as_json(config: BaseModel | Mapping[str, Any] | None) -> dict[str, Any] | None:
    """Config as plain JSON data: what is hashed into the key and stored in the manifest."""
    if config is None:
        return None
    if isinstance(config, BaseModel):
        return config.model_dump(mode="json")
    # A JSON round trip turns tuples into lists etc., so the manifest holds exactly what
    # was hashed.
    return json.loads(_canonical_json(dict(config)))


def _check_stage(stage: str) -> None:
    if not isinstance(stage, str) or not _STAGE_PATTERN.fullmatch(stage):
        raise InputError(
            f"invalid stage name {stage!r}: use only lowercase letters, digits and '_'"
        )


def _check_key(key: str) -> None:
    # Keys become folder names, so anything else could escape the store root.
    if not isinstance(key, str) or not _KEY_PATTERN.fullmatch(key):
        raise InputError(
            f"invalid artifact key {key!r}: expected '<stage>-<{KEY_DIGEST_LENGTH} hex digits>'"
        )


def _check_file_names(names: list[str]) -> None:
    """File names must be relative POSIX paths that stay inside the artifact folder."""
    for name in names:
        parts = name.split("/") if isinstance(name, str) else []
        if (not parts or "\\" in name or "\0" in name
                or any(part in ("", ".", "..") for part in parts)):
            raise InputError(
                f"invalid artifact file name {name!r}: use a relative POSIX path "
                "without '..', '.', empty parts or a leading '/'"
            )
        if name == MANIFEST_NAME:
            raise InputError(f"invalid artifact file name {name!r}: the name is reserved")
    # "a" and "a/b" cannot both exist: "a" would have to be a file and a folder.
    folders = {
        name.rsplit("/", depth)[0] for name in names for depth in range(1, name.count("/") + 1)
    }
    clashes = sorted(folders.intersection(names))
    if clashes:
        raise InputError(f"artifact file name {clashes[0]!r} is also used as a folder name")


# --------------------------------------------------------------------------- byte streams


def _raw_chunks(source: BinaryIO) -> Iterator[bytes]:
    """Chunks of an open binary file until it is exhausted."""
    return iter(lambda: source.read(CHUNK_SIZE), b"")


def _input_chunks(source: BinaryIO, label: str) -> Iterator[bytes]:
    """Chunks of a caller's file: failing to read it is an input error, not a store error."""
    try:
        yield from _raw_chunks(source)
    except OSError as exc:
        raise InputError(f"cannot read {label}: {_reason(exc)}") from exc


def _path_chunks(path: str | os.PathLike[str], label: str) -> Iterator[bytes]:
    """Chunks of the caller's file at ``path``."""
    try:
        source = open(path, "rb")
    except OSError as exc:
        raise InputError(f"cannot read {label}: {_reason(exc)}") from exc
    with source:
        yield from _input_chunks(source, label)


def _source_chunks(name: str, source: FileSource) -> Iterator[bytes]:
    """Chunks of any accepted file source: bytes, a path or an open binary file."""
    if isinstance(source, (bytes, bytearray, memoryview)):
        yield bytes(source)
    elif isinstance(source, (str, os.PathLike)):
        yield from _path_chunks(source, f"{os.fspath(source)} (source of {name!r})")
    elif hasattr(source, "read"):
        yield from _input_chunks(source, f"the source of {name!r}")
    else:
        raise InputError(
            f"unsupported source for {name!r}: {type(source).__name__} "
            "(give bytes, a path or an open binary file)"
        )


def _copy_hashing(chunks: Iterator[bytes], target: BinaryIO) -> FileEntry:
    """Write chunks to ``target`` and return the checksum and size of what was written."""
    digest = hashlib.sha256()
    size = 0
    for chunk in chunks:
        target.write(chunk)
        digest.update(chunk)
        size += len(chunk)
    return FileEntry(sha256=digest.hexdigest(), size=size)


def _hash_stream(source: BinaryIO) -> FileEntry:
    """Checksum and size of an open binary file."""
    digest = hashlib.sha256()
    size = 0
    for chunk in _raw_chunks(source):
        digest.update(chunk)
        size += len(chunk)
    return FileEntry(sha256=digest.hexdigest(), size=size)


def _mismatch(actual: FileEntry, expected: FileEntry) -> str | None:
    """How a file differs from its manifest entry, or None if it matches."""
    if actual.size != expected.size:
        return f"has {actual.size} bytes but the manifest says {expected.size}"
    if actual.sha256 != expected.sha256:
        return f"has sha256 {actual.sha256[:12]}… but the manifest says {expected.sha256[:12]}…"
    return None


# --------------------------------------------------------------------------- local helpers


def _write_durably(path: Path, data: bytes) -> None:
    with open(path, "wb") as target:
        target.write(data)
        target.flush()
        os.fsync(target.fileno())


def _fsync_dir(path: Path) -> None:
    # Makes a rename inside the folder survive a power cut; not possible on every platform.
    if not hasattr(os, "O_DIRECTORY"):
        return
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _rename_if_absent(source: Path, destination: Path) -> bool:
    """Atomically rename a folder; False if ``destination`` already exists (someone won)."""
    try:
        os.rename(source, destination)
    except OSError as exc:
        if exc.errno in (errno.EEXIST, errno.ENOTEMPTY):
            return False
        raise
    return True


def _remove_tree(path: Path) -> None:
    """Remove a folder, first renaming it aside so no reader ever sees it half removed."""
    trash = path.parent / f".trash-{uuid.uuid4().hex}"
    try:
        os.rename(path, trash)
    except FileNotFoundError:
        return
    shutil.rmtree(trash, ignore_errors=True)


def _reason(exc: BaseException) -> str:
    """An exception as a single line, for one-line user messages."""
    text = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
    return " ".join(text.split()) or type(exc).__name__


def _cache_root() -> Path:
    """Local folder for copies of remote artifacts: ``$FACECAP_HOME/store-cache``."""
    return facecap_home() / "store-cache"


def _manifest_bytes(manifest: Manifest) -> bytes:
    return manifest.model_dump_json(indent=2).encode("utf-8")


def _now_utc() -> str:
    return datetime.now(UTC).isoformat(timespec="milliseconds")


# --------------------------------------------------------------------------- the store


class ArtifactStore:
    """Content-addressed artifacts in a local folder or under any fsspec URL.

    See the module docstring for the layout and the commit protocol.
    """

    def __init__(self, url: str | os.PathLike[str]) -> None:
        """Use the store at ``url``: a local path, or a ``file://``, ``s3://``, ``memory://`` URL.

        Nothing is created until the first put.
        """
        text = os.fspath(url)
        if "://" not in text:
            text = os.path.expanduser(text)
        fs, root = url_to_fs(text)
        self._fs: fsspec.AbstractFileSystem = fs
        self._root: str = root.rstrip("/") or "/"
        self._is_local = isinstance(fs, LocalFileSystem)

    @property
    def url(self) -> str:
        """Where the store lives: an absolute folder path, or a URL for remote stores."""
        return self._root if self._is_local else self._fs.unstrip_protocol(self._root)

    @property
    def fs(self) -> fsspec.AbstractFileSystem:
        """The fsspec filesystem holding the store."""
        return self._fs

    def __repr__(self) -> str:
        return f"ArtifactStore({self.url!r})"

    # ----------------------------------------------------------------- paths

    def _artifact_path(self, key: str) -> str:
        return f"{self._root}/artifacts/{key}"

    def _file_path(self, key: str, name: str, folder: str | None = None) -> str:
        """Where a file lies: in the artifact folder, or in a writer's folder inside it."""
        base = self._artifact_path(key)
        return f"{base}/{folder}/{name}" if folder else f"{base}/{name}"

    def _stored_path(self, manifest: Manifest, name: str) -> str:
        return self._file_path(manifest.key, name, manifest.folder)

    def _manifest_path(self, key: str) -> str:
        return self._file_path(key, MANIFEST_NAME)

    def _location(self, key: str) -> str:
        """The artifact's folder as a user can delete it: a path, or a URL if remote."""
        path = self._artifact_path(key)
        return path if self._is_local else self._fs.unstrip_protocol(path)

    # ----------------------------------------------------------------- reading

    def exists(self, key: str) -> bool:
        """True only if the artifact is committed, i.e. its manifest exists."""
        _check_key(key)
        return self._fs.exists(self._manifest_path(key))

    def manifest(self, key: str) -> Manifest:
        """The committed manifest of ``key``; ArtifactNotFoundError if there is none."""
        _check_key(key)
        try:
            data = self._fs.cat_file(self._manifest_path(key))
        except FileNotFoundError:
            raise ArtifactNotFoundError(f"artifact {key} not found in store {self.url}") from None
        try:
            manifest = Manifest.model_validate_json(data)
        except ValidationError as exc:
            raise self._corrupt(key, MANIFEST_NAME, "is not a valid manifest") from exc
        if manifest.key != key:
            raise self._corrupt(key, MANIFEST_NAME, f"belongs to artifact {manifest.key}")
        if manifest.folder is not None and not _WRITER_PATTERN.fullmatch(manifest.folder):
            # The folder becomes part of a path: nothing but a writer's name may be there.
            raise self._corrupt(key, MANIFEST_NAME, f"names an invalid folder {manifest.folder!r}")
        for name in manifest.files:
            try:
                # File names become paths in the local cache: none may lead out of it.
                _check_file_names([name])
            except InputError:
                raise self._corrupt(key, MANIFEST_NAME, f"names a file outside its artifact "
                                                        f"({name!r})") from None
        return manifest

    def read_bytes(self, key: str, name: str, verify: bool = True) -> bytes:
        """The bytes of one file of an artifact, checked against the manifest if ``verify``."""
        manifest = self.manifest(key)
        entry = self._entry(manifest, name)
        try:
            data = self._fs.cat_file(self._stored_path(manifest, name))
        except FileNotFoundError:
            raise self._corrupt(key, name, "is missing") from None
        if verify:
            actual = FileEntry(sha256=hashlib.sha256(data).hexdigest(), size=len(data))
            problem = _mismatch(actual, entry)
            if problem:
                raise self._corrupt(key, name, problem)
        return data

    def verify(self, key: str) -> None:
        """Check every file of an artifact against its manifest; CorruptArtifactError if not."""
        manifest = self.manifest(key)
        for name, entry in manifest.files.items():
            problem = self._stored_file_problem(manifest, name, entry)
            if problem:
                raise self._corrupt(key, name, problem)

    def get(self, key: str, verify: bool = True) -> Path:
        """A local folder holding the artifact's files (and its ``manifest.json``).

        Local stores return the artifact folder itself: treat it as read-only. Remote stores
        download it once into ``$FACECAP_HOME/store-cache/<key>/`` and reuse that copy while
        it matches the manifest. With ``verify`` every file's checksum and size are checked.
        """
        if self._is_local:
            if verify:
                self.verify(key)
            else:
                self.manifest(key)  # raises if the artifact is not committed
            return Path(self._artifact_path(key))
        return self._get_remote(key, verify)

    def keys(self, stage: str | None = None) -> list[str]:
        """Keys of the committed artifacts, optionally of one stage only, sorted."""
        if stage is not None:
            _check_stage(stage)
        # Globbing for manifests lists committed artifacts only, in one listing on S3.
        pattern = f"{self._root}/artifacts/*/{MANIFEST_NAME}"
        found = (path.rstrip("/").split("/")[-2] for path in self._fs.glob(pattern))
        return sorted(
            key
            for key in found
            if _KEY_PATTERN.fullmatch(key) and (stage is None or key.startswith(f"{stage}-"))
        )

    # ----------------------------------------------------------------- writing

    def put(
        self,
        key: str,
        files: Mapping[str, FileSource],
        *,
        stage: str,
        inputs: Mapping[str, str],
        config: BaseModel | Mapping[str, Any] | None,
        version: str,
        meta: Mapping[str, Any] | None = None,
    ) -> Manifest:
        """Store ``files`` as artifact ``key`` and return its manifest.

        ``files`` maps relative POSIX names (sub-folders allowed) to bytes, a path to copy,
        or an open binary file. If ``key`` is already committed nothing is written and the
        existing manifest is returned. A failed put leaves no manifest, so the artifact does
        not exist; OS errors while writing become StoreWriteError.
        """
        _check_key(key)
        _check_stage(stage)
        if not key.startswith(f"{stage}-"):
            # keys(stage) selects by this prefix, so it must agree with the manifest.
            raise InputError(f"artifact key {key} does not belong to stage {stage!r}")
        names = list(files)
        _check_file_names(names)
        if self.exists(key):
            return self.manifest(key)

        def make_manifest(entries: dict[str, FileEntry]) -> Manifest:
            return Manifest(
                key=key,
                stage=stage,
                version=version,
                inputs=dict(inputs),
                config=_config_as_json(config),
                files=entries,
                created=_now_utc(),
                meta=dict(meta or {}),
            )

        if self._is_local:
            return self._put_local(key, files, make_manifest)
        return self._put_remote(key, files, make_manifest)

    def delete(self, key: str) -> None:
        """Remove an artifact so that it will be recomputed.

        An interrupted delete never leaves a trusted half artifact: a local folder is renamed
        away in one atomic step, and on remote stores the manifest is removed first. Also
        drops the local cached copy of a remote artifact.
        """
        _check_key(key)
        folder = self._artifact_path(key)
        if not self._fs.exists(folder):
            raise ArtifactNotFoundError(f"artifact {key} not found in store {self.url}")
        if self._is_local:
            # One atomic rename takes the manifest and all files away at once.
            _remove_tree(Path(folder))
            return
        if self._fs.exists(self._manifest_path(key)):
            self._fs.rm_file(self._manifest_path(key))
        self._fs.rm(folder, recursive=True)
        _remove_tree(_cache_root() / key)

    # ----------------------------------------------------------------- internals

    def _entry(self, manifest: Manifest, name: str) -> FileEntry:
        entry = manifest.files.get(name)
        if entry is None:
            raise ArtifactNotFoundError(
                f"artifact {manifest.key} in store {self.url} has no file {name!r} "
                f"(it has: {', '.join(sorted(manifest.files)) or 'no files'})"
            )
        return entry

    def _stored_file_problem(self, manifest: Manifest, name: str,
                             entry: FileEntry) -> str | None:
        """How a stored file differs from its manifest entry, or None if it matches."""
        try:
            with self._fs.open(self._stored_path(manifest, name), "rb") as stored:
                return _mismatch(_hash_stream(stored), entry)
        except FileNotFoundError:
            return "is missing"

    def _corrupt(self, key: str, name: str, problem: str) -> CorruptArtifactError:
        return CorruptArtifactError(
            f"artifact {key} is corrupt: file {name!r} {problem}; "
            f"delete {self._location(key)} so that it is recomputed"
        )

    def _write_error(self, key: str, where: str, exc: OSError) -> StoreWriteError:
        return StoreWriteError(
            f"could not write artifact {key} to {where}: {_reason(exc)}; "
            "check that the location is writable and has free space, then retry"
        )

    def _put_local(
        self,
        key: str,
        files: Mapping[str, FileSource],
        make_manifest: Callable[[dict[str, FileEntry]], Manifest],
    ) -> Manifest:
        """Write into ``.tmp/<uuid4>/`` and rename the whole folder into place at once."""
        root = Path(self._root)
        temp_folder = root / ".tmp" / uuid.uuid4().hex
        final_folder = Path(self._artifact_path(key))
        try:
            try:
                temp_folder.mkdir(parents=True)
                entries = {
                    name: self._write_local_file(temp_folder / name, _source_chunks(name, source))
                    for name, source in files.items()
                }
                manifest = make_manifest(entries)
                _write_durably(temp_folder / MANIFEST_NAME, _manifest_bytes(manifest))
                _fsync_dir(temp_folder)
                final_folder.parent.mkdir(parents=True, exist_ok=True)
                committed = _rename_if_absent(temp_folder, final_folder)
                if committed:
                    _fsync_dir(final_folder.parent)
            except OSError as exc:
                raise self._write_error(key, self.url, exc) from exc
        finally:
            # After a successful rename this folder is gone; otherwise it is debris.
            shutil.rmtree(temp_folder, ignore_errors=True)
        if committed:
            return manifest
        if self.exists(key):
            return self.manifest(key)  # a concurrent writer committed the same key first
        raise StoreWriteError(
            f"could not write artifact {key}: {final_folder} exists but has no {MANIFEST_NAME} "
            "(left by an interrupted operation); delete that folder and retry"
        )

    @staticmethod
    def _write_local_file(path: Path, chunks: Iterator[bytes]) -> FileEntry:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "wb") as target:
            entry = _copy_hashing(chunks, target)
            target.flush()
            os.fsync(target.fileno())
        return entry

    def _put_remote(
        self,
        key: str,
        files: Mapping[str, FileSource],
        make_manifest: Callable[[dict[str, FileEntry]], Manifest],
    ) -> Manifest:
        """Upload the files into a folder of this writer's own, then commit the manifest
        create-only; a writer that loses the race removes its folder and returns the
        winner's manifest."""
        folder = f"w-{uuid.uuid4().hex}"
        try:
            try:
                entries = {}
                for name, source in files.items():
                    with self._fs.open(self._file_path(key, name, folder), "wb") as target:
                        entries[name] = _copy_hashing(_source_chunks(name, source), target)
                manifest = make_manifest(entries).model_copy(update={"folder": folder})
                committed = self._commit_manifest(key, manifest)
            except OSError as exc:
                raise self._write_error(key, self.url, exc) from exc
        except BaseException:
            self._remove_writer_folder(key, folder)
            raise
        if committed is not manifest:
            self._remove_writer_folder(key, folder)
        return committed

    def _commit_manifest(self, key: str, manifest: Manifest) -> Manifest:
        """Write the manifest unless one exists; returns the manifest that is committed."""
        path = self._manifest_path(key)
        try:
            self._fs.pipe_file(path, _manifest_bytes(manifest), mode="create")
            return manifest
        except OSError as exc:
            # FileExistsError where the backend says so; S3 servers that report a failed
            # If-None-Match differently land here too. Either way: who holds the key now?
            self._fs.invalidate_cache(path)
            try:
                existing = self.manifest(key)
            except ArtifactNotFoundError:
                raise exc from None  # no manifest: the write itself failed
            if existing.folder == manifest.folder:
                return manifest  # ours: the request succeeded, its answer was lost and retried
            return existing

    def _remove_writer_folder(self, key: str, folder: str) -> None:
        """Best-effort removal of one writer's uploads (never another writer's files)."""
        try:
            self._fs.rm(f"{self._artifact_path(key)}/{folder}", recursive=True)
        except Exception:  # noqa: BLE001 - cleanup must not hide the original error
            pass

    def _get_remote(self, key: str, verify: bool) -> Path:
        """Local cached copy of a remote artifact, downloaded if absent or outdated."""
        manifest = self.manifest(key)
        cached = _cache_root() / key
        if cached.is_dir():
            if self._cached_copy_matches(cached, manifest, verify):
                return cached
            _remove_tree(cached)  # stale or damaged: the remote copy is the truth
        return self._download(key, manifest, cached, verify)

    @staticmethod
    def _cached_copy_matches(folder: Path, manifest: Manifest, verify: bool) -> bool:
        try:
            cached_manifest = Manifest.model_validate_json((folder / MANIFEST_NAME).read_bytes())
            if cached_manifest != manifest:
                return False
            if not verify:
                return True
            for name, entry in manifest.files.items():
                with open(folder / name, "rb") as cached_file:
                    if _mismatch(_hash_stream(cached_file), entry):
                        return False
        except (OSError, ValidationError):
            return False
        return True

    def _download(self, key: str, manifest: Manifest, destination: Path, verify: bool) -> Path:
        """Download into a temporary folder, check it, then rename it into the cache."""
        temp_folder = destination.parent / ".tmp" / uuid.uuid4().hex
        try:
            try:
                temp_folder.mkdir(parents=True)
                for name, entry in manifest.files.items():
                    actual = self._download_file(manifest, name, temp_folder / name)
                    problem = _mismatch(actual, entry) if verify else None
                    if problem:
                        raise self._corrupt(key, name, problem)
                _write_durably(temp_folder / MANIFEST_NAME, _manifest_bytes(manifest))
                # If another process finished the same download first, its copy is as good.
                _rename_if_absent(temp_folder, destination)
            except OSError as exc:
                raise self._write_error(key, f"the local cache {destination}", exc) from exc
        finally:
            shutil.rmtree(temp_folder, ignore_errors=True)
        return destination

    def _download_file(self, manifest: Manifest, name: str, target_path: Path) -> FileEntry:
        key = manifest.key
        try:
            remote = self._fs.open(self._stored_path(manifest, name), "rb")
        except FileNotFoundError:
            raise self._corrupt(key, name, "is missing") from None
        with remote:
            return self._write_local_file(target_path, _raw_chunks(remote))
