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
    * ``s3://bucket/prefix`` for S3 or MinIO, ``memory://name`` in tests. Other protocols
      (HTTP, FTP, ...) are refused: they cannot commit a manifest create-only, and a store URL
      must never make a worker send requests to whatever host it names.

Credentials are never passed to this module. For S3 and MinIO they come from the
environment only: s3fs reads ``AWS_ACCESS_KEY_ID`` and ``AWS_SECRET_ACCESS_KEY``, and
fsspec reads ``FSSPEC_S3_ENDPOINT_URL`` for a MinIO endpoint.

Remote artifacts are downloaded for local use into a cache,
``$FACECAP_HOME/store-cache/<key>/`` (``FACECAP_HOME`` defaults to ``~/.cache/facecap``).

To force an artifact to be recomputed, delete its folder ``<root>/artifacts/<key>`` (or
call :meth:`ArtifactStore.delete`).

Open a store with :func:`open_store`.
"""

import os

from fsspec.implementations.local import LocalFileSystem

from facecap.tasks.store.base import ArtifactStore, _filesystem
from facecap.tasks.store.files import (
    MANIFEST_NAME,
    ArtifactNotFoundError,
    CorruptArtifactError,
    FileEntry,
    FileSource,
    Manifest,
    StoreWriteError,
)
from facecap.tasks.store.keys import KEY_DIGEST_LENGTH, artifact_key, file_digest, input_key
from facecap.tasks.store.local import LocalStore
from facecap.tasks.store.remote import RemoteStore


def open_store(url: str | os.PathLike[str]) -> ArtifactStore:
    """The store at ``url``: a :class:`LocalStore` for a folder (a path or ``file://``), a
    :class:`RemoteStore` for an object store (``s3://``, ``memory://``). A URL that names
    another protocol, or cannot be parsed, is an ``InputError``."""
    fs, _ = _filesystem(url)
    return LocalStore(url) if isinstance(fs, LocalFileSystem) else RemoteStore(url)


__all__ = [
    "KEY_DIGEST_LENGTH",
    "MANIFEST_NAME",
    "ArtifactNotFoundError",
    "ArtifactStore",
    "CorruptArtifactError",
    "FileEntry",
    "FileSource",
    "LocalStore",
    "Manifest",
    "RemoteStore",
    "StoreWriteError",
    "artifact_key",
    "file_digest",
    "input_key",
    "open_store",
]
