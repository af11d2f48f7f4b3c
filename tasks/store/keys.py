"""Artifact keys: content addresses of what a stage makes, and of the raw inputs."""

from __future__ import annotations

import functools
import hashlib
import json
import os
import re
from collections.abc import Mapping
from typing import Any

from pydantic import BaseModel

from facecap.tasks.store.files import MANIFEST_NAME, reason
from facecap_core.errors import InputError
from facecap_core.photos import list_photos

KEY_DIGEST_LENGTH = 32  # 128 bits of sha256 is plenty to avoid collisions, and keeps paths short

STAGE_PATTERN = re.compile(r"[a-z0-9_]+")
WRITER_PATTERN = re.compile(r"w-[0-9a-f]{32}")
KEY_PATTERN = re.compile(rf"([a-z0-9_]+)-[0-9a-f]{{{KEY_DIGEST_LENGTH}}}")


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
    and a mapping holding the same values give the same key; a stage's key is
    ``facecap.tasks.graph.stage_key``'s, which leaves key-neutral settings out first.
    """
    check_stage(stage)
    description = {
        "stage": stage,
        "version": version,
        "inputs": dict(inputs),
        "config": config_as_json(config),
    }
    if params:
        description["params"] = json.loads(canonical_json(dict(params)))
    digest = hashlib.sha256(canonical_json(description)).hexdigest()
    return f"{stage}-{digest[:KEY_DIGEST_LENGTH]}"


def file_digest(path: str | os.PathLike[str]) -> str:
    """sha256 (hex) of a file's bytes; an unreadable file is the caller's input error."""
    try:
        with open(path, "rb") as source:
            return hashlib.file_digest(source, "sha256").hexdigest()
    except OSError as exc:
        raise InputError(f"cannot read {os.fspath(path)}: {reason(exc)}") from exc


def input_key(path: str | os.PathLike[str]) -> str:
    """Key of a raw input file (such as a video) or a folder of photos, derived from its
    content alone (a folder's: its photos' names and bytes)."""
    if os.path.isdir(path):
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


def canonical_json(value: Any) -> bytes:
    # Sorted keys and no whitespace make equal values hash equally whatever their order.
    return json.dumps(value, sort_keys=True, separators=(",", ":")).encode("utf-8")


def config_as_json(config: BaseModel | Mapping[str, Any] | None) -> dict[str, Any] | None:
    """Config as plain JSON data: what is hashed into the key and stored in the manifest."""
    if config is None:
        return None
    if isinstance(config, BaseModel):
        return config.model_dump(mode="json")
    # A JSON round trip turns tuples into lists etc., so the manifest holds exactly what
    # was hashed.
    return json.loads(canonical_json(dict(config)))


def check_stage(stage: str) -> None:
    if not isinstance(stage, str) or not STAGE_PATTERN.fullmatch(stage):
        raise InputError(
            f"invalid stage name {stage!r}: use only lowercase letters, digits and '_'"
        )


def check_key(key: str) -> None:
    # Keys become folder names, so anything else could escape the store root.
    if not isinstance(key, str) or not KEY_PATTERN.fullmatch(key):
        raise InputError(
            f"invalid artifact key {key!r}: expected '<stage>-<{KEY_DIGEST_LENGTH} hex digits>'"
        )


def check_file_names(names: list[str]) -> None:
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
