"""Latency accounting, and the scheduler's delay that follows the detector.

One :class:`LatencyStats` per stage (detection delay, sampling, sorting, solving, publishing, end to end): a
Prometheus-style histogram plus a window of recent values for percentiles. :class:`AutoLatency` is
``[daemon] latency_s = "auto"``: the smallest delay that covers what the detector delivers, from the measured
detection delays and intervals. Durations are int64 nanoseconds measured by the caller; this module reads no
clock. Memory is fixed: the histogram has fixed buckets and the windows are preallocated rings.
"""

from __future__ import annotations

from bisect import bisect_left
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mocapd.errors import InputError

#: upper bounds of the histogram buckets, milliseconds (Prometheus ``le`` labels, in seconds on /metrics)
BUCKETS_MS: tuple[float, ...] = (0.5, 1, 2, 5, 10, 20, 50, 100, 150, 200, 250, 300, 400, 500, 750, 1000, 2000)


class LatencyStats:
    """Histogram (cumulative over the run) and the last ``window`` values (for p50/p95/p99).

    Parameters
    ----------
    window : int
        Recent values kept for percentiles (e.g. 60 s at 60 Hz = 3600).
    """

    def __init__(self, window: int = 4096) -> None:
        self._bounds_ns = [b * 1e6 for b in BUCKETS_MS]  # a list: bisect on it is a tenth of searchsorted's call
        self.bucket_counts = np.zeros(len(BUCKETS_MS) + 1, dtype=np.int64)  # last: +Inf
        self.count = 0
        self.sum_ns = 0
        self._recent: NDArray[np.int64] = np.zeros(window, dtype=np.int64)
        self._n_recent = 0
        self._i = 0

    def add(self, value_ns: int) -> None:
        """Record one duration (ns)."""
        self.bucket_counts[bisect_left(self._bounds_ns, value_ns)] += 1
        self.count += 1
        self.sum_ns += int(value_ns)
        self._recent[self._i] = value_ns
        self._i = (self._i + 1) % len(self._recent)
        self._n_recent = min(self._n_recent + 1, len(self._recent))

    def recent(self) -> NDArray[np.int64]:
        """The kept recent values (unordered), shape ``(n,)``."""
        return self._recent[: self._n_recent]

    def percentiles_ms(self, qs: tuple[float, ...] = (50, 95, 99)) -> dict[str, float | None]:
        """``{"p50": ms, ...}`` over the recent window (None when empty)."""
        r = self.recent()
        if r.size == 0:
            return {f"p{q:g}": None for q in qs}
        values = np.percentile(r, qs) / 1e6
        return {f"p{q:g}": round(float(v), 3) for q, v in zip(qs, values, strict=True)}

    def summary(self) -> dict[str, Any]:
        """JSON-able: count, mean and percentiles in milliseconds."""
        mean = self.sum_ns / self.count / 1e6 if self.count else None
        return {"count": self.count, "mean_ms": None if mean is None else round(mean, 3), **self.percentiles_ms()}

    def prometheus(self, name: str, labels: str = "") -> list[str]:
        """Histogram lines in the Prometheus text format (seconds), without the HELP/TYPE header."""
        sep = "," if labels else ""
        lines = []
        cumulative = np.cumsum(self.bucket_counts)
        for bound, c in zip(BUCKETS_MS, cumulative[:-1], strict=True):
            lines.append(f'{name}_bucket{{{labels}{sep}le="{bound / 1e3:g}"}} {int(c)}')
        lines.append(f'{name}_bucket{{{labels}{sep}le="+Inf"}} {int(cumulative[-1])}')
        lab = f"{{{labels}}}" if labels else ""
        lines.append(f"{name}_sum{lab} {self.sum_ns / 1e9:.9f}")
        lines.append(f"{name}_count{lab} {self.count}")
        return lines


@dataclass(frozen=True)
class AutoLatencyOptions:
    """How ``[daemon] latency_s = "auto"`` follows the detector (see :class:`AutoLatency`)."""

    min_ns: int = 30_000_000
    """Never below this."""
    max_ns: int = 2_000_000_000
    """Never above this (also: a camera silent longer than this is away, and its gap is no detection interval)."""
    start_ns: int = 500_000_000
    """The latency until enough detections were measured."""
    quantile: float = 95.0
    """Percentile of the measured needs that the latency covers."""
    margin_ns: int = 0
    """Added to that percentile (the daemon adds one output period: a tick may run that much late)."""
    window: int = 1024
    """Needs kept (all cameras together), at most."""
    max_age_ns: int = 60_000_000_000
    """... and only those that arrived in the last minute: start-up (models warming, the detection chooser's
    first comparisons) is forgotten a minute later, while the chooser's later exploration epochs (3 s of the
    other mode every 2 min at most, :mod:`~mocapd.pipeline.detection_mode`) stay under 5 % of the window and so
    out of the p95."""
    min_samples: int = 16
    """Needs measured before the first estimate replaces ``start_ns``."""
    hysteresis: float = 0.1
    """The goal moves only when the estimate leaves ``goal ± max(hysteresis × goal, hysteresis_min_ns)``."""
    hysteresis_min_ns: int = 20_000_000
    settle_ns: int = 30_000_000_000
    """... and when the estimate has stayed more than ``hysteresis_min_ns`` on one side of the goal for this long:
    a lasting change inside the band is followed, not held (the band alone held a live goal at 486 ms over an
    estimate of 446 ms for the rest of a run, docs/daemon.md)."""
    up_rate: float = 0.25
    """The latency grows towards a higher goal by at most this many seconds per second of wall time (the solve
    time then advances at 0.75× wall time for a while: never backwards)."""
    down_rate: float = 0.05
    """... and shrinks by at most this many seconds per second (solve time at 1.05× wall time)."""
    evaluate_every_ns: int = 1_000_000_000
    """The goal is re-estimated at most this often."""

    def __post_init__(self) -> None:
        if not 0 <= self.min_ns <= self.start_ns <= self.max_ns:
            raise InputError(f"auto latency needs 0 <= min <= start <= max, got {self.min_ns} {self.start_ns} "
                             f"{self.max_ns}")  # fmt: skip
        if not (0.0 < self.up_rate < 1.0 and 0.0 < self.down_rate < 1.0):
            raise InputError("auto latency rates must be in (0, 1) s/s: solve time must never run backwards")
        if self.settle_ns <= 0:
            raise InputError(f"auto latency settle time must be > 0, got {self.settle_ns} ns")
        if not 0.0 < self.quantile <= 100.0 or self.window < 1 or self.min_samples < 1:
            raise InputError("auto latency needs a quantile in (0, 100], window >= 1 and min_samples >= 1")


class AutoLatency:
    """The smallest scheduler delay that covers what the detector delivers, adapted slowly with hysteresis.

    The scheduler interpolates camera ``c`` at solve time ``t`` between its detected frames captured at
    ``t_a <= t < t_b``; it has them once frame ``b`` has arrived (at ``arrival_b``). For every ``t`` in
    ``[t_a, t_b)`` that takes at most ``arrival_b - t_a`` = the detection delay of ``b`` plus the detection
    interval ``t_b - t_a``. So each detected frame gives one *need* ``arrival_b - t_a``; the latency's goal is
    the ``quantile`` of the recent needs plus ``margin_ns`` (the issue's "p95 detection delay plus one detection
    interval", measured as one quantity per frame rather than as two percentiles added).

    The goal moves when the estimate leaves a band around it (hysteresis), or has stayed on one side of it for
    ``settle_ns`` (a lasting change inside the band), and the latency follows the goal at a bounded rate, so
    solve time never jumps and never runs backwards. Pure: times are arguments.

    Parameters
    ----------
    n_cameras : int
    options : AutoLatencyOptions
    """

    def __init__(self, n_cameras: int, options: AutoLatencyOptions | None = None) -> None:
        self.options = o = options if options is not None else AutoLatencyOptions()
        self.latency_ns = o.start_ns
        self.goal_ns = o.start_ns
        self.estimate_ns: int | None = None
        self._last_capture: list[int | None] = [None] * n_cameras
        self._needs = np.zeros(o.window, dtype=np.int64)
        self._delays = np.zeros(o.window, dtype=np.int64)
        self._intervals = np.zeros(o.window, dtype=np.int64)
        self._arrivals = np.zeros(o.window, dtype=np.int64)  # arrival time of each need
        self._n = 0  # needs recorded so far (the rings hold the last `window`)
        self._nd = 0  # delays recorded so far
        self._updated_ns: int | None = None
        self._evaluated_ns: int | None = None
        self.goal_changes = 0
        self.gaps = 0  # detection intervals longer than max_ns (a camera away), left out
        self._side = 0  # where the estimate is: above (1) or below (-1) the goal by > hysteresis_min_ns, or 0
        self._side_since_ns = 0

    def observe(self, camera: int, capture_ns: int, arrival_ns: int) -> None:
        """One detected frame of ``camera``: captured at ``capture_ns``, its detections in at ``arrival_ns``."""
        o = self.options
        self._delays[self._nd % o.window] = arrival_ns - capture_ns
        self._nd += 1
        previous = self._last_capture[camera]
        if previous is not None and capture_ns > previous:
            if capture_ns - previous > o.max_ns:
                self.gaps += 1
            else:
                k = self._n % o.window
                self._needs[k] = arrival_ns - previous
                self._intervals[k] = capture_ns - previous
                self._arrivals[k] = arrival_ns
                self._n += 1
        if previous is None or capture_ns > previous:
            self._last_capture[camera] = capture_ns

    def update(self, now_ns: int, *, idle: bool = False) -> int:
        """The latency to use at ``now_ns`` (call once per tick, ``now_ns`` non-decreasing).

        ``idle``: nothing has been solved from the cameras yet, so no motion is on anybody's screen: a goal below
        the latency is taken at once rather than approached at ``down_rate`` (at start-up the 0.5 s placeholder
        would otherwise take ~9 s to come down to a tracked stream's ~70 ms). Solve time then jumps forward, never
        backwards: a higher goal is still approached at ``up_rate``.
        """
        o = self.options
        # Until the first estimate, every tick looks: it comes with the first keypoints, often before the first solve.
        if self._evaluated_ns is None or self.estimate_ns is None or now_ns - self._evaluated_ns >= o.evaluate_every_ns:
            self._evaluated_ns = now_ns
            self._evaluate(now_ns)
        if idle and self.goal_ns < self.latency_ns:
            self.latency_ns = self.goal_ns
        elif self._updated_ns is not None and now_ns > self._updated_ns:
            dt = now_ns - self._updated_ns
            if self.goal_ns > self.latency_ns:
                self.latency_ns = min(self.goal_ns, self.latency_ns + int(o.up_rate * dt))
            elif self.goal_ns < self.latency_ns:
                self.latency_ns = max(self.goal_ns, self.latency_ns - int(o.down_rate * dt))
        self._updated_ns = now_ns if self._updated_ns is None else max(now_ns, self._updated_ns)
        return self.latency_ns

    def _evaluate(self, now_ns: int) -> None:
        o = self.options
        n = min(self._n, o.window)
        recent = self._needs[:n][self._arrivals[:n] >= now_ns - o.max_age_ns]
        if recent.size < o.min_samples:
            return
        need = float(np.percentile(recent, o.quantile))
        first = self.estimate_ns is None  # the start value is a placeholder: the first estimate replaces it
        self.estimate_ns = estimate = int(min(o.max_ns, max(o.min_ns, need + o.margin_ns)))
        band = max(o.hysteresis * self.goal_ns, o.hysteresis_min_ns)
        off = estimate - self.goal_ns
        side = 0 if abs(off) <= o.hysteresis_min_ns else (1 if off > 0 else -1)
        if side != self._side:
            self._side, self._side_since_ns = side, now_ns
        settled = side != 0 and now_ns - self._side_since_ns >= o.settle_ns
        if first or abs(off) > band or settled:
            self.goal_ns = estimate
            self.goal_changes += 1
            self._side = 0

    def status(self) -> dict[str, Any]:
        """JSON-able: the latency now, its goal, the estimate and what it is made of (ms)."""
        o = self.options
        n, nd = min(self._n, o.window), min(self._nd, o.window)

        def ms(v: float | None) -> float | None:
            return None if v is None else round(v / 1e6, 1)

        return {
            "mode": "auto", "latency_ms": ms(self.latency_ns), "goal_ms": ms(self.goal_ns),
            "estimate_ms": ms(self.estimate_ns), "needs": self._n, "goal_changes": self.goal_changes,
            "gaps": self.gaps, "quantile": o.quantile,
            "detection_delay_p95_ms": ms(float(np.percentile(self._delays[:nd], 95))) if nd else None,
            "detection_interval_p50_ms": ms(float(np.percentile(self._intervals[:n], 50))) if n else None,
            "detection_interval_p95_ms": ms(float(np.percentile(self._intervals[:n], 95))) if n else None,
            "need_p95_ms": ms(float(np.percentile(self._needs[:n], 95))) if n else None,
        }  # fmt: skip
