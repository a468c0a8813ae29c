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

**Pixels before decoding** (issue 45). A small compressed picture can declare a huge one: a 3.1 MB PNG declaring
32767×32767 pixels made ``run`` decode 3 GB of BGR (19 GB peak RSS; OpenCV only refuses above 2³⁰ pixels) and
``calibrate cameras`` sit in C for minutes, deaf to Ctrl-C. So the size a picture *declares* is read from its header
first (Pillow's lazy open: the PNG IHDR, the JPEG SOF, the TIFF IFD, the BMP header; nothing decoded) and a picture
over :data:`MAX_IMAGE_PIXELS`, or not of the size its caller expects (every picture of an image folder is the size
of its first), is one line naming it and is never decoded. A picture whose header Pillow cannot read is refused the
same way: its size would be known only by decoding it.
"""

from __future__ import annotations

import io
import os
import struct
import warnings
from pathlib import Path
from typing import IO, Any

import cv2
import numpy as np
from PIL import Image, UnidentifiedImageError

from mocapd.errors import InputError, MocapdError
from mocapd.io.input_files import GiB, MiB, checked_fd, read_input_bytes
from mocapd.io.native_logs import quiet_opencv

quiet_opencv()  # a damaged picture is said here once, not by libtiff in ten lines (issue 45)

MAX_IMAGE_BYTES = 512 * MiB
"""Largest picture file read (an uncompressed 16-bit 8K TIFF is about 400 MiB)."""
MAX_VIDEO_BYTES = 1024 * GiB
"""Largest video file opened (hours of high-bitrate 4K; FFmpeg streams it, so this bounds damage, not memory)."""
MAX_IMAGE_PIXELS = 1 << 26
"""Most pixels a picture may declare to be decoded: 67 Mpx (8192x8192; a 50 Mpx calibration photograph fits), whose
BGR image is 192 MiB."""

#: what Pillow raises on a header it cannot read (a damaged or truncated file, a format it does not know)
_HEADER_ERRORS = (UnidentifiedImageError, OSError, SyntaxError, ValueError, TypeError, EOFError, IndexError, KeyError,
                  struct.error)  # fmt: skip


def read_image(
    path: str | Path,
    what: str = "image",
    *,
    max_bytes: int = MAX_IMAGE_BYTES,
    max_pixels: int = MAX_IMAGE_PIXELS,
    size: tuple[int, int] | None = None,
    error: type[MocapdError] = InputError,
) -> np.ndarray:
    """A picture file as BGR (H, W, 3) uint8, read through the checks of :func:`~mocapd.io.input_files.open_input`,
    decoded only once its header declares at most ``max_pixels`` pixels (and ``size``, (width, height), if given:
    either way round, as an EXIF orientation turns it).

    Raises
    ------
    error
        Missing, not a regular file, larger than ``max_bytes``, unreadable, declaring more than ``max_pixels`` pixels
        or another size than ``size``, or not a picture OpenCV decodes.
    """
    data = read_input_bytes(path, what, max_bytes=max_bytes, error=error)
    check_declared_size(_declared_size(io.BytesIO(data), path, what, error), path, what, max_pixels, size, error)
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR) if data else None
    if image is None:
        raise error(f"{what} {path}: cannot decode (not a picture OpenCV reads: {', '.join(_IMAGE_KINDS)})")
    return np.asarray(image, np.uint8)


_IMAGE_KINDS = ("PNG", "JPEG", "BMP", "TIFF")


def picture_size(
    path: str | Path, what: str = "image", *, max_bytes: int = MAX_IMAGE_BYTES, error: type[MocapdError] = InputError
) -> tuple[int, int]:
    """(width, height) a picture file's header declares, without decoding it (and without reading more of the file
    than the header): what ``check-config`` checks every picture of an image folder with.

    Raises
    ------
    error
        Missing, not a regular file, larger than ``max_bytes``, or no header Pillow reads.
    """
    fd = checked_fd(path, what, max_bytes=max_bytes, error=error)
    with os.fdopen(fd, "rb") as fh:
        return _declared_size(fh, path, what, error)


def check_declared_size(
    declared: tuple[int, int],
    path: str | Path,
    what: str,
    max_pixels: int = MAX_IMAGE_PIXELS,
    size: tuple[int, int] | None = None,
    error: type[MocapdError] = InputError,
) -> None:
    """Raise ``error`` (one line) when a picture declaring ``declared`` (width, height) may not be decoded."""
    width, height = declared
    if width * height > max_pixels:
        raise error(
            f"{what} {path}: declares {width}x{height} pixels, more than the {max_pixels:,} a picture may have "
            "(not decoded)"
        )
    if size is not None and declared not in (size, size[::-1]):
        raise error(f"{what} {path}: declares {width}x{height} pixels, not {size[0]}x{size[1]} like the first")


def _declared_size(fh: IO[bytes], path: str | Path, what: str, error: type[MocapdError]) -> tuple[int, int]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", Image.DecompressionBombWarning)  # our bound is lower; said in one line
        try:
            with Image.open(fh, formats=_IMAGE_KINDS) as im:
                return int(im.size[0]), int(im.size[1])
        except Image.DecompressionBombError:
            # Pillow refuses at 2 x its MAX_IMAGE_PIXELS before telling the size: a picture far over any bound here.
            raise error(
                f"{what} {path}: declares more than {2 * (Image.MAX_IMAGE_PIXELS or 0):,} pixels (not decoded)"
            ) from None
        except _HEADER_ERRORS as exc:
            detail = (str(exc).splitlines() or [type(exc).__name__])[0]
            raise error(
                f"{what} {path}: cannot decode (not a picture whose size can be read: {', '.join(_IMAGE_KINDS)}; "
                f"{detail})"
            ) from None


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
