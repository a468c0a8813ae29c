"""Pixel formats: Bayer naming (GenICam vs OpenCV), conversion into ring slots."""

from __future__ import annotations

import numpy as np
import pytest

from mocapd.errors import ConfigError, InputError
from mocapd.io.pixels import convert_into, from_rgb, mosaic, pixel_format

PATTERNS = {"BayerRG8": "RGGB", "BayerBG8": "BGGR", "BayerGR8": "GRBG", "BayerGB8": "GBRG"}


@pytest.mark.parametrize("name", sorted(PATTERNS))
def test_bayer_demosaic_keeps_uniform_colour(name: str) -> None:
    # A mosaic made by hand from the GenICam pattern (first row first): a uniform colour must come back as is.
    rgb = np.zeros((8, 10, 3), np.uint8)
    rgb[...] = (200, 100, 30)
    channel = {"R": 0, "G": 1, "B": 2}
    raw = np.empty((8, 10), np.uint8)
    pattern = PATTERNS[name]
    for dy in (0, 1):
        for dx in (0, 1):
            raw[dy::2, dx::2] = rgb[dy::2, dx::2, channel[pattern[2 * dy + dx]]]
    fmt = pixel_format(name)
    assert np.array_equal(mosaic(rgb, fmt), raw)
    out = np.zeros((8, 10, 3), np.uint8)
    convert_into(fmt, raw.reshape(-1), 8, 10, out)
    assert np.array_equal(out[2:-2, 2:-2], rgb[2:-2, 2:-2])


def test_mono_and_rgb_copy_exactly() -> None:
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (6, 4, 3), dtype=np.uint8)
    out = np.zeros((6, 4, 3), np.uint8)
    convert_into(pixel_format("RGB8"), from_rgb(rgb, pixel_format("RGB8")), 6, 4, out)
    assert np.array_equal(out, rgb)
    mono = np.zeros((6, 4, 1), np.uint8)
    raw = from_rgb(rgb, pixel_format("Mono8"))
    convert_into(pixel_format("Mono8"), raw, 6, 4, mono)
    assert np.array_equal(mono[:, :, 0], raw.reshape(6, 4))


def test_errors() -> None:
    with pytest.raises(ConfigError, match="Mono8"):
        pixel_format("YUV422")
    with pytest.raises(InputError, match="do not fit"):
        convert_into(pixel_format("RGB8"), np.zeros(10, np.uint8), 6, 4, np.zeros((6, 4, 3), np.uint8))
    with pytest.raises(InputError, match="not a Bayer"):
        mosaic(np.zeros((2, 2, 3), np.uint8), pixel_format("Mono8"))
