"""The artifact store's interface and what its backends share (:mod:`facecap.tasks.store`)."""

from __future__ import annotations

import hashlib
import os
import re
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import fsspec
from fsspec.core import url_to_fs
from fsspec.implementations.memory import MemoryFileSystem
from pydantic import BaseModel, ValidationError

from facecap.tasks.store.files import (
    MANIFEST_NAME,
    ArtifactNotFoundError,
    CorruptArtifactError,
    FileEntry,
    FileSource,
    Manifest,
    StoreWriteError,
    hash_stream,
    mismatch,
    now_utc,
    reason,
)
from facecap.tasks.store.keys import (
    KEY_PATTERN,
    WRITER_PATTERN,
    check_file_names,
    check_key,
    check_stage,
    config_as_json,
)
from facecap_core.errors import InputError

MakeManifest = Callable[[dict[str, FileEntry]], Manifest]

SCHEMES = frozenset({"file", "s3", "memory"})
"""Where artifacts can live: a local folder (a path or ``file://``), S3 or MinIO (``s3://``),
and ``memory://`` for tests. Other fsspec protocols are refused: HTTP, FTP and the like cannot
commit a manifest create-only, and a store URL must never make a worker send requests to
whatever host it names."""


_PASSWORDS = (re.compile(r"(?P<head>[A-Za-z][A-Za-z0-9+.-]*://+[^\s/@:'\"]*):[^\s'\"]*@"),
              re.compile(r"(?P<head>[\"'][^\s/@:'\"]*):(?!//)[^\s'\"]*@"))
"""``user:password@`` of a URL's authority (the password up to the last ``@``: secret keys
hold ``/`` and ``+``), also where a library's message quotes it without the URL around it
(s3fs takes ``user:password@host`` for a bucket name)."""


def redact(text: str | os.PathLike[str]) -> str:
    """``text`` (a store URL, or a message naming one) with every password of a URL in it
    shown as ``***``: ``s3://user:***@host/bucket``. Every message that names a store passes
    its URL through here: messages reach terminals, logs and the Prefect UI."""
    text = os.fspath(text)
    for pattern in _PASSWORDS:
        text = pattern.sub(r"\g<head>:***@", text)
    return text


def scheme(url: str | os.PathLike[str]) -> str:
    """The URL's protocol: ``file`` for a plain path."""
    text = os.fspath(url)
    return text.split("://", 1)[0].lower() if "://" in text else "file"


def _filesystem(url: str | os.PathLike[str]) -> tuple[fsspec.AbstractFileSystem, str]:
    """The fsspec filesystem and root of a store URL; anything else is bad input."""
    if "::" in os.fspath(url):  # fsspec's URL chaining: the chained protocols go unchecked
        raise InputError(f"the store {redact(url)} chains protocols (::), which a store "
                         "cannot do; give a folder or an s3://bucket/prefix URL (--store or "
                         "FACECAP_STORE)")
    if scheme(url) not in SCHEMES:
        raise InputError(f"the store {redact(url)} uses the protocol {scheme(url)!r}, which "
                         "cannot hold artifacts; give a folder or an s3://bucket/prefix URL "
                         "(--store or FACECAP_STORE)")
    try:
        return url_to_fs(_expand(url))
    except (ImportError, ValueError) as exc:  # a malformed URL or a missing backend
        raise InputError(f"the store {redact(url)} cannot be opened "
                         f"({redact(' '.join(str(exc).split()))}); give a folder or an "
                         "s3://bucket/prefix URL") from None


class ArtifactStore:
    """Content-addressed artifacts in a local folder or under any fsspec URL.

    :func:`facecap.tasks.store.open_store` gives the backend for a URL:
    :class:`~facecap.tasks.store.local.LocalStore` for a folder, :class:`~facecap.tasks.store.remote.RemoteStore`
    for an object store. See :mod:`facecap.tasks.store` for the layout and the commit protocol.
    """

    is_local = False
    """Whether the store is a folder of this machine."""

    def __init__(self, url: str | os.PathLike[str]) -> None:
        """Use the store at ``url``: a local path, or a ``file://``, ``s3://``, ``memory://`` URL.

        Nothing is created until the first put.
        """
        if type(self) is ArtifactStore:
            raise TypeError("ArtifactStore is the backends' interface: open a store with "
                            "facecap.tasks.store.open_store(url)")
        fs, root = _filesystem(url)
        self._fs: fsspec.AbstractFileSystem = fs
        self._root: str = root.rstrip("/") or "/"

    @property
    def url(self) -> str:
        """Where the store lives: an absolute folder path, or a URL for remote stores."""
        return self._root if self.is_local else self._fs.unstrip_protocol(self._root)

    @property
    def shown_url(self) -> str:
        """:attr:`url` as messages show it: without a password (:func:`redact`)."""
        return redact(self.url)

    @property
    def outlives_process(self) -> bool:
        """Whether the artifacts outlast this process (``memory://`` goes with it)."""
        return not isinstance(self._fs, MemoryFileSystem)

    @property
    def fs(self) -> fsspec.AbstractFileSystem:
        """The fsspec filesystem holding the store."""
        return self._fs

    def __repr__(self) -> str:
        return f"ArtifactStore({self.shown_url!r})"

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
        return path if self.is_local else self._fs.unstrip_protocol(path)

    # ----------------------------------------------------------------- reading

    def exists(self, key: str) -> bool:
        """True only if the artifact is committed, i.e. its manifest exists."""
        check_key(key)
        return self._fs.exists(self._manifest_path(key))

    def manifest(self, key: str) -> Manifest:
        """The committed manifest of ``key``; ArtifactNotFoundError if there is none."""
        check_key(key)
        try:
            data = self._fs.cat_file(self._manifest_path(key))
        except FileNotFoundError:
            raise ArtifactNotFoundError(f"artifact {key} not found in store "
                                        f"{self.shown_url}") from None
        try:
            manifest = Manifest.model_validate_json(data)
        except ValidationError as exc:
            raise self._corrupt(key, MANIFEST_NAME, "is not a valid manifest") from exc
        if manifest.key != key:
            raise self._corrupt(key, MANIFEST_NAME, f"belongs to artifact {manifest.key}")
        if manifest.folder is not None and not WRITER_PATTERN.fullmatch(manifest.folder):
            # The folder becomes part of a path: nothing but a writer's name may be there.
            raise self._corrupt(key, MANIFEST_NAME, f"names an invalid folder {manifest.folder!r}")
        for name in manifest.files:
            try:
                # File names become paths in the local cache: none may lead out of it.
                check_file_names([name])
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
            problem = mismatch(actual, entry)
            if problem:
                raise self._corrupt(key, name, problem)
        return data

    def presigned_url(self, key: str, name: str, expires: int) -> str | None:
        """An HTTP URL that serves one file of a committed artifact for ``expires`` seconds to
        whoever has it, without credentials (S3's presigned URL); None where the store cannot
        make one (a folder, ``memory://``)."""
        self._entry(self.manifest(key), name)
        return None

    def verify(self, key: str) -> None:
        """Check every file of an artifact against its manifest; CorruptArtifactError if not."""
        manifest = self.manifest(key)
        for name, entry in manifest.files.items():
            problem = self._stored_file_problem(manifest, name, entry)
            if problem:
                raise self._corrupt(key, name, problem)

    def get(self, key: str, verify: bool = True) -> Path:
        """A local folder holding the artifact's files (and its ``manifest.json``), every
        file's checksum and size checked if ``verify``. Treat it as read-only."""
        raise NotImplementedError

    def keys(self, stage: str | None = None) -> list[str]:
        """Keys of the committed artifacts, optionally of one stage only, sorted."""
        if stage is not None:
            check_stage(stage)
        # Globbing for manifests lists committed artifacts only, in one listing on S3.
        pattern = f"{self._root}/artifacts/*/{MANIFEST_NAME}"
        found = (path.rstrip("/").split("/")[-2] for path in self._fs.glob(pattern))
        return sorted(
            key
            for key in found
            if KEY_PATTERN.fullmatch(key) and (stage is None or key.startswith(f"{stage}-"))
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
        check_key(key)
        check_stage(stage)
        if not key.startswith(f"{stage}-"):
            # keys(stage) selects by this prefix, so it must agree with the manifest.
            raise InputError(f"artifact key {key} does not belong to stage {stage!r}")
        names = list(files)
        check_file_names(names)
        if self.exists(key):
            return self.manifest(key)

        def make_manifest(entries: dict[str, FileEntry]) -> Manifest:
            return Manifest(
                key=key,
                stage=stage,
                version=version,
                inputs=dict(inputs),
                config=config_as_json(config),
                files=entries,
                created=now_utc(),
                meta=dict(meta or {}),
            )

        return self._put(key, files, make_manifest)

    def _put(self, key: str, files: Mapping[str, FileSource],
             make_manifest: MakeManifest) -> Manifest:
        """Write the files and commit the manifest atomically (per backend)."""
        raise NotImplementedError

    def delete(self, key: str) -> None:
        """Remove an artifact so that it will be recomputed; an interrupted delete never
        leaves a trusted half artifact."""
        raise NotImplementedError

    def _entry(self, manifest: Manifest, name: str) -> FileEntry:
        entry = manifest.files.get(name)
        if entry is None:
            raise ArtifactNotFoundError(
                f"artifact {manifest.key} in store {self.shown_url} has no file {name!r} "
                f"(it has: {', '.join(sorted(manifest.files)) or 'no files'})"
            )
        return entry

    def _stored_file_problem(self, manifest: Manifest, name: str,
                             entry: FileEntry) -> str | None:
        """How a stored file differs from its manifest entry, or None if it matches."""
        try:
            with self._fs.open(self._stored_path(manifest, name), "rb") as stored:
                return mismatch(hash_stream(stored), entry)
        except FileNotFoundError:
            return "is missing"

    def _corrupt(self, key: str, name: str, problem: str) -> CorruptArtifactError:
        return CorruptArtifactError(
            f"artifact {key} is corrupt: file {name!r} {problem}; "
            f"delete {redact(self._location(key))} so that it is recomputed"
        )

    def _write_error(self, key: str, where: str, exc: OSError) -> StoreWriteError:
        return StoreWriteError(
            f"could not write artifact {key} to {redact(where)}: {redact(reason(exc))}; "
            "check that the location is writable and has free space, then retry"
        )


def _expand(url: str | os.PathLike[str]) -> str:
    text = os.fspath(url)
    return text if "://" in text else os.path.expanduser(text)
