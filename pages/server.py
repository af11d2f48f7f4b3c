"""``facecap pages``: the results pages of a local store, over HTTP, to whoever has a link.

The Prefect UI links each capture run to its page (``index.html``,
:mod:`facecap.pages.capture`), and each dataset run to its dataset page; a browser cannot open
a ``file://`` address from a web page, so a store in a folder needs a server. It answers
``GET /artifacts/<key>/<file>`` with a link :mod:`facecap.tasks.store.links` signed (what S3's
presigned URLs are for a bucket) and nothing else: the file is read from the store and
checked against its manifest, an expired link gets 410 and any other request 404, the same
answer whether or not the artifact exists.
"""

from __future__ import annotations

import contextlib
import logging
import re
import socket
import sys
import threading
import time
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from urllib.parse import parse_qs, unquote, urlsplit

from facecap.tasks.store import ArtifactStore
from facecap.tasks.store.keys import KEY_PATTERN
from facecap.tasks.store.links import check_secret, content_type, link_problem
from facecap_core.errors import InputError

DEFAULT_PORT = 4280
REQUEST_SECONDS = 30.0
"""The time a client has to send its whole request (line and headers): one that sends a byte
now and then holds a thread no longer than this, however it paces them."""
ANSWER_SECONDS = 600.0
"""The time a connection may last in all, the answer included: a client that reads the
answer slowly, or not at all, holds a thread no longer than this (a 100 MB mesh over a link of
2 Mbit/s fits)."""
HUNG_UP = (BrokenPipeError, ConnectionResetError, ConnectionAbortedError)
"""What a write or read meets when the client has gone: not an error of the server's."""
PATH = re.compile(r"/artifacts/([a-z0-9_]+-[0-9a-f]+)/([^/]+)")
log = logging.getLogger("facecap.pages")


def _handler(store: ArtifactStore, request_s: float,
             answer_s: float) -> type[BaseHTTPRequestHandler]:
    # Long on purpose: one class, the handler of a store's links, closed over its settings.
    class PageHandler(BaseHTTPRequestHandler):
        server_version = "facecap-pages"
        sys_version = ""
        timeout = 30  # per read; the deadlines below bound the whole request and answer

        def setup(self) -> None:
            super().setup()
            self._deadline = _Deadline(self.connection, request_s)

        def parse_request(self) -> bool:
            parsed = super().parse_request()
            # The request has arrived whole: from now on the answer's deadline counts.
            self._deadline.extend(answer_s - request_s)
            return parsed

        def finish(self) -> None:
            try:
                super().finish()
            finally:
                self._deadline.cancel()

        def do_GET(self) -> None:  # noqa: N802 - http.server's name
            self._answer(body=True)

        def do_HEAD(self) -> None:  # noqa: N802
            self._answer(body=False)

        def _not_found(self) -> None:
            # The one answer to whatever is not a signed link, that it be no oracle.
            self._refuse(HTTPStatus.NOT_FOUND, "no such page")

        do_POST = do_PUT = do_DELETE = do_PATCH = do_OPTIONS = _not_found  # noqa: N815

        def _answer(self, body: bool) -> None:
            url = urlsplit(self.path)
            found = PATH.fullmatch(url.path)
            query = parse_qs(url.query)
            if not found or not KEY_PATTERN.fullmatch(found[1]) \
                    or set(query) != {"expires", "signature"} \
                    or any(len(v) != 1 for v in query.values()):
                return self._not_found()
            key, name = found[1], unquote(found[2])
            try:
                problem = link_problem(key, name, query["expires"][0], query["signature"][0])
            except InputError as exc:  # the secret went bad while serving: one line a request
                log.warning("%s", exc)
                return self._refuse(HTTPStatus.SERVICE_UNAVAILABLE,
                                    "the server cannot check links now")
            if problem:
                if problem.startswith("this link has expired"):
                    return self._refuse(HTTPStatus.GONE, problem)
                return self._not_found()
            try:
                data = store.read_bytes(key, name)
            except Exception as exc:  # noqa: BLE001 - gone, damaged: the browser is told little
                log.warning("%s/%s: %s", key, name, str(exc).splitlines()[0] if str(exc) else
                            type(exc).__name__)
                return self._not_found()
            self.send_response(HTTPStatus.OK)
            self.send_header("Content-Type", content_type(name))
            self.send_header("Content-Length", str(len(data)))
            # A face: no cache keeps it, and the link (its signature) goes to no other site.
            self.send_header("Cache-Control", "private, no-store")
            self.send_header("Referrer-Policy", "no-referrer")
            self.send_header("X-Content-Type-Options", "nosniff")
            self.end_headers()
            if body:
                self.wfile.write(data)

        def _refuse(self, status: HTTPStatus, why: str) -> None:
            data = f"{why}\n".encode()
            self.send_response(status)
            self.send_header("Content-Type", "text/plain; charset=utf-8")
            self.send_header("Content-Length", str(len(data)))
            self.end_headers()
            if self.command != "HEAD":
                self.wfile.write(data)

        def log_request(self, code: int | str = "-", size: int | str = "-") -> None:
            # Without the query: the log must not hold working links.
            # A request line that did not parse has no path.
            log.info("%s %s %s", getattr(self, "command", None),
                     urlsplit(getattr(self, "path", "")).path, code)

        def log_message(self, format: str, *args) -> None:  # noqa: A002 - the base's name
            log.debug(format, *args)

    return PageHandler


class _Deadline:
    """Ends a connection when its time is up, whatever it is doing: a shut-down socket ends
    the handler's read (an empty one: the request is dropped) or its write (a broken pipe,
    as when the client hangs up)."""

    def __init__(self, connection: socket.socket, seconds: float):
        self._connection, self._lock = connection, threading.Lock()
        self._at = time.monotonic() + seconds
        self._timer: threading.Timer | None = None
        self._arm()

    def _arm(self) -> None:
        self._timer = threading.Timer(max(0.0, self._at - time.monotonic()), self._expire)
        self._timer.daemon = True
        self._timer.start()

    def extend(self, seconds: float) -> None:
        with self._lock:
            if self._timer is None:  # expired or cancelled: nothing more to give
                return
            self._timer.cancel()
            self._at += max(0.0, seconds)
            self._arm()

    def cancel(self) -> None:
        with self._lock:
            if self._timer is not None:
                self._timer.cancel()
                self._timer = None

    def _expire(self) -> None:
        with self._lock:
            if self._timer is None:
                return
            self._timer = None
        log.info("a connection was ended at its deadline")
        with contextlib.suppress(OSError):  # already closed by the client
            self._connection.shutdown(socket.SHUT_RDWR)


class _PageServer(ThreadingHTTPServer):
    daemon_threads = True

    def handle_error(self, request, client_address) -> None:
        failure = sys.exc_info()[1]
        if isinstance(failure, HUNG_UP):  # the client went (or its deadline ended it)
            log.info("the client at %s hung up (%s)", client_address[0],
                     type(failure).__name__)
            return
        log.exception("the answer to %s failed", client_address[0])  # a bug: its traceback


def page_server(store: ArtifactStore, host: str = "127.0.0.1", port: int = DEFAULT_PORT,
                request_s: float = REQUEST_SECONDS,
                answer_s: float = ANSWER_SECONDS) -> ThreadingHTTPServer:
    """A server (not yet serving) of the store's linked files on ``host:port`` (port 0: any
    free one, see ``server.server_address``). A connection has ``request_s`` seconds to send
    its request and ``answer_s`` in all, the answer included. The link secret is checked
    first: a damaged one is a one-line InputError here, not an error at every request."""
    check_secret()
    return _PageServer((host, port), _handler(store, request_s, max(request_s, answer_s)))


def serve_in_background(server: ThreadingHTTPServer) -> threading.Thread:
    """Serve in a daemon thread (``facecap serve``: beside the deployments)."""
    thread = threading.Thread(target=server.serve_forever, name="facecap-pages", daemon=True)
    thread.start()
    return thread


def address(server: ThreadingHTTPServer) -> str:
    """``http://host:port`` of a server (a wildcard host as this machine's name)."""

    host, port = server.server_address[:2]
    if host in ("0.0.0.0", "::", ""):
        host = socket.getfqdn()
    return f"http://{host}:{port}" if ":" not in str(host) else f"http://[{host}]:{port}"
