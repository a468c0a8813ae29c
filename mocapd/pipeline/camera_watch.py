"""The bumped-camera watch in the daemon (issue 43, part 2): :class:`~mocapd.core.camera_watch.CameraWatch` fed by
the scheduler's solve threads through :attr:`FixedLatencyScheduler.observation_hook
<mocapd.pipeline.scheduler.FixedLatencyScheduler.observation_hook>`, read by the event loop (``/status``, the log),
told of a camera replaced as one of the scheduler's camera listeners (:meth:`LiveCameraWatch.camera_replaced`).

The people of a tick are solved in parallel, so every call takes the watch's lock; a call costs a few
triangulations on the checked ticks (``rate_hz``), one on a person's screened solves (``screen_hz``) and nothing on
the others.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mocapd.core.camera import Camera
from mocapd.core.camera_watch import CameraWatch, Proposal, WatchOptions

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class CameraChange:
    """One camera's calibration replaced while running: logged, in ``/status`` (``camera_changes``) and recorded in
    the session (``mocapd resolve`` uses the new camera from ``t_ns`` on)."""

    t_ns: int  # the solve time of the last tick with the old camera
    index: int  # the camera's index in the rig
    camera: Camera  # the new one
    source: str  # who changed it: "camera watch" (a re-estimate applied), ...
    rotation_deg: float  # the turn from the old pose
    details: dict[str, Any] = field(default_factory=dict)  # e.g. the re-estimate's matches, error before and after


def turn_deg(a: Camera, b: Camera) -> float:
    """The angle (degrees) between two cameras' orientations."""
    c = (np.trace(np.asarray(b.R) @ np.asarray(a.R).T) - 1.0) / 2.0
    return round(float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))), 3)


class LiveCameraWatch:
    """The watch behind a lock; its new events handed out once each (:meth:`new_events`)."""

    def __init__(self, cameras: list[Camera], options: WatchOptions) -> None:
        self.watch = CameraWatch(cameras, options)
        self._lock = threading.Lock()
        self._said = 0  # events already handed out

    def observe(self, t_ns: int, uv: FloatArray, conf: FloatArray, person: str) -> FloatArray:
        """The scheduler's hook: one solved person's undistorted keypoints and confidences, and who they are (their
        solves screened ``screen_hz`` times a second); the confidences the solve uses back (a camera in doubt
        down-weighted)."""
        with self._lock:
            return self.watch.observe(t_ns, uv, conf, person)

    def pending(self) -> list[tuple[int, Proposal]]:
        """Re-estimates that passed their checks, to apply (``[calibration.watch] apply``)."""
        with self._lock:
            return self.watch.pending()

    def doubted_since(self, camera: int) -> int | None:
        with self._lock:
            return self.watch.doubted_since(camera)

    def camera_replaced(self, index: int, camera: Camera) -> None:
        """The scheduler's camera listener: camera ``index`` is ``camera`` from the next tick on."""
        with self._lock:
            self.watch.apply(index, camera)

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
