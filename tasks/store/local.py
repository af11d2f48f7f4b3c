"""The store in a folder of this machine: every artifact is written to ``.tmp/<uuid4>/`` and
renamed into place in one atomic step."""

from __future__ import annotations

import errno
import os
import shutil
import time
import uuid
from collections.abc import Mapping
from pathlib import Path

from facecap.tasks.own_files import own_folder
from facecap.tasks.store.base import ArtifactStore, MakeManifest
from facecap.tasks.store.files import (
    MANIFEST_NAME,
    ArtifactNotFoundError,
    FileSource,
    Manifest,
    StoreWriteError,
    fsync_dir,
    manifest_bytes,
    remove_tree,
    rename_if_absent,
    source_chunks,
    write_durably,
    write_local_file,
)
from facecap.tasks.store.keys import check_key
from facecap.tasks.store.links import link
from facecap_core.errors import InputError
from facecap_core.settings import settings

_CHECKED: dict[tuple[str, str, int], tuple[int, ...]] = {}
"""The stored files this process found equal to their manifest entry: (path, sha256, size)
-> the file's identity then (:func:`_file_identity`)."""
MAX_CHECKED = 200_000
"""The most files :data:`_CHECKED` remembers."""
RECENT_NS = 2_000_000_000
"""Files modified or changed (their metadata: ``touch``, ``cp -p``) less than this long
before their check are checked again each time."""


def _now_ns() -> int:
    return time.time_ns()


def _file_identity(path: str) -> tuple[int, ...] | None:
    """What changes whenever a file is written or replaced: its device, inode, size and
    modification and change times (ns); None for no file."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)


class LocalStore(ArtifactStore):
    """Artifacts in a local folder (a path or a ``file://`` URL)."""

    is_local = True

    def __init__(self, url) -> None:
        super().__init__(url)
        for path in (Path(self._root), *Path(self._root).parents):
            if path.is_symlink() and not path.exists():  # a loop, or a link to nothing
                try:
                    path.resolve(strict=True)
                except RuntimeError:
                    why = "a link that leads back to itself"
                except OSError as exc:
                    why = ("a link that leads back to itself" if exc.errno == errno.ELOOP
                           else "a link to nothing")
                else:  # pragma: no cover - exists() said otherwise a moment ago
                    continue
                raise InputError(f"the store {url} is not a folder ({path} is {why}); give the "
                                 "path of a folder (--store or FACECAP_STORE)")
        existing = next((p for p in (Path(self._root), *Path(self._root).parents)
                         if p.exists()), None)
        if existing is not None and not existing.is_dir():
            raise InputError(f"the store {url} is not a folder ({existing} is a file); give "
                             "the path of a folder (--store or FACECAP_STORE)")

    def presigned_url(self, key: str, name: str, expires: int) -> str | None:
        """A link to the file on the page server of ``FACECAP_PAGES_URL``
        (:mod:`facecap.tasks.store.links`), valid ``expires`` seconds (at most 7 days); None where no
        page server is configured."""

        self._entry(self.manifest(key), name)
        base = settings().pages_url
        return link(base, key, name, expires) if base else None

    def verify(self, key: str) -> None:
        """Check every file of an artifact against its manifest; CorruptArtifactError if not.
        A file this process checked already and that is unchanged since (the same inode,
        size, modification and change times) is not read again: each depth map of a capture
        reads the frames stage's artifact (60 MB at 720p), and forty maps read it forty
        times."""
        manifest = self.manifest(key)
        for name, entry in manifest.files.items():
            path = self._stored_path(manifest, name)
            # Taken before the file is read: a write while it is read changes it.
            seen = _file_identity(path)
            if seen is not None and _CHECKED.get((path, entry.sha256, entry.size)) == seen:
                continue
            problem = self._stored_file_problem(manifest, name, entry)
            if problem:
                raise self._corrupt(key, name, problem)
            # A file written within the file system's timestamp granularity (a few ms on
            # older kernels) of its check could be written again with the same times: only
            # files whose last modification and last change are both older are remembered.
            if seen is not None and _now_ns() - max(seen[3], seen[4]) > RECENT_NS:
                if len(_CHECKED) >= MAX_CHECKED:  # a worker's life long: start again
                    _CHECKED.clear()
                _CHECKED[(path, entry.sha256, entry.size)] = seen

    def get(self, key: str, verify: bool = True) -> Path:
        """The artifact folder itself: treat it as read-only."""
        if verify:
            self.verify(key)
        else:
            self.manifest(key)  # raises if the artifact is not committed
        return Path(self._artifact_path(key))

    def delete(self, key: str) -> None:
        """Remove an artifact so that it will be recomputed: one atomic rename takes the
        manifest and all files away at once."""
        check_key(key)
        folder = Path(self._artifact_path(key))
        if not folder.exists():
            raise ArtifactNotFoundError(f"artifact {key} not found in store {self.url}")
        remove_tree(folder)

    def _put(self, key: str, files: Mapping[str, FileSource],
             make_manifest: MakeManifest) -> Manifest:
        """Write into ``.tmp/<uuid4>/`` and rename the whole folder into place at once."""
        root = Path(self._root)
        temp_folder = root / ".tmp" / uuid.uuid4().hex
        final_folder = Path(self._artifact_path(key))
        try:
            try:
                # Never behind a link planted as .tmp: made, or checked, as a folder of its own.
                os.close(own_folder(temp_folder.parent))
                temp_folder.mkdir()
                entries = {
                    name: write_local_file(temp_folder / name, source_chunks(name, source))
                    for name, source in files.items()
                }
                manifest = make_manifest(entries)
                write_durably(temp_folder / MANIFEST_NAME, manifest_bytes(manifest))
                fsync_dir(temp_folder)
                final_folder.parent.mkdir(parents=True, exist_ok=True)
                committed = rename_if_absent(temp_folder, final_folder)
                if committed:
                    fsync_dir(final_folder.parent)
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
