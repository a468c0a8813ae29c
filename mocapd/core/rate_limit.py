"""A token bucket: at most ``burst`` events at once, then one more every ``1 / rate_per_s`` seconds.

The daemon's heading resets share one (every source: HTTP, the WebSocket, ``mocapd reset-heading``, a tracker's
gestures): a reset turns every sensor of a suit, so a flood of them, from whatever door, would spin the wearer's
heading around and fill the log. Pure: the caller passes the time.
"""

from __future__ import annotations


class TokenBucket:
    """``burst`` tokens, refilled at ``rate_per_s``; :meth:`take` spends one if there is one.

    Parameters
    ----------
    rate_per_s : float
        Tokens added per second (> 0).
    burst : int
        Most tokens held (>= 1): how many events may come at once after a quiet spell.
    now_ns : int
        The time the bucket starts full (nanoseconds, any monotonic clock).
    """

    def __init__(self, rate_per_s: float, burst: int, now_ns: int) -> None:
        if not rate_per_s > 0 or burst < 1:
            raise ValueError(f"rate_per_s must be > 0 and burst >= 1, got {rate_per_s}, {burst}")
        self.rate_per_s = rate_per_s
        self.burst = burst
        self._tokens = float(burst)
        self._at_ns = now_ns
        #: events allowed and refused so far
        self.allowed = 0
        self.refused = 0

    def _refill(self, now_ns: int) -> None:
        if now_ns > self._at_ns:
            self._tokens = min(float(self.burst), self._tokens + (now_ns - self._at_ns) * 1e-9 * self.rate_per_s)
            self._at_ns = now_ns

    def take(self, now_ns: int) -> float:
        """Spend a token: 0.0 when allowed, else the seconds until the next one (nothing spent, counted refused)."""
        self._refill(now_ns)
        if self._tokens >= 1.0:
            self._tokens -= 1.0
            self.allowed += 1
            return 0.0
        self.refused += 1
        return (1.0 - self._tokens) / self.rate_per_s
