"""Keypoint sources: what feeds each camera's detection timeline.

A source is one camera's "frames in, timestamped 2D people out" stage. :class:`DetectorKeypointSource` runs any
:data:`Detector` (the onnxruntime detector of issue 6 plugs in here) on the frames of an Aravis or replay source
in a worker thread, so it never blocks the event loop; until the detector lands,
:class:`mocapd.service.synthetic_rig.SyntheticKeypointSource` plays a detector's output for a
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


class FrameProducer(Protocol):
    """A frame source (:class:`mocapd.io.frame_source.ThreadedSource`: Aravis camera, video, image folder)."""

    name: str
    ring: FrameRing

    async def run(self, on_frame: Callable[[FrameRef], None]) -> None: ...


#: a 2D detector: one image (height, width, channels) uint8 in, the people it sees out (called in a worker thread)
Detector = Callable[[NDArray[np.uint8]], Detections2D]


class DetectorKeypointSource:
    """Frames of a camera through a detector, never blocking the event loop.

    The detector runs in a worker thread; while it is busy, newer frames replace the waiting one (temporal
    sub-sampling, as in seed 003 §3.4.2: the detector sets the detection rate, the scheduler interpolates), and
    the frames skipped that way are counted. Detections are stamped with the frame's host capture time.
    """

    def __init__(
        self,
        camera: int,
        frames: FrameProducer,
        detector: Detector,
        *,
        executor: Executor | None = None,
        clock: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        self.camera = camera
        self.name = frames.name
        self.frames = frames
        self.detector = detector
        self.executor = executor
        self.clock = clock
        self.detected = 0
        self.skipped = 0
        self.lost = 0  # frames overwritten in the ring before the detector could copy them

    async def run(self, sink: KeypointSink) -> None:
        loop = asyncio.get_running_loop()
        wake = asyncio.Event()
        pending: list[FrameRef] = []

        def on_frame(ref: FrameRef) -> None:
            if pending:
                self.skipped += 1
                pending[0] = ref
            else:
                pending.append(ref)
            wake.set()

        async def detect_loop() -> None:
            while True:
                await wake.wait()
                wake.clear()
                while pending:
                    ref = pending.pop()
                    dets = await loop.run_in_executor(self.executor, self._detect, ref)
                    if dets is None:
                        self.lost += 1
                        continue
                    sink(self.camera, ref.host_ns, dets, self.clock())
                    self.detected += 1

        async with asyncio.TaskGroup() as tg:
            worker = tg.create_task(detect_loop())
            await self.frames.run(on_frame)  # returns at the end of a replay; errors propagate to the supervisor
            worker.cancel()

    def _detect(self, ref: FrameRef) -> Detections2D | None:
        image = self.frames.ring.read(ref.seq)
        return None if image is None else self.detector(image)

    def status(self) -> dict[str, Any]:
        return {"name": self.name, "kind": "detector", "detected": self.detected, "skipped": self.skipped,
                "lost": self.lost}  # fmt: skip
