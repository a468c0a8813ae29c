"""Keypoint sources: what feeds each camera's detection timeline.

A source is one camera's "frames in, timestamped 2D people out" stage. The real one (the onnxruntime detector on
an Aravis or replay frame source, run in worker threads so it never blocks the event loop) implements the same
:class:`KeypointSource` protocol; until it lands,
:class:`mocapd.service.synthetic_rig.SyntheticKeypointSource` plays a detector's output for a
synthetic world: frames captured at the camera rate (cameras unsynchronised: each has its own phase), detections
delivered ``detection_delay_s`` after capture, stamped with the capture time.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

from mocapd.core.sorting import Detections2D

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
