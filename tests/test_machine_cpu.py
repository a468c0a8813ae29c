"""The machine's CPU counters (mocapd.io.machine_cpu): psutil's CPU times read on this machine, their busy time growing
with this process's work, the busy fields of each platform, and a machine whose CPU cannot be read read as "not
measured"."""

from __future__ import annotations

import os
import time
from collections import namedtuple

import psutil

from mocapd.io.machine_cpu import MachineCpuReader, busy_ns


def test_the_real_machines_busy_time_counts_this_processs_work() -> None:
    """Half a second of this process's CPU shows in the machine's busy time (which also holds everyone else's: it
    is at least ours, within the kernel's 10 ms clock ticks), and the CPUs are the machine's."""
    reader = MachineCpuReader()
    first, cpu0 = reader.read(), time.process_time_ns()
    assert first is not None, reader.unavailable
    assert first.cpus == os.cpu_count() and first.busy_ns > 0
    spin_until = time.process_time_ns() + 500_000_000
    while time.process_time_ns() < spin_until:
        pass
    second, cpu1 = reader.read(), time.process_time_ns()
    assert second is not None and second.cpus == first.cpus
    ours = cpu1 - cpu0
    assert second.busy_ns - first.busy_ns >= ours - 30_000_000 * first.cpus, (second, first, ours)
    assert reader.unavailable is None


def test_the_busy_fields_of_each_platform() -> None:
    """Linux: user + nice + system + irq + softirq + steal (idle and iowait are not; guest is already in user);
    Windows: user + system + interrupt + dpc; macOS: user + nice + system; this machine's psutil fields too."""
    linux = namedtuple("linux", "user nice system idle iowait irq softirq steal guest guest_nice")
    assert busy_ns(linux(1.0, 0.2, 0.3, 50.0, 0.4, 0.05, 0.06, 0.07, 0.5, 0.0)) == round(1.68e9)
    windows = namedtuple("windows", "user system idle interrupt dpc")
    assert busy_ns(windows(2.0, 1.0, 40.0, 0.25, 0.125)) == round(3.375e9)
    mac = namedtuple("mac", "user nice system idle")
    assert busy_ns(mac(1.5, 0.5, 1.0, 9.0)) == 3_000_000_000
    here = psutil.cpu_times()
    rest = sum(here) - here.idle - getattr(here, "iowait", 0.0) - getattr(here, "guest", 0.0)
    assert abs(busy_ns(here) - (rest - getattr(here, "guest_nice", 0.0)) * 1e9) < 1e3  # summed in another order


def test_a_machine_whose_cpu_cannot_be_read_is_not_measured() -> None:
    """psutil failing (a system it cannot read) or no CPU count: None, said once, and not tried again every
    window."""
    calls = []

    def failing() -> object:
        calls.append(1)
        raise OSError("no such file: /proc/stat")

    reader = MachineCpuReader(cpu_times=failing)
    assert reader.read() is None and "psutil.cpu_times failed" in str(reader.unavailable)
    assert reader.read() is None and len(calls) == 1
    uncounted = MachineCpuReader(cpu_count=lambda: None)
    assert uncounted.read() is None and "CPU count" in str(uncounted.unavailable)
