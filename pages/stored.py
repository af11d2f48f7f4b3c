"""The pages in the store: each run's page kept as an artifact, and the links that open it.

A link from the Prefect UI opens a page from the store (S3's presigned URL, or the page
server's for a store in a folder, :mod:`facecap.pages.server`); ``forget`` removes a page with
the face it shows, as it was made from that face's artifacts.
"""

from __future__ import annotations

import functools
import hashlib
import json
import logging
from importlib.metadata import version
from pathlib import Path

import facecap.pages.capture as capture_page
from facecap.tasks.runner import key_lock, lease, network_errors
from facecap.tasks.store import artifact_key
from facecap.tasks.store.keys import KEY_PATTERN
from facecap_core.errors import FacecapError

_log = logging.getLogger(__name__)

PAGE_NAME = "index.html"
PAGE_STAGE = "page"
"""The store keeps each run's page as an artifact of this name, made from the run's stage
artifacts: what a link from the Prefect UI opens (:func:`facecap.flows.ui.results_link`), what
``forget`` removes with the face it shows, what ``prune --unreferenced`` keeps while a
``report.json`` names it."""


def keep_page(store, inputs: dict[str, str], page: bytes) -> str:
    """Keep ``page`` in the store as an artifact made from ``inputs`` (name -> key), held
    for the run in progress; returns its key."""
    config = {"sha256": hashlib.sha256(page).hexdigest()}
    key = artifact_key(PAGE_STAGE, inputs, config, "1")
    lease(store, key)
    store.put(key, {PAGE_NAME: page}, stage=PAGE_STAGE, inputs=inputs, config=config,
              version="1")
    return key


PARTS_NAME = "parts.json"
"""The page parts artifact's one file (:func:`facecap.pages.capture.page_parts`)."""


@functools.cache
def _parts_config() -> dict:
    # What makes the parts is part of what they are made from: parts kept by other code (the
    # page module and the ones whose functions it calls for the parts) or by other
    # libraries (the JPEG encoder, the scan's decimation) are never read.
    from facecap.pages import scan
    from facecap_core import camera, frames, meshio
    from facecap_core.evaluation import alignment
    from facecap_core.evaluation import stage as evaluation
    from facecap_core.pose import cameras_json

    sources = hashlib.sha256()
    for module in (capture_page, scan, camera, frames, meshio, alignment, evaluation,
                   cameras_json):
        sources.update(Path(module.__file__).read_bytes())
    return {"parts": sources.hexdigest(),
            "libraries": {name: version(name) for name in PARTS_LIBRARIES}}


PARTS_LIBRARIES = ("numpy", "opencv-python-headless", "open3d")
"""The distributions whose versions name the page parts (:func:`_parts_config`)."""


def _parts_key(inputs: dict[str, str]) -> str:
    return artifact_key(PAGE_STAGE, inputs, _parts_config(), "1")


def stage_keys(report: dict) -> dict[str, str]:
    """The run's stage artifacts (report row -> key): what its page is made from."""
    return {name: info["key"] for name, info in report.get("stages", {}).items()}


def stored_parts(store, report: dict) -> tuple[str, dict | None]:
    """The key of the page parts of the run's stage artifacts, and the parts themselves
    where a run of the same artifacts kept them (None otherwise), held for the run in
    progress. Parts that cannot be read are removed, for :func:`keep_parts` to keep anew."""
    key = _parts_key(stage_keys(report))
    lease(store, key)
    if not store.exists(key):
        return key, None
    try:
        return key, json.loads((store.get(key) / PARTS_NAME).read_text())
    except (OSError, ValueError, FacecapError) as exc:
        _log.warning("the page parts %s are made again: %s", key, _first_line(exc))
    try:
        with key_lock(store, key):
            store.delete(key)
    except (OSError, FacecapError, *network_errors()) as exc:  # the page is made all the same
        _log.warning("the damaged page parts %s stay in the store: %s", key, _first_line(exc))
    return key, None


def _first_line(exc: BaseException) -> str:
    return str(exc).splitlines()[0] if str(exc) else type(exc).__name__


def keep_parts(store, report: dict, parts: dict) -> str:
    """Keep the page ``parts`` of the run's stage artifacts in the store; returns their
    key."""
    inputs = stage_keys(report)
    key = _parts_key(inputs)
    lease(store, key)
    with key_lock(store, key):
        store.put(key, {PARTS_NAME: json.dumps(parts).encode()}, stage=PAGE_STAGE,
                  inputs=inputs, config=_parts_config(), version="1")
    return key


def store_page(store, report: dict, page: bytes) -> str:
    """Keep ``page`` (this run's ``index.html``) in the store, made from the run's stage
    artifacts; returns its key."""
    return keep_page(store, stage_keys(report), page)


RESULTS_LINK_SECONDS = 24 * 3600
"""How long the link from the Prefect UI to a capture's page lasts: whoever has it can open
the page (the face in 3D) until then, without credentials. A rerun (every stage reused,
seconds) publishes a fresh one; ``facecap forget`` deletes the link and the page."""


def stored_link(store, key: str | None, name: str) -> str | None:
    """A link that opens file ``name`` of artifact ``key`` of ``store`` (an ArtifactStore)
    in a browser for :data:`RESULTS_LINK_SECONDS`: S3's presigned URL, or for a folder store
    the page server's (``FACECAP_PAGES_URL``); None where the store can make none or does not
    hold the artifact."""
    if not isinstance(key, str) or not KEY_PATTERN.fullmatch(key):
        return None
    try:
        return store.presigned_url(key, name, RESULTS_LINK_SECONDS)
    except (OSError, FacecapError, *network_errors()) as exc:
        # The results are made: a link is not worth failing for (a missing or damaged page,
        # an unreadable link secret, a store that cannot be reached).
        _log.warning("no link to %s of %s: %s", name, key, _first_line(exc))
        return None
