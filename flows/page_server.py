"""``facecap pages``: the results pages of a local store, over HTTP, to whoever has a link.

The Prefect UI links each capture run to its page (``index.html``, :mod:`facecap.flows.page`), and
each dataset run to its dataset page; a browser cannot open a ``file://`` address from a web
page, so a store in a folder needs a server. It answers ``GET /artifacts/<key>/<file>`` with a
link :mod:`facecap.tasks.store.links` signed (what S3's presigned URLs are for a bucket) and nothing
else: the file is read from the store and checked against its manifest, an expired link gets
410 and any other request 404, the same answer whether or not the artifact exists.
"""

from __future__ import annotations

import logging
import re
import socket
import threading
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from urllib.parse import parse_qs, unquote, urlsplit

from facecap.tasks.store import ArtifactStore
from facecap.tasks.store.keys import KEY_PATTERN
from facecap.tasks.store.links import content_type, link_problem

DEFAULT_PORT = 4280
PATH = re.compile(r"/artifacts/([a-z0-9_]+-[0-9a-f]+)/([^/]+)")
log = logging.getLogger("facecap.pages")


def _handler(store: ArtifactStore) -> type[BaseHTTPRequestHandler]:
    class PageHandler(BaseHTTPRequestHandler):
        server_version = "facecap-pages"
        sys_version = ""
        timeout = 30  # a client that holds its connection open holds a thread no longer

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
            problem = link_problem(key, name, query["expires"][0], query["signature"][0])
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


def page_server(store: ArtifactStore, host: str = "127.0.0.1",
                port: int = DEFAULT_PORT) -> ThreadingHTTPServer:
    """A server (not yet serving) of the store's linked files on ``host:port`` (port 0: any
    free one, see ``server.server_address``)."""
    server = ThreadingHTTPServer((host, port), _handler(store))
    server.daemon_threads = True
    return server


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
