"""Replay sources with the same interface as a camera: a video file and a folder of images.

Both are :class:`~mocapd.io.frame_source.ThreadedSource`: one thread decodes frames into a lazy ring and hands
:class:`~mocapd.pipeline.frame_ring.FrameRef` to asyncio. The ring keeps the decoder's BGR image (a video is decoded
straight into the ring's raw slot) and converts it to RGB (or gray with ``gray=True``) only when the frame is read.
Per frame:

* ``host_ns``: ``time.monotonic_ns()`` when the frame was published;
* ``device_ns``: the frame's presentation time in ns from the start of the file (video timestamps, or
  ``index / fps`` for images);
* ``frame_id``: the frame's index in the file or folder.

``realtime=True`` paces frames on their presentation times (a replay behaves like a live camera);
``realtime=False`` delivers them as fast as they decode. ``run`` returns at the end unless ``loop=True``.

Files are opened through :mod:`mocapd.io.media_files` (regular files of bounded size: a FIFO among the pictures is
one line, not a wait; a picture is decoded only once its header declares the first picture's size).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from mocapd.errors import DeviceError, InputError
from mocapd.io.frame_source import ThreadedSource
from mocapd.io.media_files import open_video, read_image
from mocapd.io.pixels import bgr_ring
from mocapd.pipeline.frame_ring import FrameRef

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


class _ReplaySource(ThreadedSource):
    """Pacing and publishing shared by the file and folder sources."""

    def __init__(
        self,
        name: str,
        height: int,
        width: int,
        *,
        gray: bool,
        realtime: bool,
        loop: bool,
        ring_slots: int,
        **kw: Any,
    ) -> None:
        super().__init__(name, bgr_ring(name, ring_slots, height, width, gray=gray), **kw)
        self.gray = gray
        self.realtime = realtime
        self.loop = loop
        self._start_ns = 0
        self._offset_ns = 0  # presentation time added per loop so device_ns keeps increasing

    def _publish(self, bgr: NDArray[np.uint8], index: int, pts_ns: int) -> FrameRef:
        """Publish the decoded frame ``bgr`` (h, w, 3): decoded into the ring's raw slot already, or copied there."""
        slot = self.ring.next_raw()
        if bgr.shape != slot.shape:
            raise DeviceError(f"{self.name}: frame {index} is {bgr.shape[1]}x{bgr.shape[0]}, not like the first")
        pts_ns += self._offset_ns
        if self.realtime and self._start_ns:
            delay = self._start_ns + pts_ns - time.monotonic_ns()
            if delay > 0:
                time.sleep(delay / 1e9)
        t0 = time.monotonic_ns()
        if not np.shares_memory(bgr, slot):
            np.copyto(slot, bgr)
        now = time.monotonic_ns()
        if self._start_ns == 0:  # the clock starts when the first frame is published, so none is ever early
            self._start_ns = now - pts_ns
        ref = self.ring.publish(now, pts_ns, index)
        self.convert.add(now - t0)
        self.counters.frames += 1
        return ref


class VideoFileSource(_ReplaySource):
    """Frames of a video file (anything OpenCV/FFmpeg decodes).

    Parameters
    ----------
    name : str
    path : Path
    realtime : bool
        Pace on the video's timestamps (True) or as fast as possible (False).
    loop : bool
        Start again at the end instead of finishing.
    gray : bool
        Store 1-channel gray frames instead of RGB.
    ring_slots : int
    """

    def __init__(
        self,
        name: str,
        path: Path,
        *,
        realtime: bool = True,
        loop: bool = False,
        gray: bool = False,
        ring_slots: int = 16,
        **kw: Any,
    ) -> None:
        self.path = Path(path)
        cap = open_video(self.path)
        ok, first = cap.read()
        self.fps = float(cap.get(cv2.CAP_PROP_FPS)) or 30.0
        cap.release()
        if not ok or first is None:
            raise InputError(f"cannot decode a frame of video {self.path}")
        super().__init__(
            name,
            first.shape[0],
            first.shape[1],
            gray=gray,
            realtime=realtime,
            loop=loop,
            ring_slots=ring_slots,
            **kw,
        )
        self._cap: Any = None
        self._index = 0

    def _open(self) -> None:
        self._cap = open_video(self.path, error=DeviceError)
        self._index = 0
        self._start_ns = 0

    def _grab(self) -> FrameRef | bool | None:
        # Decoded straight into the ring's raw slot (OpenCV writes into a given array of the right size).
        ok, bgr = self._cap.read(self.ring.next_raw())
        if not ok:
            if not self.loop or self._index == 0:
                return False
            self._offset_ns += round(self._index * 1e9 / self.fps)
            self._cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
            self._index = 0
            return None
        # Presentation time from the frame index: container timestamps of some files are unreliable.
        ref = self._publish(bgr, self._index, round(self._index * 1e9 / self.fps))
        self._index += 1
        return ref

    def _close(self) -> None:
        if self._cap is not None:
            self._cap.release()
        self._cap = None


class ImageFolderSource(_ReplaySource):
    """Images of a folder in name order, presented at ``fps``.

    Parameters
    ----------
    name : str
    folder : Path
    fps : float
        Presentation rate in Hz.
    realtime, loop, gray, ring_slots
        As for :class:`VideoFileSource`.
    """

    def __init__(
        self,
        name: str,
        folder: Path,
        *,
        fps: float = 30.0,
        realtime: bool = True,
        loop: bool = False,
        gray: bool = False,
        ring_slots: int = 16,
        **kw: Any,
    ) -> None:
        self.files = sorted(p for p in Path(folder).iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not self.files:
            raise InputError(f"{folder} holds no image ({', '.join(IMAGE_SUFFIXES)})")
        first = read_image(self.files[0])
        if fps <= 0:
            raise InputError(f"fps must be positive, got {fps}")
        super().__init__(
            name,
            first.shape[0],
            first.shape[1],
            gray=gray,
            realtime=realtime,
            loop=loop,
            ring_slots=ring_slots,
            **kw,
        )
        self.fps = fps
        self.size = (int(first.shape[1]), int(first.shape[0]))
        """(width, height) of the first picture: every picture's size."""
        self._index = 0

    def _open(self) -> None:
        self._index = 0
        self._start_ns = 0

    def _grab(self) -> FrameRef | bool | None:
        if self._index == len(self.files):
            if not self.loop:
                return False
            self._offset_ns += round(self._index * 1e9 / self.fps)
            self._index = 0
        path = self.files[self._index]
        # Its header first: a picture declaring another size than the first (a decompression bomb among them) is
        # refused before it is decoded, not after (issue 45: 19 GB for a PNG declaring 32767x32767).
        bgr = read_image(path, size=self.size, error=DeviceError)
        ref = self._publish(bgr, self._index, round(self._index * 1e9 / self.fps))
        self._index += 1
        return ref

    def _close(self) -> None:
        self._index = 0
