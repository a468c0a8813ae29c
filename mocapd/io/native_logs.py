"""Native libraries' own log output, routed through mocapd's handling (issue 45).

OpenCV and onnxruntime write their errors to stderr themselves, past Python's logging and so past its rate limit
(:mod:`mocapd.io.log_throttle`): a broken TIFF decoded in a loop printed 450 libtiff lines in 40 s, a detector
model failing at run time 376 onnxruntime lines in 40 s. Every one of these failures also reaches mocapd as a
result it handles — a picture that does not decode, ``cv2.error``, onnxruntime's exception from ``run`` — and is said
there, in one rate-limited line naming the file or the camera. So the libraries' own output is turned down to fatal
errors: OpenCV's log level (unless ``OPENCV_LOG_LEVEL`` is set: a user debugging a camera asks for it) and each
onnxruntime session's log severity.
"""

from __future__ import annotations

import os
from typing import Any

#: onnxruntime's log severities: 0 verbose, 1 info, 2 warning, 3 error, 4 fatal
ORT_FATAL = 4


def quiet_opencv() -> None:
    """Turn OpenCV's own log output down to fatal errors, unless ``OPENCV_LOG_LEVEL`` asks otherwise."""
    if os.environ.get("OPENCV_LOG_LEVEL"):
        return
    from cv2.utils import logging as cv_logging

    cv_logging.setLogLevel(cv_logging.LOG_LEVEL_FATAL)


def quiet_session_options(opts: Any) -> Any:
    """``opts`` (an ``onnxruntime.SessionOptions``) with the session's own log output down to fatal errors: a
    failing ``run`` raises, and its caller says it (returns ``opts``)."""
    opts.log_severity_level = ORT_FATAL
    return opts
