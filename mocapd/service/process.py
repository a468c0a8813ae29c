"""Ending a daemon process quickly once it has closed everything it opened."""

from __future__ import annotations

import logging
import os
import sys
from typing import NoReturn

from mocapd.io.log_throttle import RepeatFilter


def exit_now(code: int) -> NoReturn:
    """Flush the log and standard streams and end the process without the interpreter's teardown.

    Only for a process whose work is closed (devices, sockets, sessions flushed and fsynced, threads joined):
    tearing down the numeric libraries (numba, onnxruntime, OpenCV, SciPy, matplotlib) takes a second or more on
    a loaded 2-core machine, and a daemon asked to stop must be gone within ``daemon.shutdown_timeout_s`` plus a
    second (systemd's ``TimeoutStopSec``, a technician's Ctrl-C).
    """
    for handler in logging.getLogger().handlers:  # counts of rate-limited log lines not yet said
        for f in handler.filters:
            if isinstance(f, RepeatFilter):
                f.flush()
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)
