"""Latency accounting: a Prometheus-style histogram plus a window of recent values for percentiles.

One :class:`LatencyStats` per stage (detection delay, sampling, sorting, solving, publishing, end to end).
Durations are int64 nanoseconds measured by the caller; this module reads no clock. Memory is fixed: the
histogram has fixed buckets and the percentile window is a preallocated ring.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

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
        self._bounds_ns = np.array([b * 1e6 for b in BUCKETS_MS])
        self.bucket_counts = np.zeros(len(BUCKETS_MS) + 1, dtype=np.int64)  # last: +Inf
        self.count = 0
        self.sum_ns = 0
        self._recent: NDArray[np.int64] = np.zeros(window, dtype=np.int64)
        self._n_recent = 0
        self._i = 0

    def add(self, value_ns: int) -> None:
        """Record one duration (ns)."""
        self.bucket_counts[int(np.searchsorted(self._bounds_ns, value_ns, side="left"))] += 1
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
