"""Camera pixel formats, their conversion into an image, and the capture ring of a format.

Supported formats (GenICam PFNC names): ``Mono8`` → 1 channel; ``RGB8`` → 3 channels (R, G, B);
``BayerRG8``, ``BayerBG8``, ``BayerGR8``, ``BayerGB8`` → demosaiced by OpenCV into 3 channels (R, G, B).

OpenCV names a Bayer pattern after the second row's first two pixels, GenICam after the first row's: GenICam
``BayerRG8`` (R at pixel (0, 0)) is OpenCV's ``COLOR_BayerBG2RGB``. ``tests/test_pixels.py`` checks this on a
mosaic made by hand.

A Bayer camera's ring (:func:`capture_ring`) is lazy: capture copies the mosaic (one byte a pixel) into the ring
and demosaicing happens when something reads the frame (the detector, a camera panel, the recorder), once per
frame read. ``Mono8`` and ``RGB8`` need no conversion beyond the copy, which capture does straight into the image.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from mocapd.errors import ConfigError, InputError
from mocapd.pipeline.frame_ring import FrameRing, block_mean


@dataclass(frozen=True)
class PixelFormat:
    """A pixel format mocapd can capture.

    Attributes
    ----------
    name : str
        GenICam name, e.g. ``"BayerRG8"``.
    bytes_per_pixel : int
        Bytes per pixel in the camera buffer.
    channels : int
        Channels per pixel in the ring buffer (1 or 3).
    cv_code : int or None
        OpenCV demosaicing code for Bayer formats, None otherwise.
    """

    name: str
    bytes_per_pixel: int
    channels: int
    cv_code: int | None = None


PIXEL_FORMATS: dict[str, PixelFormat] = {
    "Mono8": PixelFormat("Mono8", 1, 1),
    "RGB8": PixelFormat("RGB8", 3, 3),
    "BayerRG8": PixelFormat("BayerRG8", 1, 3, cv2.COLOR_BayerBG2RGB),
    "BayerBG8": PixelFormat("BayerBG8", 1, 3, cv2.COLOR_BayerRG2RGB),
    "BayerGR8": PixelFormat("BayerGR8", 1, 3, cv2.COLOR_BayerGB2RGB),
    "BayerGB8": PixelFormat("BayerGB8", 1, 3, cv2.COLOR_BayerGR2RGB),
}


# OpenCV's demosaic-to-gray code of each demosaic-to-RGB code above.
_BAYER_GRAY = {
    cv2.COLOR_BayerBG2RGB: cv2.COLOR_BayerBG2GRAY,
    cv2.COLOR_BayerRG2RGB: cv2.COLOR_BayerRG2GRAY,
    cv2.COLOR_BayerGB2RGB: cv2.COLOR_BayerGB2GRAY,
    cv2.COLOR_BayerGR2RGB: cv2.COLOR_BayerGR2GRAY,
}


def pixel_format(name: str) -> PixelFormat:
    """Look up a supported pixel format by its GenICam name.

    Raises
    ------
    ConfigError
        If the format is not supported, listing the supported ones.
    """
    try:
        return PIXEL_FORMATS[name]
    except KeyError:
        raise ConfigError(f"pixel format {name!r} is not supported; use one of {sorted(PIXEL_FORMATS)}") from None


def convert_into(fmt: PixelFormat, raw: NDArray[np.uint8], height: int, width: int, out: NDArray[np.uint8]) -> None:
    """Convert one raw camera buffer into a ring slot (the frame's only copy).

    Parameters
    ----------
    fmt : PixelFormat
        Format of ``raw``.
    raw : ndarray, shape (n_bytes,), uint8
        The camera buffer (a zero-copy view); at least ``height * width * fmt.bytes_per_pixel`` bytes.
    height, width : int
        Image size in pixels.
    out : ndarray, shape (height, width, fmt.channels), uint8
        Destination slot, written in place.
    """
    n = height * width * fmt.bytes_per_pixel
    if raw.size < n or out.shape != (height, width, fmt.channels):
        raise InputError(
            f"{fmt.name}: buffer of {raw.size} bytes / slot {out.shape} do not fit a {width}x{height} image"
        )
    if fmt.cv_code is None:
        np.copyto(out, raw[:n].reshape(height, width, fmt.channels))
    else:
        cv2.cvtColor(raw[:n].reshape(height, width), fmt.cv_code, dst=out)


def capture_ring(name: str, n_slots: int, height: int, width: int, fmt: PixelFormat) -> FrameRing:
    """The ring a camera delivering ``fmt`` captures into: lazy (raw mosaic, demosaiced when read) for Bayer
    formats, eager (the copy is the conversion) for ``Mono8`` and ``RGB8``."""
    if fmt.cv_code is None:
        return FrameRing(name, n_slots, height, width, fmt.channels)

    def demosaic(raw: NDArray[np.uint8], out: NDArray[np.uint8]) -> None:
        convert_into(fmt, raw, height, width, out)

    def gray(raw: NDArray[np.uint8], factor: int) -> NDArray[np.uint8]:
        return bayer_gray(fmt, raw, height, width, factor)

    return FrameRing(name, n_slots, height, width, fmt.channels, raw_shape=(height * width * fmt.bytes_per_pixel,),
                     convert=demosaic, gray=gray)  # fmt: skip


def bayer_gray(fmt: PixelFormat, raw: NDArray[np.uint8], height: int, width: int, factor: int) -> NDArray[np.uint8]:
    """A Bayer mosaic as a gray image downsampled by ``factor`` (for the keypoint tracker).

    An even factor averages whole 2x2 cells of the mosaic, (R + 2G + B) / 4 each: a luminance image with no
    demosaicing (one area resize, ~0.05 ms for 544x960). Factor 1 (or odd) demosaics straight to gray.

    Returns
    -------
    ndarray, shape (height // factor, width // factor), uint8
    """
    if fmt.cv_code is None:
        raise InputError(f"{fmt.name} is not a Bayer format")
    mosaic = raw[: height * width].reshape(height, width)
    if factor % 2 == 0:
        return block_mean(mosaic, factor)
    code = _BAYER_GRAY[fmt.cv_code]
    return block_mean(np.asarray(cv2.cvtColor(mosaic, code), np.uint8), factor)


def bgr_ring(name: str, n_slots: int, height: int, width: int, *, gray: bool = False) -> FrameRing:
    """The lazy ring of a decoder's frames (video file, image folder, webcam): raw slots hold the decoder's BGR
    image, shape (height, width, 3), converted to RGB (or gray, 1 channel) when read."""
    code = cv2.COLOR_BGR2GRAY if gray else cv2.COLOR_BGR2RGB

    def convert(bgr: NDArray[np.uint8], out: NDArray[np.uint8]) -> None:
        cv2.cvtColor(bgr, code, dst=out[:, :, 0] if gray else out)

    def to_gray(bgr: NDArray[np.uint8], factor: int) -> NDArray[np.uint8]:
        return block_mean(np.asarray(cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY), np.uint8), factor)

    return FrameRing(name, n_slots, height, width, 1 if gray else 3, raw_shape=(height, width, 3), convert=convert,
                     gray=to_gray)  # fmt: skip


def store_raw(fmt: PixelFormat, raw: NDArray[np.uint8], height: int, width: int, ring: FrameRing) -> None:
    """Put one camera buffer into the ring's next slot: its bytes as they are (lazy ring) or converted (eager).

    Parameters
    ----------
    fmt : PixelFormat
        Format of ``raw``.
    raw : ndarray, shape (n_bytes,), uint8
        The camera buffer (a zero-copy view); at least ``height * width * fmt.bytes_per_pixel`` bytes.
    height, width : int
        Image size in pixels.
    ring : FrameRing
        Of shape (height, width, fmt.channels); call its ``publish`` next.
    """
    if not ring.lazy:
        convert_into(fmt, raw, height, width, ring.next_slot())
        return
    slot = ring.next_raw()
    n = height * width * fmt.bytes_per_pixel
    if raw.size < n or slot.shape != (n,):
        raise InputError(
            f"{fmt.name}: buffer of {raw.size} bytes / raw slot {slot.shape} do not fit a {width}x{height} image"
        )
    np.copyto(slot, raw[:n])


def mosaic(rgb: NDArray[np.uint8], fmt: PixelFormat) -> NDArray[np.uint8]:
    """Sample an RGB image into a Bayer mosaic (what a Bayer sensor would deliver), for fakes and tests.

    Parameters
    ----------
    rgb : ndarray, shape (h, w, 3), uint8
    fmt : PixelFormat
        A Bayer format.

    Returns
    -------
    ndarray, shape (h, w), uint8
    """
    if fmt.cv_code is None:
        raise InputError(f"{fmt.name} is not a Bayer format")
    pattern = fmt.name[5:7] + {"RG": "GB", "BG": "GR", "GR": "BG", "GB": "RG"}[fmt.name[5:7]]
    channel = {"R": 0, "G": 1, "B": 2}
    out = np.empty(rgb.shape[:2], np.uint8)
    for dy in (0, 1):
        for dx in (0, 1):
            out[dy::2, dx::2] = rgb[dy::2, dx::2, channel[pattern[2 * dy + dx]]]
    return out


def from_rgb(rgb: NDArray[np.uint8], fmt: PixelFormat) -> NDArray[np.uint8]:
    """Encode an RGB image, shape (h, w, 3), as the raw bytes a camera sends in format ``fmt``.

    Returns
    -------
    ndarray, shape (h * w * fmt.bytes_per_pixel,), uint8
    """
    if fmt.name == "RGB8":
        return np.ascontiguousarray(rgb).reshape(-1)
    if fmt.name == "Mono8":
        return np.ascontiguousarray(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), dtype=np.uint8).reshape(-1)
    return mosaic(rgb, fmt).reshape(-1)
