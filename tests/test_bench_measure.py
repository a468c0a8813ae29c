"""The camera-rig benchmark's measuring window (``mocapd.service.bench.cameras.Measure``)."""

from __future__ import annotations

import asyncio
import time
from typing import Any

import pytest

from mocapd.service.bench import cameras


class _Recorded(cameras.Measure):
    """Records the snapshots' times instead of reading a daemon."""

    def __init__(self, seconds: float, warm_up_s: float) -> None:
        super().__init__(seconds, warm_up_s)
        self.times: list[float] = []

    def _snapshot(self, daemon: Any) -> dict[str, Any]:
        self.times.append(time.monotonic())
        return {"t": self.times[-1]}


def test_the_window_is_its_seconds_even_when_the_loop_stalled_past_the_warm_up(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A loaded machine can stall the event loop past the warm-up's end (seen once on CI: a 4 s window measured
    0 detections); the end snapshot still comes ``seconds`` after the first, not at once."""
    monkeypatch.setattr(cameras, "summarize", lambda *args, **kw: {})
    measure = _Recorded(seconds=0.3, warm_up_s=0.05)

    async def main() -> None:
        async def stall() -> None:
            await asyncio.sleep(0.01)
            time.sleep(0.5)  # blocks the loop: past warm-up + seconds when the monitor wakes

        await asyncio.gather(measure(None), stall())  # type: ignore[arg-type]

    asyncio.run(main())
    start, end = measure.times
    assert end - start >= 0.3
