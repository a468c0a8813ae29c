"""Taps on a tracker, from its acceleration: the gesture SlimeVR users reset their trackers' headings with.

The SlimeVR server (``TapDetection.kt``, ``TapDetectionManager.kt``) watches one torso tracker (upper chest,
chest, hip or waist, the first there is) and counts sharp jolts of its linear acceleration: the norm's range over a
short clump of time exceeding a threshold is one tap, after which the acceleration must fall low again before
the next counts; taps older than a window (a fixed time per tap wanted) are forgotten, and so are all of them
while the rest of the body moves (a heel strike is a jolt too). Two taps (by default) trigger a yaw reset, after a
short delay that lets the hand go back down. Written from that description; the numbers are the server's.

Pure: :meth:`TapDetector.update` takes a time, the watched sensor's linear-acceleration norm and whether the body
moves, and says when the wanted taps have come.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

from mocapd.errors import InputError

GRAVITY = 9.80665


@dataclass(frozen=True)
class TapOptions:
    taps: int = 2
    """Taps that make the gesture."""
    jolt: float = 6.0
    """Range of the linear acceleration's norm within ``clump_ns`` that is a tap (m/s²)."""
    clump_ns: int = 60_000_000
    calm: float = 2.25
    """The norm must fall below this before the next tap counts; the body is still while the other sensors' norms
    stay below it (m/s²)."""
    window_per_tap_ns: int = 300_000_000
    """The taps must come within ``taps ×`` this."""

    def __post_init__(self) -> None:
        if self.taps < 1 or self.jolt <= 0 or self.calm <= 0 or self.clump_ns <= 0 or self.window_per_tap_ns <= 0:
            raise InputError(f"tap options must be positive: {self}")


@dataclass
class TapDetector:
    """Counts taps of one sensor (see the module docstring)."""

    options: TapOptions = field(default_factory=TapOptions)
    _norms: deque[tuple[int, float]] = field(default_factory=deque)
    _taps: deque[int] = field(default_factory=deque)
    _wait_calm: bool = False
    detected: int = 0
    """Gestures detected so far."""

    def update(self, t_ns: int, linear_norm: float, body_moving: bool) -> bool:
        """One sample of the watched sensor; True when it completed the gesture (the taps are then forgotten)."""
        o = self.options
        norms = self._norms
        norms.append((t_ns, linear_norm))
        while t_ns - norms[0][0] > o.clump_ns:
            norms.popleft()
        hi = max(n for _, n in norms)
        lo = min(n for _, n in norms)
        if hi - lo > o.jolt and not self._wait_calm:
            self._taps.append(t_ns)
            self._wait_calm = True
        if hi < o.calm:
            self._wait_calm = False
        while self._taps and t_ns - self._taps[0] > o.taps * o.window_per_tap_ns:
            self._taps.popleft()
        if body_moving:
            self._taps.clear()
            return False
        if len(self._taps) >= o.taps:
            self._taps.clear()
            self.detected += 1
            return True
        return False


def linear_norm(quat: tuple[float, ...], acc: tuple[float, ...], g: float = GRAVITY) -> float:
    """Norm of the linear acceleration (m/s²) of a sample: specific force ``acc`` (sensor frame) minus gravity,
    ``R_iᵀ (0, 0, g)``, with ``quat`` the sensor's orientation in a +Z-up frame. Plain floats: it runs per sample."""
    w, x, y, z = quat
    gx, gy, gz = 2.0 * (x * z - w * y) * g, 2.0 * (y * z + w * x) * g, (1.0 - 2.0 * (x * x + y * y)) * g
    return math.sqrt((acc[0] - gx) ** 2 + (acc[1] - gy) ** 2 + (acc[2] - gz) ** 2)
