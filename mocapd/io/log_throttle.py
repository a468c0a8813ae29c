"""Rate limit for repeated log lines: the first few of a call site pass, the rest are counted and summarised.

A live daemon meets the same fault many times a second (a full disk, a flooding sender, a camera that keeps
timing out); a log line per occurrence buries everything else on the console and in the journal. One
:class:`RepeatFilter` on the process's log handlers lets ``burst`` records of one *call site* (file, line, level)
through per ``window_s`` and counts the others; the first record of the site after its window closes carries the
count::

    ... WARNING mocapd.io.slimevr: tracker 12 timed out (1 234 more in the last 10 s)

A line said once per device (a device streaming, a tracker connecting) passes ``extra={"repeat_key": device}``:
each device then gets ``burst`` records of its own, so thirteen sensors starting are thirteen lines, while one
device reconnecting in a loop is still limited. The device is often named by whoever sends (a SlimeVR tracker's
MAC), so the call site as a whole — the *kind* of line — passes at most ``kind_burst`` records per window however
many devices there are (issue 45: a sender cycling through MACs got 1 089 "timed out" WARNING lines in 30 s, each
MAC its own allowance); the rest are counted for the kind and summarised as any other site's.

A site that goes quiet with records still counted is summarised by the next record of any site (at most once a
second it sweeps closed windows) and by :meth:`RepeatFilter.flush` at exit, so no count is lost. A call site,
not the message text, is the key: a line formatted with an f-string (a tracker id, a path) is still one line.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

#: records of one call site let through per window before counting starts
DEFAULT_BURST = 5
#: records of one call site with a ``repeat_key`` let through per window, all keys together (a full suit's
#: sixteen trackers dropping out at once are each named)
DEFAULT_KIND_BURST = 16
#: seconds of one window
DEFAULT_WINDOW_S = 10.0
#: call sites tracked at once; beyond it the oldest is summarised and forgotten (a bound, not a working limit:
#: call sites are lines of code)
MAX_SITES = 4096

_Key = tuple[str, int, int, object]


@dataclass
class _Site:
    window_start: float
    passed: int = 0
    suppressed: int = 0
    last: logging.LogRecord | None = None


def group_digits(n: int) -> str:
    """``1234`` -> ``"1 234"``: counts in log lines, readable at a glance."""
    return f"{n:,}".replace(",", " ")


class RepeatFilter(logging.Filter):
    """A :class:`logging.Filter` for handlers that rate-limits records per call site.

    Parameters
    ----------
    burst
        Records of one call site (of one ``repeat_key`` of it) passed per window before the rest are counted.
    window_s
        Length of a window, seconds.
    clock
        Monotonic seconds (injectable for tests).
    kind_burst
        Records of one call site passed per window, all its ``repeat_key`` values together.
    """

    def __init__(
        self,
        burst: int = DEFAULT_BURST,
        window_s: float = DEFAULT_WINDOW_S,
        clock: Callable[[], float] = time.monotonic,
        kind_burst: int = DEFAULT_KIND_BURST,
    ) -> None:
        super().__init__()
        if burst < 1 or kind_burst < 1 or not window_s > 0:
            raise ValueError(f"burst, kind_burst must be >= 1 and window_s > 0 (got {burst}, {kind_burst}, {window_s})")
        self.burst = burst
        self.kind_burst = kind_burst
        self.window_s = window_s
        self._clock = clock
        self._sites: dict[_Key, _Site] = {}  # per call site (the kind of line): what is counted and summarised
        self._keys: dict[_Key, _Site] = {}  # per call site and repeat_key: only the records each key passed
        self._last_sweep = clock()
        self._emitting = False
        # One filter on several handlers sees each record once per handler: the decision is made once.
        self._decided: tuple[logging.LogRecord | None, bool] = (None, True)

    def filter(self, record: logging.LogRecord) -> bool:
        if self._emitting:  # a summary this filter is emitting itself
            return True
        if self._decided[0] is record:
            return self._decided[1]
        decision = self._decide(record)
        self._decided = (record, decision)
        return decision

    def _decide(self, record: logging.LogRecord) -> bool:
        now = self._clock()
        if now - self._last_sweep >= 1.0:
            self._last_sweep = now
            self._sweep(now)
        repeat = getattr(record, "repeat_key", None)
        key = (record.pathname, record.lineno, record.levelno, None)
        site = self._sites.get(key)
        closed: _Site | None = None  # the site's window that this record closes, with records still counted
        if site is None:
            if len(self._sites) >= MAX_SITES:
                self._summarise(self._sites.pop(next(iter(self._sites))))
            site = self._sites[key] = _Site(window_start=now)
        elif now - site.window_start >= self.window_s:
            if site.suppressed:
                closed = _Site(site.window_start, site.passed, site.suppressed, site.last)
            site.window_start, site.passed, site.suppressed, site.last = now, 0, 0, None
        if repeat is None:
            allowed = site.passed < self.burst
        else:
            each = self._key_site((*key[:3], repeat), now)
            allowed = each.passed < self.burst and site.passed < self.kind_burst
            each.passed += allowed
        if closed is not None:
            if allowed:  # this record carries the closed window's count
                _append_count(record, closed.suppressed, now - closed.window_start)
            else:
                self._summarise(closed)
        if allowed:
            site.passed += 1
            return True
        site.suppressed += 1
        site.last = record
        return False

    def _key_site(self, key: _Key, now: float) -> _Site:
        each = self._keys.get(key)
        if each is None or now - each.window_start >= self.window_s:
            if each is None and len(self._keys) >= MAX_SITES:
                del self._keys[next(iter(self._keys))]  # nothing counted there: the kind's site holds the counts
            each = self._keys[key] = _Site(window_start=now)
        return each

    def flush(self) -> None:
        """Summarise every site with records still counted (call before the process exits)."""
        for site in self._sites.values():
            self._summarise(site)
        self._sites.clear()
        self._keys.clear()

    def _sweep(self, now: float) -> None:
        for key in [k for k, each in self._keys.items() if now - each.window_start >= self.window_s]:
            del self._keys[key]
        for key, site in list(self._sites.items()):
            if now - site.window_start >= self.window_s:
                self._summarise(site)
                del self._sites[key]

    def _summarise(self, site: _Site) -> None:
        last = site.last
        if not site.suppressed or last is None:
            return
        # The last counted record, re-emitted with the count of the others: its logger's handlers see it as any
        # other record.
        if site.suppressed > 1:
            _append_count(last, site.suppressed - 1, self._clock() - site.window_start)
        site.suppressed = 0
        self._emitting = True
        try:
            logging.getLogger(last.name).handle(last)
        finally:
            self._emitting = False


def _append_count(record: logging.LogRecord, count: int, span_s: float) -> None:
    record.msg = f"{record.getMessage()} ({group_digits(count)} more in the last {max(span_s, 1.0):.0f} s)"
    record.args = None


def install(burst: int = DEFAULT_BURST, window_s: float = DEFAULT_WINDOW_S) -> RepeatFilter:
    """Put one :class:`RepeatFilter` on every handler of the root logger (once; returns the one installed)."""
    root = logging.getLogger()
    for handler in root.handlers:
        for f in handler.filters:
            if isinstance(f, RepeatFilter):
                return f
    rf = RepeatFilter(burst=burst, window_s=window_s)
    for handler in root.handlers:
        handler.addFilter(rf)
    return rf
