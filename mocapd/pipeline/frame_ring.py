"""A preallocated ring of video frames with their timestamps (one ring per camera).

The capture thread of a camera is the only writer; readers (detector workers, the scheduler) run on the asyncio
loop or in their own threads. Every slot is allocated once, so capture never allocates per frame: the camera's
buffer is converted/copied straight into ``images[slot]``.

A frame is addressed by its sequence number ``seq`` (0, 1, 2, ... in the order written). The slot of ``seq`` is
``seq % n_slots``; it stays valid until ``n_slots`` newer frames have been written. Readers that hold a sequence
number check :meth:`FrameRing.is_valid` (or use :meth:`FrameRing.read`, which copies and re-checks) because a slow
reader can be overtaken by the writer.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mocapd.errors import InputError


@dataclass(frozen=True, slots=True)
class FrameRef:
    """Where to find one captured frame.

    Attributes
    ----------
    source : str
        Name of the camera (or replay source) that produced the frame.
    seq : int
        Sequence number in the source's ring (0-based, increments by one per written frame).
    host_ns : int
        Host time at which the frame was complete, ``time.monotonic_ns()``.
    device_ns : int
        The camera's own timestamp in ns (device clock; for files: presentation time).
    frame_id : int
        The camera's frame (block) id; GigE Vision ids are 16-bit and skip 0 when they wrap.
    """

    source: str
    seq: int
    host_ns: int
    device_ns: int
    frame_id: int


class FrameRing:
    """Fixed-size ring of frames, shape ``(n_slots, height, width, channels)``, dtype uint8.

    Parameters
    ----------
    name : str
        Name of the source writing into the ring.
    n_slots : int
        Number of frames kept (>= 2).
    height, width, channels : int
        Frame geometry; ``channels`` is 1 (mono) or 3 (RGB).
    """

    def __init__(self, name: str, n_slots: int, height: int, width: int, channels: int) -> None:
        if n_slots < 2 or height < 1 or width < 1 or channels not in (1, 3):
            raise InputError(
                f"FrameRing({name!r}): need n_slots >= 2, positive size and 1 or 3 channels, "
                f"got n_slots={n_slots}, size={width}x{height}, channels={channels}"
            )
        self.name = name
        self.n_slots = n_slots
        self.images: NDArray[np.uint8] = np.zeros((n_slots, height, width, channels), np.uint8)
        self.host_ns: NDArray[np.int64] = np.zeros(n_slots, np.int64)
        self.device_ns: NDArray[np.int64] = np.zeros(n_slots, np.int64)
        self.frame_id: NDArray[np.int64] = np.zeros(n_slots, np.int64)
        self._count = 0  # frames published so far; the next frame gets seq == _count
        self._lock = threading.Lock()

    @property
    def shape(self) -> tuple[int, int, int]:
        """Frame shape ``(height, width, channels)``."""
        _, h, w, c = self.images.shape
        return (h, w, c)

    @property
    def count(self) -> int:
        """Number of frames written so far (the next frame's sequence number)."""
        return self._count

    def next_slot(self) -> NDArray[np.uint8]:
        """The image array the writer fills next, shape ``(height, width, channels)``.

        Write into it, then call :meth:`publish`. Until then readers never see the slot as the newest frame.
        """
        slot: NDArray[np.uint8] = self.images[self._count % self.n_slots]
        return slot

    def publish(self, host_ns: int, device_ns: int, frame_id: int) -> FrameRef:
        """Mark the slot returned by :meth:`next_slot` as written and return its reference."""
        with self._lock:
            seq = self._count
            slot = seq % self.n_slots
            self.host_ns[slot] = host_ns
            self.device_ns[slot] = device_ns
            self.frame_id[slot] = frame_id
            self._count = seq + 1
        return FrameRef(self.name, seq, host_ns, device_ns, frame_id)

    def is_valid(self, seq: int) -> bool:
        """Whether frame ``seq`` is still in the ring (written and not yet overwritten).

        The writer may be filling slot ``count % n_slots``, i.e. the one of ``count - n_slots``, so only the
        ``n_slots - 1`` newest frames are guaranteed stable.
        """
        count = self._count
        return 0 <= seq < count and count - seq < self.n_slots

    def view(self, seq: int) -> NDArray[np.uint8]:
        """The image of frame ``seq`` without copying, shape ``(height, width, channels)``.

        Raises
        ------
        InputError
            If the frame is not in the ring any more (or not yet).
        """
        if not self.is_valid(seq):
            raise InputError(f"frame {seq} of {self.name!r} is not in the ring (count={self._count})")
        image: NDArray[np.uint8] = self.images[seq % self.n_slots]
        return image

    def read(self, seq: int) -> NDArray[np.uint8] | None:
        """A copy of frame ``seq``, or None if the writer overtook the reader during the copy."""
        if not self.is_valid(seq):
            return None
        out = self.images[seq % self.n_slots].copy()
        return out if self.is_valid(seq) else None

    def latest(self) -> FrameRef | None:
        """Reference of the newest frame, or None before the first one."""
        with self._lock:
            seq = self._count - 1
            if seq < 0:
                return None
            slot = seq % self.n_slots
            return FrameRef(
                self.name,
                seq,
                int(self.host_ns[slot]),
                int(self.device_ns[slot]),
                int(self.frame_id[slot]),
            )
