"""FrameRing: slots, sequence numbers, overwrite detection."""

from __future__ import annotations

import numpy as np
import pytest

from mocapd.errors import InputError
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
