"""The bumped-camera watch in the daemon (issue 43, part 2): :class:`~mocapd.core.camera_watch.CameraWatch` fed by
the scheduler's solve threads through :attr:`FixedLatencyScheduler.observation_hook
<mocapd.pipeline.scheduler.FixedLatencyScheduler.observation_hook>`, read by the event loop (``/status``, the log).

The people of a tick are solved in parallel, so every call takes the watch's lock; a call costs a few
triangulations on the checked ticks (``rate_hz``) and nothing on the others.
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mocapd.core.camera import Camera
from mocapd.core.camera_watch import CameraWatch, WatchOptions

FloatArray = NDArray[np.float64]


class LiveCameraWatch:
    """The watch behind a lock; its new events handed out once each (:meth:`new_events`)."""

    def __init__(self, cameras: list[Camera], options: WatchOptions) -> None:
        self.watch = CameraWatch(cameras, options)
        self._lock = threading.Lock()
        self._said = 0  # events already handed out

    def observe(self, t_ns: int, uv: FloatArray, conf: FloatArray) -> FloatArray:
        """The scheduler's hook: one solved person's undistorted keypoints and confidences; the confidences the
        solve uses back (a camera in doubt down-weighted)."""
        with self._lock:
            return self.watch.observe(t_ns, uv, conf)

    def status(self) -> dict[str, Any]:
        with self._lock:
            return self.watch.status()

    def in_doubt(self) -> list[str]:
        with self._lock:
            return [c.name for c, d in zip(self.watch.cameras, self.watch.in_doubt(), strict=True) if d]

    def new_events(self) -> list[tuple[int, str, str, dict[str, Any]]]:
        """Events (solve time ns, camera, what, details) not handed out before."""
        with self._lock:
            out = self.watch.events[self._said :]
            self._said = len(self.watch.events)
            return out
