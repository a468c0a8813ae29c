"""FrameRing: slots, sequence numbers, overwrite detection; lazy rings convert a frame when first read, once."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from mocapd.errors import InputError
from mocapd.io.pixels import capture_ring, convert_into, from_rgb, pixel_format
from mocapd.pipeline.frame_ring import FrameRing


def test_publish_and_read_back() -> None:
    ring = FrameRing("cam", 3, 2, 4, 3)
    assert ring.latest() is None
    for i in range(5):
        ring.next_slot()[:] = i
        ref = ring.publish(100 + i, 1000 + i, 7 + i)
        assert (ref.seq, ref.host_ns, ref.device_ns, ref.frame_id, ref.source) == (
            i,
            100 + i,
            1000 + i,
            7 + i,
            "cam",
        )
    assert ring.count == 5
    latest = ring.latest()
    assert latest is not None and latest.seq == 4 and latest.frame_id == 11
    image = ring.read(4)
    assert image is not None and np.all(image == 4) and image.shape == (2, 4, 3)
    # Only the n_slots - 1 newest frames are stable: the writer may be filling the oldest slot.
    assert ring.is_valid(3) and not ring.is_valid(2) and not ring.is_valid(5)
    assert ring.read(1) is None
    with pytest.raises(InputError, match="not in the ring"):
        ring.view(0)


def test_rejects_bad_geometry() -> None:
    with pytest.raises(InputError, match="n_slots"):
        FrameRing("cam", 1, 2, 2, 3)
    with pytest.raises(InputError, match="channels"):
        FrameRing("cam", 4, 2, 2, 2)


class _Doubling:
    """A converter that counts its calls: image = 2 * raw (one channel per raw byte)."""

    def __init__(self) -> None:
        self.calls = 0

    def __call__(self, raw: np.ndarray, out: np.ndarray) -> None:
        self.calls += 1
        out[...] = (2 * raw).reshape(out.shape)


def test_lazy_ring_converts_only_the_frames_read_once_each() -> None:
    convert = _Doubling()
    ring = FrameRing("cam", 4, 2, 3, 1, raw_shape=(6,), convert=convert)
    for i in range(10):
        ring.next_raw()[:] = i
        ring.publish(i, i, i)
    assert convert.calls == 0 and ring.conversions == 0  # nobody read: nothing converted
    image = ring.read(8)
    assert image is not None and np.all(image == 16) and image.shape == (2, 3, 1)
    assert np.all(ring.view(8) == 16) and ring.read(8) is not None
    assert convert.calls == ring.conversions == 1  # read three times, converted once
    assert np.all(ring.view(7) == 14) and ring.conversions == 2
    assert ring.read(5) is None and ring.conversions == 2  # overwritten frames are not converted
    # The writer reuses the slot of frame 7: frame 11's image is its own conversion, not frame 7's cache.
    ring.next_raw()[:] = 11
    ring.publish(10, 10, 10)
    ring.next_raw()[:] = 11
    ring.publish(11, 11, 11)
    assert np.all(ring.view(11) == 22) and ring.conversions == 3


def test_lazy_and_eager_rings_are_filled_through_their_own_slots() -> None:
    lazy = FrameRing("cam", 2, 2, 2, 3, raw_shape=(4,), convert=_Doubling())
    eager = FrameRing("cam", 2, 2, 2, 3)
    assert lazy.lazy and not eager.lazy
    with pytest.raises(InputError, match="lazy"):
        lazy.next_slot()
    with pytest.raises(InputError, match="eager"):
        eager.next_raw()
    with pytest.raises(InputError, match="both"):
        FrameRing("cam", 2, 2, 2, 3, raw_shape=(4,))


@pytest.mark.parametrize("name", ["BayerRG8", "BayerGB8", "RGB8", "Mono8"])
def test_capture_ring_reads_what_eager_conversion_gives(name: str) -> None:
    fmt = pixel_format(name)
    rgb = np.random.default_rng(1).integers(0, 256, (6, 8, 3), dtype=np.uint8)
    raw = from_rgb(rgb, fmt)
    ring = capture_ring("cam", 3, 6, 8, fmt)
    assert ring.lazy == (name.startswith("Bayer"))  # Mono8 / RGB8: the copy is the conversion
    if ring.lazy:
        ring.next_raw()[:] = raw
    else:
        convert_into(fmt, raw, 6, 8, ring.next_slot())
    ref = ring.publish(0, 0, 0)
    eager = np.zeros((6, 8, fmt.channels), np.uint8)
    convert_into(fmt, raw, 6, 8, eager)
    got = ring.read(ref.seq)
    assert got is not None and np.array_equal(got, eager)


@pytest.mark.parametrize("name", ["BayerRG8", "BayerGB8", "RGB8", "Mono8"])
def test_gray_images_for_tracking(name: str) -> None:
    """``ring.gray``: a Bayer ring's half-size gray image is the mean of each 2x2 cell of the mosaic, (R + 2G + B)
    / 4, made without demosaicing the frame; full size and the other formats go through the image; a copy, never
    a view of the slot."""
    fmt = pixel_format(name)
    rng = np.random.default_rng(2)
    rgb = np.asarray(cv2.GaussianBlur(rng.integers(0, 256, (16, 20, 3), dtype=np.uint8), (5, 5), 0), np.uint8)
    raw = from_rgb(rgb, fmt)
    ring = capture_ring("cam", 3, 16, 20, fmt)
    if ring.lazy:
        ring.next_raw()[:] = raw
    else:
        convert_into(fmt, raw, 16, 20, ring.next_slot())
    ref = ring.publish(0, 0, 0)
    half = ring.gray(ref.seq, 2)
    assert half is not None and half.shape == (8, 10) and half.dtype == np.uint8
    assert ring.conversions == 0  # no frame was demosaiced for it
    full = ring.gray(ref.seq, 1)
    assert full is not None and full.shape == (16, 20)
    full[:] = 0
    again = ring.gray(ref.seq, 1)
    assert again is not None and again.any()  # a copy: writing to it leaves the ring alone
    if name.startswith("Bayer"):
        cells = raw.reshape(16, 20).astype(np.float64).reshape(8, 2, 10, 2).mean(axis=(1, 3))
        np.testing.assert_allclose(half, cells, atol=0.51)
    luma = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float64).reshape(8, 2, 10, 2).mean(axis=(1, 3))
    # Every format's half-size gray follows the scene's brightness (Bayer: the cell means' weights differ a little).
    assert np.abs(half - luma).mean() < (8 if name.startswith("Bayer") or name == "Mono8" else 1)
    for _ in range(3):
        (ring.next_raw() if ring.lazy else ring.next_slot())[:] = 0
        ring.publish(1, 1, 1)
    assert ring.gray(ref.seq, 2) is None  # overwritten
