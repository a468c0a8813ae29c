"""How long a device has been silent while mocapd was listening: a pause of mocapd itself is not a device stall.

A camera that stops sending but keeps its socket, or a serial port that goes quiet, is declared lost after its
time-out, as an unplug is. But a process that was not running — stopped (SIGSTOP, Ctrl-Z, a debugger), a laptop
suspended, a thread starved on an overloaded machine — heard nothing for that long either, and its devices' data
is waiting in the kernel's buffers, to be read the moment it runs again. Judging the devices then would reopen
every one of them for nothing.

So silence is counted only over time the watcher was there to hear: the watcher checks every ``period``; a check
that comes more than ``2 * period + slack`` after the one before means the watcher itself was not running, and
the silence counts from that check. The slack is half the device's time-out (at least 0.25 s): a watcher thread
merely starved on a loaded machine is late by less, so it still declares a stalled device after its time-out of
checks, while a pause long enough to make a device look lost is recognised.
"""

from __future__ import annotations


class SilenceClock:
    """Silence of one device, as heard by a watcher that checks about every ``period_ns`` (all times ns, from the
    caller's monotonic clock).

    Parameters
    ----------
    now_ns : int
        Start of listening.
    period_ns : int
        How often the watcher means to check.
    timeout_ns : int
        The device's time-out: the lateness of a check tolerated before it counts as a pause of the watcher
        (scheduling on a loaded machine) is half of it, at least 0.25 s.
    """

    def __init__(self, now_ns: int, period_ns: int, timeout_ns: int) -> None:
        self.period_ns = period_ns
        self.slack_ns = max(250_000_000, timeout_ns // 2)
        self.last_heard_ns = now_ns
        self.listening_since_ns = now_ns
        self.last_check_ns = now_ns
        self.pauses = 0
        """Checks that came so late that the watcher must have been paused (not counted against the device)."""

    def heard(self, heard_ns: int) -> None:
        """The device sent something at ``heard_ns`` (the watcher was listening then: it counts as a check)."""
        self.last_heard_ns = max(self.last_heard_ns, heard_ns)
        self.last_check_ns = max(self.last_check_ns, heard_ns)

    def silent_ns(self, now_ns: int) -> int:
        """A check: how long the device has been silent while the watcher listened."""
        if now_ns - self.last_check_ns > 2 * self.period_ns + self.slack_ns:
            self.listening_since_ns = now_ns
            self.pauses += 1
        self.last_check_ns = now_ns
        return now_ns - max(self.last_heard_ns, self.listening_since_ns)
