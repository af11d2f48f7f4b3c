"""The pages in the store: each run's page kept as an artifact, and the links that open it.

A link from the Prefect UI opens a page from the store (S3's presigned URL, or the page
server's for a store in a folder, :mod:`facecap.pages.server`); ``forget`` removes a page with
the face it shows, as it was made from that face's artifacts.
"""

from __future__ import annotations

import hashlib
import logging

from facecap.tasks.runner import lease, network_errors
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


def store_page(store, report: dict, page: bytes) -> str:
    """Keep ``page`` (this run's ``index.html``) in the store, made from the run's stage
    artifacts; returns its key."""
    return keep_page(store, {name: info["key"] for name, info in
                             report.get("stages", {}).items()}, page)


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
        _log.warning("no link to %s of %s: %s", name, key, str(exc).splitlines()[0]
                     if str(exc) else type(exc).__name__)
        return None
