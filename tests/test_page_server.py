"""``facecap pages`` (:mod:`flows.page_server`) and the links it answers
(:mod:`tasks.store.links`): a link opens the one file it was made for, until it expires, and
nothing else opens."""

from __future__ import annotations

import logging
import time
import urllib.error
import urllib.request
from urllib.parse import parse_qs, urlencode, urlsplit

import pytest

from facecap.flows.page_server import address, page_server, serve_in_background
from facecap.tasks.store import ArtifactNotFoundError, artifact_key, open_store
from facecap.tasks.store.base import scheme
from facecap.tasks.store.links import SECRET_NAME, link
from facecap_core.errors import InputError
from facecap_core.settings import settings

PAGE = b"<!doctype html><title>anna</title>"


@pytest.fixture
def served(tmp_path, monkeypatch):
    """A folder store holding one page and one mesh, served on a free port, and
    FACECAP_PAGES_URL naming the server."""
    monkeypatch.setenv("FACECAP_HOME", str(tmp_path / "home"))
    store = open_store(tmp_path / "store")
    keys = {}
    for stage, files in (("page", {"index.html": PAGE}), ("fitting", {"mesh.ply": b"ply"})):
        keys[stage] = artifact_key(stage, {}, None, "1")
        store.put(keys[stage], files, stage=stage, inputs={}, config=None, version="1")
    server = page_server(store, "127.0.0.1", 0)
    serve_in_background(server)
    monkeypatch.setenv("FACECAP_PAGES_URL", address(server))
    yield store, keys
    server.shutdown()
    server.server_close()


def fetch(url: str, method: str = "GET") -> tuple[int, dict, bytes]:
    try:
        with urllib.request.urlopen(urllib.request.Request(url, method=method),
                                    timeout=10) as answer:
            return answer.status, dict(answer.headers), answer.read()
    except urllib.error.HTTPError as refused:
        return refused.code, dict(refused.headers), refused.read()


def test_a_link_opens_its_page(served):
    store, keys = served
    url = store.presigned_url(keys["page"], "index.html", 3600)
    assert url.startswith(settings().pages_url + f"/artifacts/{keys['page']}/index.html?")
    status, headers, body = fetch(url)
    assert (status, body) == (200, PAGE)
    assert headers["Content-Type"] == "text/html; charset=utf-8"
    assert headers["Cache-Control"] == "private, no-store"  # a face stays in no cache
    assert headers["Referrer-Policy"] == "no-referrer"
    status, headers, body = fetch(url, "HEAD")
    assert (status, headers["Content-Length"], body) == (200, str(len(PAGE)), b"")
    # Only the owner may read the secret that signs the links.
    assert (settings().home / SECRET_NAME).stat().st_mode & 0o077 == 0


def test_nothing_but_a_signed_link_opens(served):
    """Another file, another artifact, a changed expiry, no signature, a path out of the
    store: 404 alike, whether or not the thing exists."""
    store, keys = served
    url = store.presigned_url(keys["page"], "index.html", 3600)
    parts = urlsplit(url)
    query = {k: v[0] for k, v in parse_qs(parts.query).items()}
    base = settings().pages_url
    tried = [
        f"{base}/artifacts/{keys['fitting']}/mesh.ply?{parts.query}",  # the page's signature
        f"{base}/artifacts/{keys['fitting']}/index.html?{parts.query}",
        f"{base}{parts.path}?{urlencode({**query, 'expires': int(query['expires']) + 1})}",
        f"{base}{parts.path}",
        f"{base}{parts.path}?{parts.query}&signature=0",
        f"{base}/artifacts/page-{'0' * 32}/index.html?{parts.query}",
        f"{base}/artifacts/{keys['page']}/..%2Fmanifest.json?{parts.query}",
        f"{base}/artifacts/{keys['page']}/manifest.json?{parts.query}",
        f"{base}/../../etc/passwd",
        f"{base}/",
    ]
    for url in tried:
        status, _, body = fetch(url)
        assert (status, body) == (404, b"no such page\n"), url


def test_an_expired_link_says_so(served, monkeypatch):
    store, keys = served
    url = store.presigned_url(keys["page"], "index.html", 1)
    later = time.time() + 2
    monkeypatch.setattr(time, "time", lambda: later)
    status, _, body = fetch(url)
    assert status == 410 and b"expired" in body
    with pytest.raises(ValueError, match="7 days"):
        store.presigned_url(keys["page"], "index.html", 8 * 24 * 3600)


def test_a_damaged_page_is_not_served(served, caplog):
    store, keys = served
    url = store.presigned_url(keys["page"], "index.html", 3600)
    (store.get(keys["page"], verify=False) / "index.html").write_bytes(PAGE.upper())
    with caplog.at_level(logging.INFO, logger="facecap.pages"):
        assert fetch(url)[0] == 404
    said = [r.getMessage() for r in caplog.records]
    assert any(f"{keys['page']}/index.html: artifact {keys['page']} is corrupt" in m
               for m in said), said  # the server's log says why; the browser learns nothing
    # The log keeps no working link: the signature never reaches it.
    assert not any(parse_qs(urlsplit(url).query)["signature"][0] in r.getMessage()
                   for r in caplog.records)


def test_links_from_another_machines_secret_do_not_open(served, tmp_path, monkeypatch):
    store, keys = served
    theirs = tmp_path / "other-home"
    monkeypatch.setenv("FACECAP_HOME", str(theirs))
    forged = link(settings().pages_url, keys["page"], "index.html", 3600)
    monkeypatch.setenv("FACECAP_HOME", str(tmp_path / "home"))
    assert fetch(forged)[0] == 404


def test_no_page_server_no_link(tmp_path, monkeypatch):
    monkeypatch.setenv("FACECAP_HOME", str(tmp_path / "home"))
    monkeypatch.delenv("FACECAP_PAGES_URL", raising=False)
    store = open_store(tmp_path / "store")
    key = artifact_key("page", {}, None, "1")
    store.put(key, {"index.html": PAGE}, stage="page", inputs={}, config=None, version="1")
    assert scheme(store.url) != "s3" and store.presigned_url(key, "index.html", 60) is None
    with pytest.raises(ArtifactNotFoundError, match="no file 'mesh.ply'"):
        store.presigned_url(key, "mesh.ply", 60)


@pytest.mark.parametrize("value", ["ftp://host", "host:4280", "http://", "http://h/?a=1",
                                   "http://user:pw@h"])
def test_a_pages_url_that_is_no_address_is_refused(value, monkeypatch):
    monkeypatch.setenv("FACECAP_PAGES_URL", value)
    with pytest.raises(InputError, match="FACECAP_PAGES_URL"):
        settings()


def test_a_port_in_use_is_one_line(served, tmp_path, capsys):
    from facecap.cli import main

    store, _ = served
    port = urlsplit(settings().pages_url).port  # the fixture's server holds it
    assert main(["pages", "--port", str(port), "--store", store.url]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (f"facecap: error: cannot serve pages on 127.0.0.1:{port} (Address already in use); "
                   "choose another --port or --host"), err


def test_a_malformed_request_still_gets_an_answer(served):
    """A query no link has (a digit that is not ASCII, a signature that is not hex), another
    method, a request line that does not parse: each is answered, and the server goes on."""
    import socket

    store, keys = served
    url = store.presigned_url(keys["page"], "index.html", 3600)
    parts = urlsplit(url)
    base = settings().pages_url
    for odd in (f"{base}{parts.path}?expires=%C2%B2&signature=00",
                f"{base}{parts.path}?expires=1&signature=%C3%A9"):
        assert fetch(odd) == (404, fetch(odd)[1], b"no such page\n")
    assert fetch(url, "POST")[0] == 404
    host, port = urlsplit(base).hostname, urlsplit(base).port
    with socket.create_connection((host, port), timeout=10) as raw:
        raw.sendall(b"GET /x HTTP/9.9\r\n\r\n")
        assert b"Error" in raw.recv(200)  # the standard library's error page
    assert fetch(url)[0] == 200
