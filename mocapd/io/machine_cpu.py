"""The machine's CPU as the kernel counts it: how busy all its CPUs were, for the governor's cause test (issue 39).

The governor (:mod:`mocapd.pipeline.governor`) puts each step it sheds on trial; a step that took CPU from this
process without bringing the tick's lateness down is taken back only when *other* programs used a substantial share
of the machine meanwhile (a VR game beside the daemon): on a machine only the daemon loads, the lateness is its own
and the next step follows. What the others used is the machine's busy time less this process's CPU time, both read
at the same instants; this module reads the first, through ``psutil.cpu_times()`` (a dependency already: on Linux it
reads ``/proc/stat``'s aggregate ``cpu`` line, in the kernel's 10 ms clock ticks).

Busy is every field but idle time: ``user + nice + system + irq + softirq + steal`` on Linux (``idle`` and ``iowait``
are idle; ``guest`` and ``guest_nice`` are already inside ``user`` and ``nice``; ``steal``, a hypervisor running
another machine on this one's CPUs, is CPU this machine's programs did not get, so it counts as the others' too),
``interrupt + dpc`` beside user and system on Windows, user, nice and system on macOS. The CPUs are the logical ones
(``psutil.cpu_count()``). Where psutil cannot read them the reading is None and the governor keeps its older rule
(docs/daemon.md, "A cause test before the next step").
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import psutil

log = logging.getLogger(__name__)

BUSY_FIELDS = ("user", "nice", "system", "irq", "softirq", "steal", "interrupt", "dpc")
"""``psutil.cpu_times()`` fields counted as busy, where the platform has them (idle, iowait and guest time are not:
guest time is already inside user and nice)."""


@dataclass(frozen=True)
class MachineCpu:
    """One reading of the machine's CPU counters."""

    busy_ns: int
    """CPU time spent busy since boot, summed over the machine's CPUs (ns)."""
    cpus: int
    """The CPUs counted (logical)."""


def busy_ns(times: Any) -> int:
    """The busy time in a ``psutil.cpu_times()`` result (seconds as floats, the fields its platform has), in ns."""
    return round(sum(float(getattr(times, name, 0.0)) for name in BUSY_FIELDS) * 1e9)


class MachineCpuReader:
    """Reads :class:`MachineCpu`; :meth:`read` gives None where the machine's CPU cannot be read (said once in the
    log, with why). ``cpu_times`` and ``cpu_count`` are psutil's (a test gives others)."""

    def __init__(self, cpu_times: Callable[[], Any] = psutil.cpu_times,
                 cpu_count: Callable[[], int | None] = psutil.cpu_count) -> None:  # fmt: skip
        self._cpu_times, self._cpu_count = cpu_times, cpu_count
        #: why the machine's CPU cannot be read (None: it could, so far)
        self.unavailable: str | None = None

    def read(self) -> MachineCpu | None:
        """The counters now, or None (and :attr:`unavailable` says why)."""
        if self.unavailable is not None:
            return None  # it will not appear later: not tried again every window in vain
        try:
            times, cpus = self._cpu_times(), self._cpu_count()
        except (OSError, RuntimeError, NotImplementedError) as exc:  # psutil's errors on a system it cannot read
            self._unavailable(f"psutil.cpu_times failed ({exc.__class__.__name__}: {exc})")
            return None
        if not cpus or cpus < 1:
            self._unavailable("psutil does not know the machine's CPU count")
            return None
        return MachineCpu(busy_ns(times), int(cpus))

    def _unavailable(self, why: str) -> None:
        self.unavailable = why
        log.info("the machine's CPU cannot be read (%s): the governor's cause test does without the others' CPU", why)
