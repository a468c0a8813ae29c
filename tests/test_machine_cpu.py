"""The machine's CPU counters (mocapd.io.machine_cpu): ``/proc/stat`` read on this machine, its busy time growing with
this process's work, and texts it does not understand (or no file) read as "not measured"."""

from __future__ import annotations

import os
import time
from pathlib import Path

from mocapd.io.machine_cpu import MachineCpu, MachineCpuReader, parse_proc_stat


def test_the_real_proc_stat_counts_this_processs_work_among_the_machines() -> None:
    """Half a second of this process's CPU shows in the machine's busy time (which also holds everyone else's: it
    is at least ours, within the kernel's 10 ms clock ticks), and the CPUs are the machine's online ones."""
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


def test_the_busy_fields_and_the_online_cpus_of_a_proc_stat_text() -> None:
    """user + nice + system + irq + softirq + steal (idle and iowait are not; guest is already in user), in clock
    ticks; the CPUs are the cpuN lines."""
    text = (
        "cpu  100 20 30 5000 40 5 6 7 50 0\n"
        "cpu0 50 10 15 2500 20 3 3 4 25 0\n"
        "cpu1 50 10 15 2500 20 2 3 3 25 0\n"
        "intr 12345 0 0\nctxt 999\nprocs_running 3\n"
    )
    assert parse_proc_stat(text, 100) == MachineCpu((100 + 20 + 30 + 5 + 6 + 7) * 10_000_000, 2)


def test_what_the_reader_does_not_understand_is_not_measured(tmp_path: Path) -> None:
    """No file (not Linux), a kernel before ``steal``, or no cpuN line: None, and the reader says why once and
    stops opening the file."""
    assert parse_proc_stat("cpu  1 2 3 4\ncpu0 1 2 3 4\n", 100) is None  # four fields: before 2.6.11
    assert parse_proc_stat("cpu  1 2 3 4 5 6 7 8\n", 100) is None  # no cpuN line
    assert parse_proc_stat("cpu  1 2 3 4 5 6 7 x\ncpu0 1 2 3 4 5 6 7 8\n", 100) is None
    missing = MachineCpuReader(str(tmp_path / "stat"))
    assert missing.read() is None and "not readable" in str(missing.unavailable)
    (tmp_path / "stat").write_text("cpu  1 2 3 4 5 6 7 8\ncpu0 1 2 3 4 5 6 7 8\n")
    assert missing.read() is None  # once unavailable, not read again every window
    odd = tmp_path / "odd"
    odd.write_text("intr 1\n")
    reader = MachineCpuReader(str(odd))
    assert reader.read() is None and "no aggregate cpu line" in str(reader.unavailable)
