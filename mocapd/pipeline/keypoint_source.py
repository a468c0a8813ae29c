"""Keypoint sources: what feeds each camera's detection timeline.

A source is one camera's "frames in, timestamped 2D people out" stage. :class:`DetectorKeypointSource` runs any
:data:`Detector` (the onnxruntime detector of issue 6 plugs in here) on the frames of an Aravis or replay source
in a worker thread, so it never blocks the event loop; until the detector lands,
:class:`mocapd.sim.world.SyntheticKeypointSource` plays a detector's output for a
synthetic world: frames captured at the camera rate (cameras unsynchronised: each has its own phase), detections
delivered ``detection_delay_s`` after capture, stamped with the capture time.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from concurrent.futures import Executor
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from mocapd.core.sorting import Detections2D
from mocapd.io.device_state import OpenState
from mocapd.pipeline.clocksync import ClockSync
from mocapd.pipeline.frame_ring import FrameRef, FrameRing

#: (camera index, capture time ns, detections, arrival time ns) -> None
KeypointSink = Callable[[int, int, Detections2D, int], None]


class KeypointSource(Protocol):
    """One camera's detections, delivered to a sink as they become available."""

    name: str
    camera: int

    async def run(self, sink: KeypointSink) -> None:
        """Deliver detections until cancelled; raise :class:`~mocapd.errors.DeviceError` on a device failure
        (the daemon's supervisor restarts the source with back-off)."""
        ...

    def status(self) -> dict[str, Any]:
        """JSON-able health for /status."""
        ...

    def open_state(self) -> OpenState:
        """Whether the source's device has opened (the daemon waits for every device before READY)."""
        ...


class FrameProducer(Protocol):
    """A frame source (:class:`mocapd.io.frame_source.ThreadedSource`: Aravis camera, video, image folder)."""

    name: str
    ring: FrameRing

    async def run(self, on_frame: Callable[[FrameRef], None]) -> None: ...

    def open_state(self) -> OpenState: ...


#: a 2D detector: one image (height, width, channels) uint8 in, the people it sees out (called in a worker thread)
Detector = Callable[[NDArray[np.uint8]], Detections2D]


class DetectorKeypointSource:
    """Frames of a camera through a detector, never blocking the event loop.

    The detector runs in a worker thread on the newest frame of the ring when a worker takes the job; the frames
    captured meanwhile are skipped (temporal sub-sampling, as in seed 003 §3.4.2: the detector sets the detection
    rate, the scheduler interpolates) and counted. Detections are stamped with the frame's host capture time, or, with
    ``device_clock``, with the camera's own frame timestamp mapped to the host clock: a camera stamps the
    exposure, so the stamp leaves out the frame's transfer and the capture thread's wake-up (the map is the
    lower envelope of host arrival vs device stamp, :class:`~mocapd.pipeline.clocksync.ClockSync`, so what
    remains is exposure + the least transfer delay seen).
    """

    def __init__(
        self,
        camera: int,
        frames: FrameProducer,
        detector: Detector,
        *,
        executor: Executor | None = None,
        clock: Callable[[], int] = time.monotonic_ns,
        device_clock: ClockSync | None = None,
    ) -> None:
        self.camera = camera
        self.name = frames.name
        self.frames = frames
        self.detector = detector
        self.executor = executor
        self.clock = clock
        self.device_clock = device_clock
        self.detected = 0
        self.skipped = 0
        self.lost = 0  # copies overtaken by the ring's writer (a newer frame is taken; counted in skipped too)
        self.captured = 0
        self._last_seq = -1  # ring sequence number of the last frame detected
        self.transfer_ns = 0  # sum over detected frames of host arrival - capture stamp

    async def run(self, sink: KeypointSink) -> None:
        loop = asyncio.get_running_loop()
        wake = asyncio.Event()

        def on_frame(ref: FrameRef) -> None:
            self.captured += 1
            if self.device_clock is not None:
                self.device_clock.update(ref.device_ns, ref.host_ns)
            self.frame_arrived(ref)
            wake.set()

        async def detect_loop() -> None:
            while True:
                await wake.wait()
                wake.clear()
                done = await self._detection(loop)
                if done is None:
                    continue
                ref, dets = done
                stamp = self.capture_ns(ref)
                sink(self.camera, stamp, dets, self.clock())
                self.detected += 1
                self.transfer_ns += ref.host_ns - stamp

        async with asyncio.TaskGroup() as tg:
            worker = tg.create_task(detect_loop())
            await self.frames.run(on_frame)  # returns at the end of a replay; errors propagate to the supervisor
            worker.cancel()

    def frame_arrived(self, ref: FrameRef) -> None:
        """Called on the event loop for every captured frame (a shared detector's worker wakes up here)."""

    def capture_ns(self, ref: FrameRef) -> int:
        """The frame's capture time on the host clock (never later than its arrival)."""
        mapped = self.device_clock.to_host_ns(ref.device_ns) if self.device_clock is not None else None
        return ref.host_ns if mapped is None else min(mapped, ref.host_ns)

    async def _detection(self, loop: asyncio.AbstractEventLoop) -> tuple[FrameRef, Detections2D] | None:
        # The frame is chosen when a worker is free, not when it was queued: with several cameras sharing the
        # workers, a frame chosen at queueing time would be stale (or overwritten) by then.
        return await loop.run_in_executor(self.executor, self._detect_newest)

    def has_new_frame(self) -> bool:
        """Whether the ring holds a frame newer than the last one taken."""
        ref = self.frames.ring.latest()
        return ref is not None and ref.seq > self._last_seq

    def take_newest(self) -> tuple[FrameRef, NDArray[np.uint8]] | None:
        """The newest frame not taken yet, copied out of the ring (None if there is none); counts the frames
        skipped since the last one taken. Called by one worker at a time."""
        ring = self.frames.ring
        for _ in range(3):  # the writer may overtake the copy; then the newer frame is the one to take
            ref = ring.latest()
            if ref is None or ref.seq <= self._last_seq:
                return None
            image = ring.read(ref.seq)
            if image is None:
                self.lost += 1
                continue
            if self._last_seq >= 0:
                self.skipped += ref.seq - self._last_seq - 1
            self._last_seq = ref.seq
            return ref, image
        return None

    def _detect_newest(self) -> tuple[FrameRef, Detections2D] | None:
        """In a worker: detect the newest frame not detected yet (None if there is none)."""
        got = self.take_newest()
        return None if got is None else (got[0], self.detector(got[1]))

    def open_state(self) -> OpenState:
        return self.frames.open_state()

    def status(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "name": self.name, "kind": "detector", "captured": self.captured, "detected": self.detected,
            "skipped": self.skipped, "lost": self.lost,
            "transfer_ms_mean": round(self.transfer_ns / self.detected / 1e6, 2) if self.detected else None,
        }  # fmt: skip
        capture = getattr(self.frames, "capture_status", None)  # frame sources of mocapd.io report their device
        if callable(capture):
            out["capture"] = capture()
        return out
