"""The repeated-log-line rate limit (mocapd.io.log_throttle) on a real logging handler."""

from __future__ import annotations

import io
import logging
from collections.abc import Iterator

import pytest

from mocapd.io.log_throttle import RepeatFilter, group_digits


class _Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def logged() -> Iterator[tuple[logging.Logger, io.StringIO, RepeatFilter, _Clock]]:
    stream = io.StringIO()
    handler = logging.StreamHandler(stream)
    handler.setFormatter(logging.Formatter("%(levelname)s %(message)s"))
    clock = _Clock()
    rf = RepeatFilter(burst=3, window_s=10.0, clock=clock)
    handler.addFilter(rf)
    log = logging.getLogger("mocapd.test.throttle")
    log.propagate = False
    log.addHandler(handler)
    log.setLevel(logging.INFO)
    yield log, stream, rf, clock
    log.removeHandler(handler)


def _flood(log: logging.Logger, n: int) -> None:
    for i in range(n):
        log.warning(f"tracker {i} timed out")  # one call site, many texts: the case to limit


def test_a_flood_from_one_line_passes_the_burst_then_a_count(logged) -> None:  # type: ignore[no-untyped-def]
    log, stream, _rf, clock = logged
    _flood(log, 1237)
    assert stream.getvalue().count("\n") == 3
    clock.t = 10.5
    _flood(log, 1)
    lines = stream.getvalue().splitlines()
    # the closed window's last counted record with the count of the others, then the new window's first
    assert lines[3:] == ["WARNING tracker 1236 timed out (1 233 more in the last 10 s)", "WARNING tracker 0 timed out"]


def test_a_record_closing_its_window_between_sweeps_carries_the_count(logged) -> None:  # type: ignore[no-untyped-def]
    log, stream, _rf, clock = logged
    _flood(log, 10)  # its window opens at 0 s: 3 pass, 7 counted
    clock.t = 9.5
    log.info("a sweep at 9.5 s, before the window closes")
    clock.t = 10.2  # < 1 s since the sweep: no sweep, the record itself closes the window
    _flood(log, 1)
    assert stream.getvalue().splitlines()[-1] == "WARNING tracker 0 timed out (7 more in the last 10 s)"


def test_a_line_said_once_per_device_passes_for_every_device(logged) -> None:  # type: ignore[no-untyped-def]
    """Thirteen sensors starting were three lines and a count: which ones stream was said for none of the rest."""
    log, stream, _rf, _clock = logged

    def streaming(device: int) -> None:
        log.info(f"imu {device} streaming", extra={"repeat_key": device})  # one call site

    for i in range(13):
        streaming(i)
    assert stream.getvalue().splitlines() == [f"INFO imu {i} streaming" for i in range(13)]
    for _ in range(10):  # one device reconnecting in a loop is still limited
        streaming(0)
    assert stream.getvalue().count("INFO imu 0 streaming\n") == 3


def test_a_line_per_device_is_limited_per_kind_when_the_sender_names_the_devices(logged) -> None:  # type: ignore[no-untyped-def]
    """Issue 45: "timed out" was limited per tracker, and a sender cycling through MACs gave each MAC its own
    allowance (1 089 WARNING lines in 30 s). Now the line as a whole passes ``kind_burst`` (16) a window."""
    log, stream, rf, clock = logged
    for mac in range(1000):
        log.warning(f"tracker {mac} timed out", extra={"repeat_key": mac})  # one call site, a key per sender
    assert stream.getvalue().splitlines() == [f"WARNING tracker {mac} timed out" for mac in range(16)]
    clock.t = 10.5
    log.warning("tracker 2000 timed out", extra={"repeat_key": 2000})
    assert stream.getvalue().splitlines()[16:] == [
        "WARNING tracker 999 timed out (983 more in the last 10 s)",  # the kind's closed window, summarised
        "WARNING tracker 2000 timed out",
    ]
    for _ in range(10):  # one key is still limited to its own burst inside the kind's
        log.warning("tracker 3000 timed out", extra={"repeat_key": 3000})
    rf.flush()
    assert stream.getvalue().count("tracker 3000 timed out") == 4  # 3 passed, then the summary of the other 7
    assert stream.getvalue().splitlines()[-1] == "WARNING tracker 3000 timed out (6 more in the last 1 s)"


def test_other_lines_pass_while_one_is_counted(logged) -> None:  # type: ignore[no-untyped-def]
    log, stream, _rf, _clock = logged
    _flood(log, 100)
    log.error("disk full")
    assert stream.getvalue().splitlines()[-1] == "ERROR disk full"


def test_a_site_that_goes_quiet_is_summarised_by_the_sweep_and_at_flush(logged) -> None:  # type: ignore[no-untyped-def]
    log, stream, rf, clock = logged
    _flood(log, 8)  # 3 pass, 5 counted
    clock.t = 11.0
    log.info("something else")  # sweeps the closed window: the last counted record with the other 4
    lines = stream.getvalue().splitlines()
    assert lines[3] == "WARNING tracker 7 timed out (4 more in the last 11 s)"
    assert lines[4] == "INFO something else"
    _flood(log, 5)  # a new window: 3 pass, 2 counted
    rf.flush()
    assert stream.getvalue().splitlines()[-1] == "WARNING tracker 4 timed out (1 more in the last 1 s)"


def test_one_filter_on_two_handlers_counts_each_record_once() -> None:
    streams = [io.StringIO(), io.StringIO()]
    rf = RepeatFilter(burst=2, window_s=10.0, clock=_Clock())
    log = logging.getLogger("mocapd.test.throttle.two")
    log.propagate = False
    handlers = [logging.StreamHandler(s) for s in streams]
    for h in handlers:
        h.addFilter(rf)
        log.addHandler(h)
    try:
        _flood(log, 5)
    finally:
        for h in handlers:
            log.removeHandler(h)
    assert [s.getvalue().count("\n") for s in streams] == [2, 2]


def test_group_digits() -> None:
    assert group_digits(1234567) == "1 234 567"
    assert group_digits(12) == "12"
