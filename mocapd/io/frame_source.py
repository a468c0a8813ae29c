"""What every frame source (Aravis camera, video file, image folder) has in common.

A source owns a :class:`~mocapd.pipeline.frame_ring.FrameRing` and one capture thread. The thread blocks in the
device or decoder (both release the GIL), puts each frame once into the ring's next slot (raw, when the ring is
lazy: the conversion is left to whoever reads the frame), publishes it and hands the
:class:`~mocapd.pipeline.frame_ring.FrameRef` to the asyncio loop through the loop's
:class:`~mocapd.io.loop_mailbox.LoopMailbox` (one wake-up of the loop for the frames of every camera that arrive
while it is busy, not one each).

A consumer that must see every frame at once, on the capture thread itself (the keypoint tracker), sets
:attr:`ThreadedSource.frame_hook`: it is called there right after the frame is handed to the loop.

``await source.run(on_frame)`` supervises the thread: when the device fails (:class:`~mocapd.errors.DeviceError`)
the failure is counted and reported, and the source is reopened after an exponential back-off, while the other
sources keep running. ``run`` returns when the source ends (end of a file) and stops the thread when cancelled.
"""

from __future__ import annotations

import abc
import asyncio
import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mocapd.errors import DeviceError
from mocapd.io.device_state import OpenState
from mocapd.io.loop_mailbox import loop_mailbox
from mocapd.io.os_threads import CAPTURE_THREAD, worker_thread_setup
from mocapd.pipeline.frame_ring import FrameRef, FrameRing

log = logging.getLogger(__name__)

FrameCallback = Callable[[FrameRef], None]


@dataclass
class CaptureCounters:
    """Counters of one source, updated by its capture thread (read them from anywhere).

    Attributes
    ----------
    frames : int
        Frames published into the ring.
    missing_frames : int
        Frames the transport knows it lost (Aravis ``n_missing_frames``), summed over reconnections.
    resent_packets : int
        GigE Vision packets that had to be resent (Aravis ``n_resent_packets``), summed over reconnections.
    bad_buffers : int
        Buffers returned by the driver with a status other than success (incomplete, size mismatch...).
    timeouts : int
        Waits for a frame that timed out.
    failures : int
        Times the device failed or disappeared.
    reopens : int
        Times the source was opened again after a failure.
    last_error : str
        Message of the last failure ('' if none).
    """

    frames: int = 0
    missing_frames: int = 0
    resent_packets: int = 0
    bad_buffers: int = 0
    timeouts: int = 0
    failures: int = 0
    reopens: int = 0
    last_error: str = ""


@dataclass
class LatencyLog:
    """The last ``size`` latencies of a capture step, in ns."""

    size: int = 1024
    values: NDArray[np.int64] = field(init=False)
    count: int = 0

    def __post_init__(self) -> None:
        self.values = np.zeros(self.size, np.int64)

    def add(self, latency_ns: int) -> None:
        self.values[self.count % self.size] = latency_ns
        self.count += 1

    def recent(self) -> NDArray[np.int64]:
        """The stored latencies, shape (min(count, size),), oldest order not preserved."""
        return self.values[: min(self.count, self.size)].copy()


class ThreadedSource(abc.ABC):
    """Base class: a frame source read by one thread and supervised by an asyncio task.

    Subclasses implement :meth:`_open`, :meth:`_grab` and :meth:`_close`, all called in the capture thread.

    Parameters
    ----------
    name : str
        Name of the source (camera name).
    ring : FrameRing
        Where frames go; its shape must match what the source delivers.
    backoff_s : tuple of float
        (initial, maximum) delay before reopening a failed source, in seconds; doubles after each failure.
    """

    def __init__(self, name: str, ring: FrameRing, *, backoff_s: tuple[float, float] = (0.5, 10.0)) -> None:
        self.name = name
        self.ring = ring
        self.counters = CaptureCounters()
        self.latency = LatencyLog()
        self.backoff_s = backoff_s
        self.convert = LatencyLog()  # frame in hand -> published: the copy (or conversion) into the ring
        self.opened = threading.Event()  # set while the device is open and streaming
        self.retry_in_s: float | None = None  # the back-off being waited before reopening (None: not waiting)
        self.last_backoff_s: float | None = None  # the last back-off waited (it doubles while reopening fails)
        self.thread_id: int | None = None  # native id of the current capture thread (for CPU accounting)
        self.ever_opened = False  # the device opened at least once (a later failure is retried, not fatal)
        # How much nicer the capture thread runs once the device is open ([daemon] capture_nice; the device's own
        # threads, started while opening, keep the daemon's priority: Aravis's packet thread must not wait).
        self.worker_nice = 0
        #: called on the capture thread with each published frame, after it was handed to the loop (None: nothing)
        self.frame_hook: FrameCallback | None = None

    # -- subclasses implement -----------------------------------------------------------------------------
    @abc.abstractmethod
    def _open(self) -> None:
        """Open and start the device (blocking). Raise DeviceError on failure."""

    @abc.abstractmethod
    def _grab(self) -> FrameRef | bool | None:
        """Wait for one frame and publish it into the ring.

        Returns the frame's reference, None when no frame came (time-out; the caller loops) or False when the
        source has ended (end of file). Raise DeviceError when the device failed.
        """

    @abc.abstractmethod
    def _close(self) -> None:
        """Stop and release the device. Must not raise."""

    def capture_status(self) -> dict[str, Any]:
        """JSON-able state of the device: up or down, counters, the back-off before the next reopen."""
        c = self.counters
        state = "streaming" if self.opened.is_set() else ("waiting to reopen" if self.retry_in_s else "opening")
        return {"state": state, "up": self.opened.is_set(), "frames": c.frames, "failures": c.failures,
                "reopens": c.reopens, "retry_in_s": self.retry_in_s, "last_backoff_s": self.last_backoff_s,
                "missing_frames": c.missing_frames,
                "bad_buffers": c.bad_buffers, "timeouts": c.timeouts, "last_error": c.last_error}  # fmt: skip

    def open_state(self) -> OpenState:
        """Whether the first opening succeeded, failed (with the reason) or is still under way."""
        if self.ever_opened:
            return OpenState("open", "")
        if self.counters.failures:
            return OpenState("failed", self.counters.last_error)
        return OpenState("opening", "")

    # -- supervision ----------------------------------------------------------------------------------------
    def _thread_main(
        self,
        loop: asyncio.AbstractEventLoop,
        on_frame: FrameCallback,
        stop: threading.Event,
        done: asyncio.Future[DeviceError | None],
    ) -> None:
        result: DeviceError | BaseException | None = None
        self.thread_id = threading.get_native_id()
        mailbox = loop_mailbox(loop)
        try:
            self._open()
            self.ever_opened = True
            # Named and lowered only now: the device's own threads, started while opening, keep the daemon's.
            worker_thread_setup(CAPTURE_THREAD, self.worker_nice)
            self.opened.set()
            while not stop.is_set():
                ref = self._grab()
                if ref is False:
                    break
                if isinstance(ref, FrameRef):
                    if not mailbox.post(on_frame, ref):
                        break  # the loop closed (its tasks were not stopped first): nobody to hand frames to
                    hook = self.frame_hook
                    if hook is not None:
                        hook(ref)
        except DeviceError as exc:
            # Count and report at once: closing a vanished device can take seconds of protocol time-outs. Marked
            # down first: a /status answer read between the two would say "up" with the failure already counted.
            result = exc
            self.opened.clear()
            self.counters.failures += 1
            self.counters.last_error = str(exc)
            log.warning("camera %s failed: %s", self.name, exc)
        except BaseException as exc:
            # Anything else is a bug or a bad configuration: it must reach the task (and its TaskGroup), not end
            # the capture silently. run() raises it.
            result = exc
        finally:
            self.opened.clear()
            self._close()
            mailbox.post(_resolve, done, result)  # after this thread's frames (dropped once the loop is closed)

    async def run(self, on_frame: FrameCallback) -> None:
        """Capture until the source ends or the task is cancelled, reopening after failures.

        Parameters
        ----------
        on_frame : callable
            Called on the event loop with each published :class:`FrameRef`.
        """
        loop = asyncio.get_running_loop()
        delay = self.backoff_s[0]
        first = True
        while True:
            if not first:
                self.counters.reopens += 1
            first = False
            frames_before = self.counters.frames
            stop = threading.Event()
            done: asyncio.Future[DeviceError | None] = loop.create_future()
            thread = threading.Thread(
                target=self._thread_main, args=(loop, on_frame, stop, done), name=f"capture-{self.name}"
            )
            thread.start()
            try:
                error = await done
            except asyncio.CancelledError:
                stop.set()
                await asyncio.to_thread(thread.join)
                raise
            await asyncio.to_thread(thread.join)
            if error is None:
                return
            log.warning("camera %s: reopening in %.1f s", self.name, delay)
            self.retry_in_s = self.last_backoff_s = delay
            try:
                await asyncio.sleep(delay)
            finally:
                self.retry_in_s = None
            # A source that streamed before failing starts the back-off again from the initial delay.
            delay = self.backoff_s[0] if self.counters.frames > frames_before else min(delay * 2, self.backoff_s[1])


def _resolve(done: asyncio.Future[DeviceError | None], result: DeviceError | BaseException | None) -> None:
    if done.done():
        return
    if result is None or isinstance(result, DeviceError):
        done.set_result(result)
    else:
        done.set_exception(result)
