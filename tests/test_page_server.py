"""``facecap pages`` (:mod:`pages.server`) and the links it answers
(:mod:`tasks.store.links`): a link opens the one file it was made for, until it expires, and
nothing else opens."""

from __future__ import annotations

import logging
import time
import urllib.error
import urllib.request
from urllib.parse import parse_qs, urlencode, urlsplit

import pytest

from facecap.pages.server import address, page_server, serve_in_background
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


def test_a_slow_client_is_cut_off_at_the_request_deadline(tmp_path, monkeypatch):
    """A client that sends a header byte now and then, each within the per-read timeout,
    holds its connection (a thread) no longer than the whole request's deadline."""
    import socket

    monkeypatch.setenv("FACECAP_HOME", str(tmp_path / "home"))
    server = page_server(open_store(tmp_path / "store"), "127.0.0.1", 0, request_s=0.5)
    serve_in_background(server)
    try:
        with socket.create_connection(server.server_address[:2], timeout=10) as raw:
            raw.sendall(b"GET /artifacts/")
            raw.settimeout(0.2)
            ended, give_up = False, time.monotonic() + 20  # the bound: 40 times the deadline
            while not ended and time.monotonic() < give_up:
                try:
                    raw.sendall(b"x")  # a byte every 0.2 s: no read ever waits 30 s
                    ended = raw.recv(100) == b""
                except TimeoutError:
                    continue  # still open: the server waits for more
                except OSError:  # reset or broken pipe: ended as well
                    ended = True
            assert ended, "the server still held the connection after 20 s"
    finally:
        server.shutdown()
        server.server_close()


class _Records(logging.Handler):
    def __init__(self) -> None:
        super().__init__()
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


@pytest.fixture
def pages_log(monkeypatch):
    """The server's log records alone: not passed on to handlers other tests' Prefect runs
    left on the root logger (their console, long closed, would report a logging error)."""
    logger, held = logging.getLogger("facecap.pages"), _Records()
    monkeypatch.setattr(logger, "propagate", False)
    level = logger.level
    logger.setLevel(logging.INFO)  # (setLevel: a logger caches what its level lets through)
    logger.addHandler(held)
    yield held
    logger.removeHandler(held)
    logger.setLevel(level)


def test_a_client_that_hangs_up_mid_answer_is_no_error(served, pages_log, capfd):
    """The answer's write meets a closed connection: one line in the server's log, no
    traceback on the console, and the server goes on."""
    import socket
    import struct

    store, _ = served
    big = artifact_key("fitting", {"big": 1}, None, "1")
    store.put(big, {"mesh.glb": b"\0" * (64 << 20)}, stage="fitting", inputs={}, config=None,
              version="1")
    url = urlsplit(store.presigned_url(big, "mesh.glb", 3600))
    raw = socket.socket()
    raw.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    raw.connect((url.hostname, url.port))
    raw.sendall(f"GET {url.path}?{url.query} HTTP/1.0\r\n\r\n".encode())
    assert raw.recv(100).startswith(b"HTTP/1.0 200")
    raw.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    raw.close()  # a reset, with 64 MB still to send
    give_up = time.monotonic() + 30  # a bound, not a pace: the server's thread says when
    while time.monotonic() < give_up and not any(
            "hung up" in r.getMessage() for r in pages_log.records):
        time.sleep(0.05)
    said = [r.getMessage() for r in pages_log.records]
    assert any("hung up" in m for m in said), said
    assert not any(r.exc_info for r in pages_log.records), said
    err = capfd.readouterr().err  # socketserver's own report of a failed request:
    assert "during processing of request" not in err and "ConnectionResetError" not in err
    assert fetch(store.presigned_url(big, "mesh.glb", 3600), "HEAD")[0] == 200


@pytest.mark.parametrize("damage", ["short", "folder", "link"])
def test_a_damaged_link_secret_is_one_line_at_start_up(damage, tmp_path, monkeypatch, capsys):
    """``facecap pages`` refuses to start (exit 2, one line) rather than answering every
    request with a traceback; a secret damaged while it serves is one log line a request."""
    from http.server import ThreadingHTTPServer

    from facecap.cli import main

    home = tmp_path / "home"
    monkeypatch.setenv("FACECAP_HOME", str(home))
    home.mkdir()
    secret = home / SECRET_NAME
    if damage == "short":
        secret.write_text("0123")
    elif damage == "folder":
        secret.mkdir()
    else:
        (tmp_path / "elsewhere").write_text("f" * 64)
        secret.symlink_to(tmp_path / "elsewhere")
    served = []  # serving forever would be the defect: recorded, not waited for
    monkeypatch.setattr(ThreadingHTTPServer, "serve_forever", lambda self: served.append(1))
    assert main(["pages", "--port", "0", "--store", str(tmp_path / "store")]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("facecap: error: "), lines
    assert str(secret) in lines[0] and "retry" in lines[0], lines
    assert not served


def test_a_secret_damaged_while_serving_is_one_log_line_a_request(served, pages_log, capfd):
    store, keys = served
    url = store.presigned_url(keys["page"], "index.html", 3600)
    (settings().home / SECRET_NAME).write_text("damaged")
    status, _, body = fetch(url)
    assert status == 503 and b"cannot check links" in body
    assert any("is not a link secret facecap made" in r.getMessage() for r in pages_log.records)
    assert not any(r.exc_info for r in pages_log.records)
    assert "during processing of request" not in capfd.readouterr().err
