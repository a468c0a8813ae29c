"""A preallocated ring of video frames with their timestamps (one ring per camera).

The capture thread of a camera is the only writer; readers (detector workers, the viewer's camera panels, the
recorder) run on the asyncio loop or in their own threads. Every slot is allocated once, so capture never
allocates per frame.

Eager and lazy rings. An *eager* ring (no ``convert``) holds finished images: the writer fills ``images[slot]``
(:meth:`FrameRing.next_slot`). A *lazy* ring keeps what the source delivered, unconverted, in ``raw[slot]``
(:meth:`FrameRing.next_raw`: a Bayer mosaic, a decoder's BGR image) and converts a frame into ``images[slot]`` when
a reader first asks for it, once: the converted image is cached for the frame, so the detector and a camera panel
reading the same frame pay one conversion (counted in :attr:`FrameRing.conversions`). A camera sends 60 frames a
second and the detector reads one or two of them; converting (demosaicing) every frame at capture would spend the
capture thread's time on images nobody looks at. The conversion runs in the reader's thread.

Gray images for tracking. :meth:`FrameRing.gray` gives a frame as a gray image, optionally downsampled by an
integer factor (block means), for the keypoint tracker (:mod:`mocapd.pipeline.keypoint_tracker`) that runs on every
frame: a lazy ring makes it straight from the raw slot with the ring's own ``gray`` function (a Bayer mosaic
averaged over whole 2x2 cells *is* a half-size gray image: no demosaicing), else from the image.

A frame is addressed by its sequence number ``seq`` (0, 1, 2, ... in the order written). The slot of ``seq`` is
``seq % n_slots``; it stays valid until ``n_slots`` newer frames have been written. Readers that hold a sequence
number check :meth:`FrameRing.is_valid` (or use :meth:`FrameRing.read`, which copies and re-checks) because a slow
reader can be overtaken by the writer.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from mocapd.errors import InputError

#: fills a converted image ``out`` (height, width, channels) from one raw slot (the ring's ``raw_shape``)
Converter = Callable[[NDArray[np.uint8], NDArray[np.uint8]], None]
#: one slot (a lazy ring's raw slot, else the image) and a factor -> a gray image, shape (height // factor,
#: width // factor), each pixel the mean of a factor x factor block
GrayConverter = Callable[[NDArray[np.uint8], int], NDArray[np.uint8]]


def block_mean(image: NDArray[np.uint8], factor: int) -> NDArray[np.uint8]:
    """``image`` (h, w[, c]) downsampled by an integer ``factor``: each pixel the mean of a ``factor x factor``
    block (trailing rows and columns that make no whole block are dropped; 1 returns ``image`` itself)."""
    if factor == 1:
        return image
    if factor < 1:
        raise InputError(f"downsampling factor must be >= 1, got {factor}")
    h, w = image.shape[0] // factor, image.shape[1] // factor
    return np.asarray(cv2.resize(image[: h * factor, : w * factor], (w, h), interpolation=cv2.INTER_AREA), np.uint8)


def image_gray(image: NDArray[np.uint8], factor: int = 1) -> NDArray[np.uint8]:
    """An RGB (h, w, 3) or mono (h, w, 1) image as gray, downsampled by ``factor`` (:func:`block_mean`)."""
    gray = image[:, :, 0] if image.shape[2] == 1 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    return block_mean(np.asarray(gray, np.uint8), factor)


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
    raw_shape : tuple of int, optional
        Shape of one raw slot of a lazy ring (what the source delivers, e.g. ``(height * width,)`` for a Bayer
        mosaic). Give it together with ``convert``.
    convert : callable, optional
        ``convert(raw_slot, out)`` turns one raw slot into an image, shape ``(height, width, channels)``, written
        into ``out`` (see :data:`Converter`). Given: the ring is lazy (see the module docstring).
    gray : callable, optional
        ``gray(slot, factor)``: the gray image of one slot (the raw slot of a lazy ring, else the image), see
        :data:`GrayConverter` and :meth:`gray`. Default: from the (converted) image.
    """

    def __init__(
        self,
        name: str,
        n_slots: int,
        height: int,
        width: int,
        channels: int,
        *,
        raw_shape: tuple[int, ...] | None = None,
        convert: Converter | None = None,
        gray: GrayConverter | None = None,
    ) -> None:
        if n_slots < 2 or height < 1 or width < 1 or channels not in (1, 3):
            raise InputError(
                f"FrameRing({name!r}): need n_slots >= 2, positive size and 1 or 3 channels, "
                f"got n_slots={n_slots}, size={width}x{height}, channels={channels}"
            )
        if (raw_shape is None) != (convert is None) or (raw_shape is not None and min(raw_shape, default=0) < 1):
            raise InputError(f"FrameRing({name!r}): a lazy ring needs both a positive raw_shape and convert")
        self.name = name
        self.n_slots = n_slots
        self.images: NDArray[np.uint8] = np.zeros((n_slots, height, width, channels), np.uint8)
        self.raw: NDArray[np.uint8] | None = None if raw_shape is None else np.zeros((n_slots, *raw_shape), np.uint8)
        self.host_ns: NDArray[np.int64] = np.zeros(n_slots, np.int64)
        self.device_ns: NDArray[np.int64] = np.zeros(n_slots, np.int64)
        self.frame_id: NDArray[np.int64] = np.zeros(n_slots, np.int64)
        self.conversions = 0  # frames converted from raw (lazy rings; each frame at most once while in the ring)
        self._convert = convert
        self._gray = gray
        # Sequence number of the frame whose image images[slot] holds (-1: none). An eager ring's writer fills the
        # image itself; a lazy ring's readers fill it on first use.
        self._converted: NDArray[np.int64] = np.full(n_slots, -1, np.int64)
        self._count = 0  # frames published so far; the next frame gets seq == _count
        self._lock = threading.Lock()
        # One conversion at a time per ring: two readers asking for the same frame convert it once.
        self._convert_lock = threading.Lock()

    @property
    def shape(self) -> tuple[int, int, int]:
        """Frame shape ``(height, width, channels)``."""
        _, h, w, c = self.images.shape
        return (h, w, c)

    @property
    def lazy(self) -> bool:
        """Whether frames are kept raw and converted when first read."""
        return self.raw is not None

    @property
    def count(self) -> int:
        """Number of frames written so far (the next frame's sequence number)."""
        return self._count

    def next_slot(self) -> NDArray[np.uint8]:
        """The image array the writer of an eager ring fills next, shape ``(height, width, channels)``.

        Write into it, then call :meth:`publish`. Until then readers never see the slot as the newest frame.

        Raises
        ------
        InputError
            If the ring is lazy (its writer fills :meth:`next_raw`).
        """
        if self.raw is not None:
            raise InputError(f"ring {self.name!r} is lazy: its writer fills next_raw(), not next_slot()")
        slot: NDArray[np.uint8] = self.images[self._count % self.n_slots]
        return slot

    def next_raw(self) -> NDArray[np.uint8]:
        """The raw slot the writer of a lazy ring fills next, shape ``raw_shape``; then call :meth:`publish`.

        Raises
        ------
        InputError
            If the ring is eager (its writer fills :meth:`next_slot`).
        """
        if self.raw is None:
            raise InputError(f"ring {self.name!r} is eager: its writer fills next_slot(), not next_raw()")
        slot: NDArray[np.uint8] = self.raw[self._count % self.n_slots]
        return slot

    def publish(self, host_ns: int, device_ns: int, frame_id: int) -> FrameRef:
        """Mark the slot returned by :meth:`next_slot` / :meth:`next_raw` as written and return its reference."""
        with self._lock:
            seq = self._count
            slot = seq % self.n_slots
            self.host_ns[slot] = host_ns
            self.device_ns[slot] = device_ns
            self.frame_id[slot] = frame_id
            self._converted[slot] = -1 if self.raw is not None else seq
            self._count = seq + 1
        return FrameRef(self.name, seq, host_ns, device_ns, frame_id)

    def is_valid(self, seq: int) -> bool:
        """Whether frame ``seq`` is still in the ring (written and not yet overwritten).

        The writer may be filling slot ``count % n_slots``, i.e. the one of ``count - n_slots``, so only the
        ``n_slots - 1`` newest frames are guaranteed stable.
        """
        count = self._count
        return 0 <= seq < count and count - seq < self.n_slots

    def _image(self, seq: int) -> NDArray[np.uint8] | None:
        """The image of frame ``seq`` in its slot, converted now if it is the first time it is asked for; None if
        the frame is not in the ring (or the writer overtook the conversion)."""
        if not self.is_valid(seq):
            return None
        slot = seq % self.n_slots
        if self._converted[slot] != seq:  # a lazy ring's frame nobody read yet (or a frame just overwritten)
            raw, convert = self.raw, self._convert
            if raw is None or convert is None:  # eager: the writer has already reused the slot
                return None
            with self._convert_lock:
                if self._converted[slot] != seq:  # another reader may have converted it while this one waited
                    self._converted[slot] = -1
                    convert(raw[slot], self.images[slot])
                    self.conversions += 1
                    if not self.is_valid(seq):  # the writer refilled the raw slot during the conversion
                        return None
                    self._converted[slot] = seq
        image: NDArray[np.uint8] = self.images[slot]
        return image

    def view(self, seq: int) -> NDArray[np.uint8]:
        """The image of frame ``seq`` without copying, shape ``(height, width, channels)`` (converted first if
        the ring is lazy and nobody read the frame yet). Valid while :meth:`is_valid` holds.

        Raises
        ------
        InputError
            If the frame is not in the ring any more (or not yet).
        """
        image = self._image(seq)
        if image is None:
            raise InputError(f"frame {seq} of {self.name!r} is not in the ring (count={self._count})")
        return image

    def read(self, seq: int) -> NDArray[np.uint8] | None:
        """A copy of frame ``seq`` (converted first if the ring is lazy and nobody read the frame yet), or None if
        the writer overtook the reader during the conversion or the copy."""
        image = self._image(seq)
        if image is None:
            return None
        out = image.copy()
        return out if self.is_valid(seq) else None

    def gray(self, seq: int, factor: int = 1) -> NDArray[np.uint8] | None:
        """Frame ``seq`` as a new gray image downsampled by ``factor``, shape (height // factor, width // factor),
        or None if the frame is not in the ring (or the writer overtook the conversion). A lazy ring with a
        ``gray`` function makes it from the raw slot without converting the frame."""
        if not self.is_valid(seq):
            return None
        if self._gray is not None:
            slot = seq % self.n_slots
            out = self._gray(self.raw[slot] if self.raw is not None else self.images[slot], factor)
        else:
            image = self._image(seq)
            if image is None:
                return None
            out = image_gray(image, factor)
        if out.base is not None or not out.flags.owndata:
            out = out.copy()  # never a view of a slot the writer will refill
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
