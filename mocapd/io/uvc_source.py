"""USB webcams (UVC) through OpenCV's ``VideoCapture``: the cameras most people already own.

One :class:`UvcSource` per camera, a :class:`~mocapd.io.frame_source.ThreadedSource`: its thread blocks in
``VideoCapture.read`` (which releases the GIL) decoding straight into the camera's lazy ring (BGR, converted to RGB
when the frame is read) and hands the frame to asyncio. On Linux the camera is opened through V4L2
(``/dev/videoN`` or a stable ``/dev/v4l/by-id/...`` path, or an index); resolution, frame rate and FOURCC are
requested before the first frame, and the size the driver really delivers must be the size the camera was
calibrated at, or the open fails naming both.

Time: ``host_ns`` is when ``read`` returned (a webcam has no exposure clock we can read portably); ``device_ns`` is
the driver's buffer timestamp (``CAP_PROP_POS_MSEC``: V4L2 stamps each buffer when its transfer started) when it
has one, else the host time.

A regular file given as ``device`` is opened through the very same path and played at its own frame rate, as a
webcam would deliver it: that is how the tests drive this source without a USB camera.
"""

from __future__ import annotations

import logging
import os
import stat
import time
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from mocapd.errors import ConfigError, DeviceError
from mocapd.io.frame_source import ThreadedSource
from mocapd.io.media_files import open_video
from mocapd.io.pixels import bgr_ring
from mocapd.pipeline.frame_ring import FrameRef

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class UvcCameraConfig:
    """How to open one webcam.

    Attributes
    ----------
    name : str
    device : int or str
        Index (0 = ``/dev/video0``) or path.
    width, height : int
        The size the camera must deliver (its calibration's).
    fps : float or None
        Frame rate to request; None keeps the driver's.
    fourcc : str
        Pixel format to request (``MJPG``, ``YUYV``, ...); "" keeps the driver's.
    ring_slots : int
    lost_after_s : float
        A camera that delivers nothing for this long is declared lost and reopened.
    """

    name: str
    device: int | str
    width: int
    height: int
    fps: float | None = None
    fourcc: str = ""
    ring_slots: int = 8
    lost_after_s: float = 3.0

    def __post_init__(self) -> None:
        if self.fourcc and len(self.fourcc) != 4:
            raise ConfigError(f"camera {self.name!r}: fourcc {self.fourcc!r} must be 4 characters")
        if self.width < 1 or self.height < 1:
            raise ConfigError(f"camera {self.name!r}: size {self.width}x{self.height} must be positive")


def is_regular_file(device: int | str) -> bool:
    """True when ``device`` names a file (a recording played as a webcam), not a device node or an index."""
    if isinstance(device, int):
        return False
    try:
        return stat.S_ISREG(os.stat(device).st_mode)
    except OSError:
        return False


class UvcSource(ThreadedSource):
    """One webcam captured into a ring buffer by its own thread."""

    def __init__(self, config: UvcCameraConfig, **kw: Any) -> None:
        super().__init__(config.name, bgr_ring(config.name, config.ring_slots, config.height, config.width), **kw)
        self.config = config
        self._cap: Any = None
        self._file = is_regular_file(config.device)
        self._period_ns = 0
        self._next_ns = 0
        self._index = 0

    def _open(self) -> None:
        c = self.config
        if self._file:  # a video file standing in for a webcam: the checks of every media file
            cap = open_video(str(c.device), f"camera {c.name!r}: video", error=DeviceError)
        else:
            # Through V4L2 explicitly: OpenCV's default may pick GStreamer, which ignores the property requests.
            target = c.device if isinstance(c.device, int) else str(c.device)
            cap = cv2.VideoCapture(target, cv2.CAP_V4L2)
        if not cap.isOpened():
            cap.release()
            raise DeviceError(f"camera {c.name!r}: cannot open {c.device!r} (is it plugged in, and may we read it?)")
        if not self._file:
            if c.fourcc:
                cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter.fourcc(*c.fourcc))
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, c.width)
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, c.height)
            if c.fps is not None:
                cap.set(cv2.CAP_PROP_FPS, c.fps)
        width, height = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        if (width, height) != (c.width, c.height):
            cap.release()
            raise DeviceError(
                f"camera {c.name!r} ({c.device}) delivers {width}x{height}, but it is calibrated at "
                f"{c.width}x{c.height}: set width/height it supports, or calibrate it at this size"
            )
        fps = c.fps or float(cap.get(cv2.CAP_PROP_FPS)) or 30.0
        self._period_ns = round(1e9 / fps) if self._file else 0
        self._next_ns = time.monotonic_ns()
        self._index = 0
        self._cap = cap

    def _grab(self) -> FrameRef | None:
        if self._file:
            self._pace()
        slot = self.ring.next_raw()
        ok, bgr = self._cap.read(slot)  # decoded into the ring's raw slot when the size is right
        now = time.monotonic_ns()
        if not ok or bgr is None:
            if self._file:  # a recording played as a webcam: start again, as a camera keeps streaming
                self._cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
                return None
            raise DeviceError(f"camera {self.name!r} ({self.config.device}) stopped delivering frames")
        if bgr.shape != slot.shape:
            self.counters.bad_buffers += 1
            return None
        stamp_ms = float(self._cap.get(cv2.CAP_PROP_POS_MSEC)) if not self._file else 0.0
        device_ns = round(stamp_ms * 1e6) if stamp_ms > 0 else now
        t0 = time.monotonic_ns()
        if not np.shares_memory(bgr, slot):  # the decoder made its own array after all
            np.copyto(slot, bgr)
        ref = self.ring.publish(now, device_ns, self._index)
        self.convert.add(time.monotonic_ns() - t0)
        self._index += 1
        self.counters.frames += 1
        return ref

    def _pace(self) -> None:
        """A file plays at its frame rate: wait for the next frame's due time (drop behind, never burst)."""
        now = time.monotonic_ns()
        if self._next_ns > now:
            time.sleep((self._next_ns - now) / 1e9)
        self._next_ns = max(self._next_ns + self._period_ns, time.monotonic_ns())

    def _close(self) -> None:
        if self._cap is not None:
            self._cap.release()
        self._cap = None
