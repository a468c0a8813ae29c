"""The machine's CPU as the kernel counts it: how busy all its CPUs were, for the governor's cause test (issue 39).

The governor (:mod:`mocapd.pipeline.governor`) puts each step it sheds on trial; a step that took CPU from this
process without bringing the tick's lateness down is taken back only when *other* programs used a substantial share
of the machine meanwhile (a VR game beside the daemon): on a machine only the daemon loads, the lateness is its own
and the next step follows. What the others used is the machine's busy time less this process's CPU time, both read
at the same instants; this module reads the first.

Linux: ``/proc/stat``'s aggregate ``cpu`` line (proc(5)), in clock ticks (``SC_CLK_TCK``, 100 a second). Busy is
``user + nice + system + irq + softirq + steal``: ``idle`` and ``iowait`` are idle time; ``guest`` and
``guest_nice`` are already inside ``user`` and ``nice``; ``steal`` (a hypervisor running another machine on this
one's CPUs) is CPU this machine's programs did not get, so it counts as the others' too. The CPUs are the
``cpuN`` lines (the online ones). Elsewhere (no ``/proc/stat``), or on text this does not understand, the reading is
None and the governor keeps its older rule (docs/daemon.md, "A cause test before the next step").
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass

log = logging.getLogger(__name__)

PROC_STAT = "/proc/stat"
#: the ``cpu`` line's fields counted as busy, by position after the label (proc(5): user nice system idle iowait
#: irq softirq steal guest guest_nice)
_BUSY_FIELDS = (0, 1, 2, 5, 6, 7)


@dataclass(frozen=True)
class MachineCpu:
    """One reading of the machine's CPU counters."""

    busy_ns: int
    """CPU time spent busy since boot, summed over the machine's CPUs (ns)."""
    cpus: int
    """The CPUs counted (online)."""


def parse_proc_stat(text: str, clock_ticks: int) -> MachineCpu | None:
    """The reading in a ``/proc/stat`` text, its counters in units of ``1 / clock_ticks`` s; None when the text has
    no aggregate ``cpu`` line with at least the eight fields up to ``steal`` (kernels before 2.6.11) or no
    ``cpuN`` line."""
    busy: int | None = None
    cpus = 0
    for line in text.splitlines():
        label, _, rest = line.partition(" ")
        if label == "cpu":
            fields = rest.split()
            if len(fields) < 8 or not all(f.isdigit() for f in fields[:8]):
                return None
            busy = sum(int(fields[k]) for k in _BUSY_FIELDS)
        elif label.startswith("cpu") and label[3:].isdigit():
            cpus += 1
    if busy is None or cpus == 0 or clock_ticks <= 0:
        return None
    return MachineCpu(busy * 1_000_000_000 // clock_ticks, cpus)


class MachineCpuReader:
    """Reads :class:`MachineCpu` from ``/proc/stat``; :meth:`read` gives None where that cannot be read (said once in
    the log, with why)."""

    def __init__(self, path: str = PROC_STAT) -> None:
        self.path = path
        self._clock_ticks = _clock_ticks()
        #: why the machine's CPU cannot be read (None: it could, so far)
        self.unavailable: str | None = None

    def read(self) -> MachineCpu | None:
        """The counters now, or None (and :attr:`unavailable` says why)."""
        if self.unavailable is not None:
            return None  # it will not appear later: no file opened every window in vain
        try:
            with open(self.path, encoding="ascii") as fh:
                text = fh.read()
        except (OSError, UnicodeDecodeError) as exc:
            self._unavailable(f"{self.path} not readable ({exc.__class__.__name__}: {exc})")
            return None
        reading = parse_proc_stat(text, self._clock_ticks)
        if reading is None:
            self._unavailable(f"{self.path} has no aggregate cpu line this reader understands")
        return reading

    def _unavailable(self, why: str) -> None:
        self.unavailable = why
        log.info("the machine's CPU cannot be read (%s): the governor's cause test does without the others' CPU", why)


def _clock_ticks() -> int:
    """The kernel's clock ticks a second (``/proc/stat``'s unit); 0 where the system has no such setting."""
    try:
        return int(os.sysconf("SC_CLK_TCK"))
    except (AttributeError, ValueError, OSError):  # not POSIX (Windows has no os.sysconf)
        return 0
