"""What every backend of the store shares: the manifest, the errors, hashing while copying,
and durable local writes."""

from __future__ import annotations

import errno
import hashlib
import os
import shutil
import uuid
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, BinaryIO

from pydantic import BaseModel, Field, field_validator

from facecap_core.errors import FacecapError, InputError

MANIFEST_NAME = "manifest.json"
CHUNK_SIZE = 1024 * 1024  # 1 MiB: keeps memory flat when hashing or copying large videos

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

    @field_validator("created")
    @classmethod
    def _check_created(cls, value: str) -> str:
        # Pruning compares it with the time now: a manifest it cannot date is a damaged one
        # (CorruptArtifactError where it is read), not one to remove as old.
        try:
            zone = datetime.fromisoformat(value).utcoffset()
        except ValueError:
            raise ValueError(f"created {value!r} is not an ISO-8601 time") from None
        if zone is None:
            raise ValueError(f"created {value!r} has no time zone")
        return value

    @property
    def created_at(self) -> datetime:
        """When the artifact was committed (``created``, with its time zone)."""
        return datetime.fromisoformat(self.created)


def manifest_bytes(manifest: Manifest) -> bytes:
    return manifest.model_dump_json(indent=2).encode("utf-8")


def now_utc() -> str:
    return datetime.now(UTC).isoformat(timespec="milliseconds")


# --------------------------------------------------------------------------- byte streams


def raw_chunks(source: BinaryIO) -> Iterator[bytes]:
    """Chunks of an open binary file until it is exhausted."""
    return iter(lambda: source.read(CHUNK_SIZE), b"")


def _input_chunks(source: BinaryIO, label: str) -> Iterator[bytes]:
    """Chunks of a caller's file: failing to read it is an input error, not a store error."""
    try:
        yield from raw_chunks(source)
    except OSError as exc:
        raise InputError(f"cannot read {label}: {reason(exc)}") from exc


def _path_chunks(path: str | os.PathLike[str], label: str) -> Iterator[bytes]:
    """Chunks of the caller's file at ``path``."""
    try:
        source = open(path, "rb")
    except OSError as exc:
        raise InputError(f"cannot read {label}: {reason(exc)}") from exc
    with source:
        yield from _input_chunks(source, label)


def source_chunks(name: str, source: FileSource) -> Iterator[bytes]:
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


def copy_hashing(chunks: Iterator[bytes], target: BinaryIO) -> FileEntry:
    """Write chunks to ``target`` and return the checksum and size of what was written."""
    digest = hashlib.sha256()
    size = 0
    for chunk in chunks:
        target.write(chunk)
        digest.update(chunk)
        size += len(chunk)
    return FileEntry(sha256=digest.hexdigest(), size=size)


def hash_stream(source: BinaryIO) -> FileEntry:
    """Checksum and size of an open binary file."""
    digest = hashlib.sha256()
    size = 0
    for chunk in raw_chunks(source):
        digest.update(chunk)
        size += len(chunk)
    return FileEntry(sha256=digest.hexdigest(), size=size)


def mismatch(actual: FileEntry, expected: FileEntry) -> str | None:
    """How a file differs from its manifest entry, or None if it matches."""
    if actual.size != expected.size:
        return f"has {actual.size} bytes but the manifest says {expected.size}"
    if actual.sha256 != expected.sha256:
        return f"has sha256 {actual.sha256[:12]}… but the manifest says {expected.sha256[:12]}…"
    return None


# --------------------------------------------------------------------------- local files


def write_local_file(path: Path, chunks: Iterator[bytes]) -> FileEntry:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as target:
        entry = copy_hashing(chunks, target)
        target.flush()
        os.fsync(target.fileno())
    return entry


def write_durably(path: Path, data: bytes) -> None:
    with open(path, "wb") as target:
        target.write(data)
        target.flush()
        os.fsync(target.fileno())


def fsync_dir(path: Path) -> None:
    # Makes a rename inside the folder survive a power cut; not possible on every platform.
    if not hasattr(os, "O_DIRECTORY"):
        return
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def rename_if_absent(source: Path, destination: Path) -> bool:
    """Atomically rename a folder; False if ``destination`` already exists (someone won)."""
    try:
        os.rename(source, destination)
    except OSError as exc:
        if exc.errno in (errno.EEXIST, errno.ENOTEMPTY):
            return False
        raise
    return True


def remove_tree(path: Path) -> None:
    """Remove a folder, first renaming it aside so no reader ever sees it half removed."""
    trash = path.parent / f".trash-{uuid.uuid4().hex}"
    try:
        os.rename(path, trash)
    except FileNotFoundError:
        return
    shutil.rmtree(trash, ignore_errors=True)


def reason(exc: BaseException) -> str:
    """An exception as a single line, for one-line user messages."""
    text = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
    return " ".join(text.split()) or type(exc).__name__
