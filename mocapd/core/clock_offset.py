"""Offset of a remote host's clock from ours, from round trips (NTP's clock filter, simplified).

A round trip: we read our clock (``t0``), ask the remote host for its clock, it answers ``t1``, we read ours again
(``t2``). Whatever the delays each way, the remote read happened between ``t0`` and ``t2``, so the offset
``remote - local`` is ``t1 - (t0 + t2) / 2`` to within half the round trip. Queueing delays only ever add to the
round trip, so of the last ``window`` round trips the one with the smallest bound is kept: its round trip, plus the
drift the two clocks may have made since (``max_drift_ppm`` of its age). The bound is reported as the uncertainty.

Pure: times are arguments.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class OffsetEstimate:
    offset_ns: int
    """remote clock - local clock."""
    uncertainty_ns: int
    """Bound on the error of ``offset_ns``: half the chosen round trip plus the drift since."""
    rtt_ns: int
    samples: int


class ClockOffsetEstimator:
    """Min-round-trip filter over the last ``window`` round trips (see the module docstring)."""

    def __init__(self, window: int = 32, max_drift_ppm: float = 100.0) -> None:
        if window < 1:
            raise ValueError("window must be >= 1")
        self.window = window
        self.max_drift_ppm = max_drift_ppm
        self._samples: deque[tuple[int, int, int]] = deque(maxlen=window)  # (t_local_mid, offset, rtt)
        self.rejected = 0

    def add(self, t0_ns: int, remote_ns: int, t2_ns: int) -> bool:
        """One round trip; False (counted) if ``t2 < t0`` (not a round trip)."""
        if t2_ns < t0_ns:
            self.rejected += 1
            return False
        mid = (t0_ns + t2_ns) // 2
        self._samples.append((mid, remote_ns - mid, t2_ns - t0_ns))
        return True

    def reset(self) -> None:
        self._samples.clear()

    def estimate(self, now_ns: int) -> OffsetEstimate | None:
        """The best offset at ``now_ns`` (None before the first round trip)."""
        best: tuple[int, int, int] | None = None
        for mid, offset, rtt in self._samples:
            bound = rtt // 2 + round(max(0, now_ns - mid) * self.max_drift_ppm * 1e-6)
            if best is None or bound < best[0]:
                best = (bound, offset, rtt)
        if best is None:
            return None
        return OffsetEstimate(best[1], best[0], best[2], len(self._samples))
