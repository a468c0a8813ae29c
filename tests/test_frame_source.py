"""The capture supervision of :class:`~mocapd.io.frame_source.ThreadedSource`: a device that fails while
streaming is reported down no later than its failure is counted and logged, so no ``capture_status()`` (what
``/status`` shows of a camera) says "up" beside a counted failure. A source whose device streams one frame, then
fails (what a pulled cable does to an Aravis camera), read at the moment the failure is logged.

And the frames' crossing to the loop: the frames captured while the loop is busy wake it once between them, not once
each, and all arrive in order."""

from __future__ import annotations

import asyncio
import logging
import time
from typing import Any

from mocapd.errors import DeviceError
from mocapd.io.frame_source import ThreadedSource
from mocapd.pipeline.frame_ring import FrameRef, FrameRing
from tests.loop_spy import spy_wakeups


class _OneFrameThenGone(ThreadedSource):
    """Opens, publishes one black frame, then its device vanishes (every later open fails too)."""

    def __init__(self) -> None:
        super().__init__("cam0", FrameRing("cam0", 2, 4, 4, 1), backoff_s=(0.01, 0.01))
        self.opens = 0
        self.grabs = 0

    def _open(self) -> None:
        self.opens += 1
        if self.opens > 1:
            raise DeviceError("camera 'cam0' is gone")

    def _grab(self) -> FrameRef | bool | None:
        self.grabs += 1
        if self.grabs > 1:
            raise DeviceError("camera 'cam0' stopped answering")
        self.ring.next_slot()[:] = 0  # a black frame
        return self.ring.publish(1, 1, 1)

    def _close(self) -> None:
        pass


class _StatusAtFailure(logging.Handler):
    """Reads the source's status when its failure is logged (the capture thread, just after counting it)."""

    def __init__(self, source: ThreadedSource) -> None:
        super().__init__()
        self.source = source
        self.seen: list[dict[str, Any]] = []

    def emit(self, record: logging.LogRecord) -> None:
        if record.getMessage().startswith("camera cam0 failed"):
            self.seen.append(self.source.capture_status())


def test_a_failed_device_is_down_when_its_failure_is_counted() -> None:
    source = _OneFrameThenGone()
    handler = _StatusAtFailure(source)
    log = logging.getLogger("mocapd.io.frame_source")
    log.addHandler(handler)
    frames: list[FrameRef] = []

    async def run() -> None:
        task = asyncio.create_task(source.run(frames.append))
        while len(handler.seen) < 2:  # the streaming device's failure, then a reopen's
            await asyncio.sleep(0.01)
        task.cancel()

    try:
        asyncio.run(asyncio.wait_for(run(), 30))
    finally:
        log.removeHandler(handler)
    assert len(frames) == 1
    assert [(s["failures"], s["up"]) for s in handler.seen[:2]] == [(1, False), (2, False)], handler.seen
    assert handler.seen[0]["last_error"] == "camera 'cam0' stopped answering"


class _Burst(ThreadedSource):
    """Publishes ``n`` frames as fast as it can, then ends (a replay at the end of its file)."""

    def __init__(self, n: int) -> None:
        super().__init__("cam0", FrameRing("cam0", 4, 4, 4, 1))
        self.n = n
        self.grabs = 0

    def _open(self) -> None:
        pass

    def _grab(self) -> FrameRef | bool | None:
        self.grabs += 1
        if self.grabs > self.n:
            return False
        self.ring.next_slot()[:] = 0
        return self.ring.publish(self.grabs, self.grabs, self.grabs)

    def _close(self) -> None:
        pass


def test_frames_captured_while_the_loop_is_busy_wake_it_once_between_them() -> None:
    """The loop is busy with the first frame until the capture thread has published all 200 and ended. With
    ``call_soon_threadsafe`` per frame (the old code) each frame wrote the loop's self-pipe: 200 wake-ups and one
    for the end. Through the loop's mailbox: one for the first frame, one for everything queued behind it."""
    n = 200
    source = _Burst(n)
    got: list[int] = []

    async def main() -> list[str]:
        wakeups = spy_wakeups(asyncio.get_running_loop())

        def on_frame(ref: FrameRef) -> None:
            if not got:  # the first frame keeps the loop busy until the thread has captured every frame and ended
                deadline = time.monotonic() + 30
                while source.grabs <= n and time.monotonic() < deadline:
                    time.sleep(0.001)
            got.append(ref.seq)

        await asyncio.wait_for(source.run(on_frame), 60)
        return wakeups

    wakeups = asyncio.run(main())
    assert got == list(range(n))  # every frame, in order, before the end of the source was seen
    crossings = [name for name in wakeups if name in ("on_frame", "_resolve", "_drain")]
    assert len(crossings) <= 2, crossings  # the old code: 201
