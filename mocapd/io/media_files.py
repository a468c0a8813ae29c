"""Images and videos a user points mocapd at, as a door: the checks of :mod:`mocapd.io.input_files` before a
decoder sees them.

The doors: ``[[cameras]]`` of ``source = "video"`` (a file) and ``source = "images"`` (a folder of pictures),
``calibrate cameras --intrinsics/--extrinsics`` picture folders, and the videos ``mocapd eval video`` reads.
OpenCV's decoders open files by name and were handed any name: a FIFO named ``0001.png`` in an image folder, or
given as the video, made ``imread``/``VideoCapture`` wait for a writer forever (issue 34); a multi-gigabyte
"picture" was read whole. Here a media file is first opened without blocking and checked on its descriptor (a
regular file, at most :data:`MAX_IMAGE_BYTES` or :data:`MAX_VIDEO_BYTES`); a picture is then read from that
descriptor with bounded memory and decoded from the bytes (``imdecode``), and FFmpeg is given
``/proc/self/fd/N`` — the file that was checked, not whatever the name points to a moment later. A file that is
not a picture or video the decoders read is one line naming it (``InputError``, or the caller's class).

Not bounded here: the pixels a small compressed picture declares (OpenCV refuses more than 2³⁰ pixels itself).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from mocapd.errors import InputError, MocapdError
from mocapd.io.input_files import GiB, MiB, checked_fd, read_input_bytes

MAX_IMAGE_BYTES = 512 * MiB
"""Largest picture file read (an uncompressed 16-bit 8K TIFF is about 400 MiB)."""
MAX_VIDEO_BYTES = 1024 * GiB
"""Largest video file opened (hours of high-bitrate 4K; FFmpeg streams it, so this bounds damage, not memory)."""


def read_image(
    path: str | Path, what: str = "image", *, max_bytes: int = MAX_IMAGE_BYTES, error: type[MocapdError] = InputError
) -> np.ndarray:
    """A picture file as BGR (H, W, 3) uint8, read through the checks of :func:`~mocapd.io.input_files.open_input`.

    Raises
    ------
    error
        Missing, not a regular file, larger than ``max_bytes``, unreadable, or not a picture OpenCV decodes.
    """
    data = read_input_bytes(path, what, max_bytes=max_bytes, error=error)
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR) if data else None
    if image is None:
        raise error(f"{what} {path}: cannot decode (not a picture OpenCV reads: {', '.join(_IMAGE_KINDS)})")
    return np.asarray(image, np.uint8)


_IMAGE_KINDS = ("PNG", "JPEG", "BMP", "TIFF")


def open_video(
    path: str | Path, what: str = "video", *, max_bytes: int = MAX_VIDEO_BYTES, error: type[MocapdError] = InputError
) -> Any:
    """An opened ``cv2.VideoCapture`` of a checked video file (the caller releases it).

    Raises
    ------
    error
        Missing, not a regular file, larger than ``max_bytes``, or not a video OpenCV/FFmpeg opens.
    """
    fd = checked_fd(path, what, max_bytes=max_bytes, error=error)
    try:
        cap = cv2.VideoCapture(f"/proc/self/fd/{fd}")  # FFmpeg opens its own descriptor of the checked file
    finally:
        os.close(fd)
    if not cap.isOpened():
        cap.release()
        raise error(f"{what} {path}: cannot open (not a video OpenCV/FFmpeg reads?)")
    return cap
