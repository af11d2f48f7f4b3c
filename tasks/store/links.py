"""Links that open one file of a folder store's artifact over HTTP, for a while, to whoever
has them: for a local store, what S3's presigned URLs are for a bucket.

``facecap pages`` (:mod:`facecap.pages.server`) serves them. A link names the artifact, the
file and the second it expires, and carries an HMAC-SHA256 of the three under a secret that
only this machine's facecap holds (``$FACECAP_HOME/link-secret``, made on first use, readable
by its owner only): the server answers a link it signed until it expires, and nothing else,
so the address of one face's page never leads to another's.
"""

from __future__ import annotations

import hashlib
import hmac
import mimetypes
import os
import re
import secrets
import stat
import time
from urllib.parse import quote, urlencode

from facecap_core.errors import InputError
from facecap_core.settings import settings

SECRET_NAME = "link-secret"
LINK_MAX_SECONDS = 7 * 24 * 3600
"""The longest a link lasts: S3's limit on a presigned URL (signature version 4), and the
page server's alike."""


def check_link_seconds(expires: int) -> None:
    """Refuse a link lifetime outside 1 s .. :data:`LINK_MAX_SECONDS`."""
    if not 0 < expires <= LINK_MAX_SECONDS:
        raise ValueError(f"a link lasts 1 s to 7 days; got {expires} s")


def content_type(name: str) -> str:
    """The media type a browser is told a stored file has: a page opens as a page, and
    anything unknown downloads."""

    kind = {".glb": "model/gltf-binary"}.get(os.path.splitext(name)[1].lower()) \
        or mimetypes.guess_type(name)[0] or "application/octet-stream"
    return f"{kind}; charset=utf-8" if kind.startswith("text/") else kind


def _secret() -> bytes:
    path = settings().home / SECRET_NAME
    try:
        return _read_secret(path)
    except OSError as exc:  # a folder, a file facecap may not read, a home it may not write
        raise InputError(f"the link secret {path} cannot be read or made ({exc.strerror}); "
                         "remove it or correct its permissions and retry (every link made "
                         "with the old one stops working)") from None


def _read_secret(path) -> bytes:
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        # Made once, by whichever process asks first; O_EXCL so that two never write two.
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600)
    except FileExistsError:
        pass
    else:
        with os.fdopen(fd, "w") as made:
            made.write(secrets.token_hex(32))
    # Never through a link, never blocked on a FIFO: a plain file of this machine's.
    held = os.fdopen(os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK), "rb")
    with held:  # a process that lost the race may read it half written
        if not stat.S_ISREG(os.fstat(held.fileno()).st_mode):
            raise InputError(f"{path} is not a file; remove it and retry")
        for _ in range(50):
            held.seek(0)
            secret = held.read(65).strip()
            if len(secret) == 64 and re.fullmatch(rb"[0-9a-f]{64}", secret):
                return secret
            time.sleep(0.01)
    raise InputError(f"{path} is not a link secret facecap made; remove it and retry "
                     "(every link made with the old one stops working)")


def check_secret() -> None:
    """Raise a one-line InputError if this machine's link secret cannot be read (or made):
    what the page server checks before it serves."""
    _secret()


def signature(key: str, name: str, expires_at: int) -> str:
    """The signature of a link to file ``name`` of artifact ``key`` until ``expires_at``
    (seconds since the epoch)."""
    message = f"{key}\n{name}\n{expires_at}".encode()
    return hmac.new(_secret(), message, hashlib.sha256).hexdigest()


def link(base_url: str, key: str, name: str, expires: int) -> str:
    """The address under the page server ``base_url`` that serves file ``name`` of
    artifact ``key`` for ``expires`` seconds."""
    check_link_seconds(expires)
    expires_at = int(time.time()) + int(expires)
    query = urlencode({"expires": expires_at, "signature": signature(key, name, expires_at)})
    return f"{base_url.rstrip('/')}/artifacts/{key}/{quote(name, safe='')}?{query}"


def link_problem(key: str, name: str, expires_at: str, signed: str) -> str | None:
    """Why a request for ``key``/``name`` with these query values may not be answered
    (None: it may): a signature that is not this machine's, or a link that has expired."""
    if not (re.fullmatch(r"[0-9]{1,12}", expires_at) and re.fullmatch(r"[0-9a-f]{64}", signed)):
        return "not a link facecap made"
    if not hmac.compare_digest(signature(key, name, int(expires_at)), signed):
        return "not a link facecap made"
    if int(expires_at) < time.time():
        return "this link has expired: the run's page in the Prefect UI has a fresh one"
    return None
