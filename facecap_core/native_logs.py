"""What native libraries write straight to file descriptor 2 (glog from COLMAP, absl and
TFLite from MediaPipe), kept out of the user's terminal and in facecap's log instead."""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import tempfile
import threading

_STDERR_LOCK = threading.Lock()  # file descriptor 2 is the process's: one redirection at a time
GLOG_WARNINGS = ("W", "E", "F")
"""glog and absl severities that are warnings or worse (a line starts with its letter)."""


@contextlib.contextmanager
def native_stderr_to_log(log: logging.Logger, warnings: tuple[str, ...] = GLOG_WARNINGS,
                         prefix: str = ""):
    """Lines written to stderr meanwhile go to ``log``: at WARNING those whose severity
    letter is in ``warnings``, the rest at DEBUG."""
    with _STDERR_LOCK, tempfile.TemporaryFile() as sink:
        sys.stderr.flush()
        saved = os.dup(2)
        os.dup2(sink.fileno(), 2)
        try:
            yield
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            sink.seek(0)
            for line in sink.read().decode(errors="replace").splitlines():
                severity = line.lstrip("\x1b[0123456789;m")[:1]  # after a colour code
                log.log(logging.WARNING if severity in warnings else logging.DEBUG,
                        "%s%s", prefix, line)
