"""The store in an object store (S3, MinIO; ``memory://`` in tests) through fsspec.

Object stores have no atomic rename: each writer uploads into a folder of its own and commits
the manifest create-only (S3's ``If-None-Match: *``); of two writers of one key the first
manifest wins. Artifacts are read from a verified local copy in ``$FACECAP_HOME/store-cache``.
"""

from __future__ import annotations

import os
import shutil
import uuid
from collections.abc import Mapping
from pathlib import Path

from pydantic import ValidationError

from facecap.tasks.own_files import own_folder
from facecap.tasks.store.base import ArtifactStore, MakeManifest, scheme
from facecap.tasks.store.files import (
    MANIFEST_NAME,
    ArtifactNotFoundError,
    FileEntry,
    FileSource,
    Manifest,
    copy_hashing,
    hash_stream,
    manifest_bytes,
    mismatch,
    raw_chunks,
    remove_tree,
    rename_if_absent,
    source_chunks,
    write_durably,
    write_local_file,
)
from facecap.tasks.store.keys import check_key
from facecap.tasks.store.links import check_link_seconds, content_type
from facecap_core.assets import facecap_home


def cache_root() -> Path:
    """Local folder for copies of remote artifacts: ``$FACECAP_HOME/store-cache``."""
    return facecap_home() / "store-cache"


class RemoteStore(ArtifactStore):
    """Artifacts under an fsspec URL (``s3://bucket/prefix``, ``memory://name``)."""

    def delete(self, key: str) -> None:
        """Remove an artifact so that it will be recomputed: the manifest first (the
        artifact is gone from then on), then its files and the local cached copy."""
        check_key(key)
        folder = self._artifact_path(key)
        if not self._fs.exists(folder):
            raise ArtifactNotFoundError(f"artifact {key} not found in store {self.shown_url}")
        if self._fs.exists(self._manifest_path(key)):
            self._fs.rm_file(self._manifest_path(key))
        self._fs.rm(folder, recursive=True)
        remove_tree(cache_root() / key)

    def _put(self, key: str, files: Mapping[str, FileSource],
             make_manifest: MakeManifest) -> Manifest:
        """Upload the files into a folder of this writer's own, then commit the manifest
        create-only; a writer that loses the race removes its folder and returns the
        winner's manifest."""
        folder = f"w-{uuid.uuid4().hex}"
        try:
            try:
                entries = {}
                for name, source in files.items():
                    with self._fs.open(self._file_path(key, name, folder), "wb") as target:
                        entries[name] = copy_hashing(source_chunks(name, source), target)
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
            self._fs.pipe_file(path, manifest_bytes(manifest), mode="create")
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

    def presigned_url(self, key: str, name: str, expires: int) -> str | None:
        """S3: a presigned GET URL of the file, signed with the store's credentials and
        naming the endpoint as this machine reaches it; valid ``expires`` seconds (S3 allows
        at most 7 days)."""
        manifest = self.manifest(key)
        self._entry(manifest, name)
        if scheme(self.url) != "s3":
            return None
        check_link_seconds(expires)

        # The object's own type is whatever the upload left (S3 often says binary): the link
        # names the type, so that a page opens in the browser rather than downloading, and
        # asks that no cache keeps it (a face).
        return self._fs.url(self._stored_path(manifest, name), expires=int(expires),
                            ResponseContentType=content_type(name),
                            ResponseCacheControl="private, no-store")

    def get(self, key: str, verify: bool = True) -> Path:
        """The local copy in ``$FACECAP_HOME/store-cache/<key>/``, downloaded once and reused
        while it matches the manifest."""
        manifest = self.manifest(key)
        cached = cache_root() / key
        if cached.is_dir():
            if self._cached_copy_matches(cached, manifest, verify):
                return cached
            remove_tree(cached)  # stale or damaged: the remote copy is the truth
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
                    if mismatch(hash_stream(cached_file), entry):
                        return False
        except (OSError, ValidationError):
            return False
        return True

    def _download(self, key: str, manifest: Manifest, destination: Path, verify: bool) -> Path:
        """Download into a temporary folder, check it, then rename it into the cache."""
        temp_folder = destination.parent / ".tmp" / uuid.uuid4().hex
        try:
            try:
                os.close(own_folder(temp_folder.parent))  # never behind a link planted as .tmp
                temp_folder.mkdir()
                for name, entry in manifest.files.items():
                    actual = self._download_file(manifest, name, temp_folder / name)
                    problem = mismatch(actual, entry) if verify else None
                    if problem:
                        raise self._corrupt(key, name, problem)
                write_durably(temp_folder / MANIFEST_NAME, manifest_bytes(manifest))
                # If another process finished the same download first, its copy is as good.
                rename_if_absent(temp_folder, destination)
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
            return write_local_file(target_path, raw_chunks(remote))
