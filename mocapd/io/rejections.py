"""Counted, logged rejections of outside input (datagrams, client requests) that a flood cannot turn into a
flood of log lines.

Every rejection is counted by reason (at most ``max_reasons`` distinct keys, the rest under ``"other"``: reasons
are this program's own words, but a caller that puts outside text in one must not grow the table). A warning is
logged for the first rejection and then at most once per ``interval_ns``, saying how many were rejected so far:
the log shows that something is being rejected and why, the counters (in ``/status``) show how much.
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from collections.abc import Callable


class Rejections:
    """Rejection counters of one door, e.g. the IMU bridge's socket.

    Parameters
    ----------
    door : str
        What rejects, as the log line starts (``"imu bridge"``).
    log : logging.Logger
        Where the warnings go (the door's own module logger).
    interval_ns : int
        At most one warning per this many nanoseconds.
    clock : callable
        Host monotonic nanoseconds.
    max_reasons : int
        Distinct reason keys kept.
    """

    def __init__(
        self,
        door: str,
        log: logging.Logger,
        *,
        interval_ns: int = 10_000_000_000,
        clock: Callable[[], int] = time.monotonic_ns,
        max_reasons: int = 32,
    ) -> None:
        self.door = door
        self.total = 0
        self.by_reason: Counter[str] = Counter()
        self._log = log
        self._interval_ns = interval_ns
        self._clock = clock
        self._max_reasons = max_reasons
        self._next_log_ns: int | None = None

    def reject(self, reason: str, detail: str = "", count: int = 1) -> None:
        """Count ``count`` rejections for ``reason`` (a short fixed phrase); ``detail`` only goes into the log."""
        if count <= 0:
            return
        reasons = self.by_reason
        key = reason if reason in reasons or len(reasons) < self._max_reasons - 1 else "other"
        reasons[key] += count
        self.total += count
        now = self._clock()
        if self._next_log_ns is None or now >= self._next_log_ns:
            self._next_log_ns = now + self._interval_ns
            self._log.warning(
                "%s: rejected %s%s; %d rejected so far (counts per reason in /status)",
                self.door, reason, f" ({detail[:200]})" if detail else "", self.total,
            )  # fmt: skip

    def as_dict(self) -> dict[str, int]:
        """Rejections per reason (for /status)."""
        return dict(self.by_reason)
