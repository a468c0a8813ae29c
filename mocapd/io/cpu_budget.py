"""Hold this process to a CPU budget (a fraction of cores, or several) with a Linux cgroup: slow machines anywhere.

Why. Real-time claims must hold on the users' laptops, which are slower than the machine a figure was measured on
and share their CPU with a VR game (issue 39). ``mocapd demo --cpu-budget 0.8`` and ``mocapd bench latency
--cpu-budget 0.8`` run the daemon's process as if it had 0.8 of a core: the kernel's CFS bandwidth control lets its
threads run at most ``cores x period`` of CPU time per ``period``, then throttles them until the next period, as
a machine with less CPU would. The period is 10 ms (the kernel's default is 100 ms): two threads exhaust a 0.8-core
quota in 40 ms of a 100 ms period and the whole process then stands still for 60 ms, which no slower CPU does.

The period is longer where the quota would be under two of the kernel's bandwidth slices
(``/proc/sys/kernel/sched_cfs_bandwidth_slice_us``, 5 ms by default): :func:`period_for`. The kernel hands a
quota out to the CPUs in slices, so a 4 ms quota (0.4 of a core in 10 ms) went whole to the first CPU that asked
and the process's threads on the other CPU stood throttled, waiting for the slack timer, while its budget was not
spent: a budget that runs the process on one CPU at a time, which no 2-core machine does. Measured with ``mocapd
demo --cpu-budget 0.4`` on a 2-core AMD EPYC (docs/daemon.md, "The budget's period"): 88-93 % of the 10 ms periods
throttled, 10-18 % of the output ticks missed; with the same quota in 1 ms slices (the sysctl set for the test)
2.2 %; in a 25 ms period (two 5 ms slices in its 10 ms quota) 3.1-3.8 %. The price is longer stands: up to
``period - quota`` (15 ms at 0.4 of a core), still shorter than a 60 Hz tick.
The fake cameras (and anything a demo spawns to stand in for hardware) are exempt: real cameras encode on their own.

Mechanisms, the first that works:

1. cgroup v2 ``cpu.max`` ("QUOTA PERIOD"), in a child of this process's cgroup, where the ``cpu`` controller is
   available there (``cgroup.controllers``; enabled in the parent's ``cgroup.subtree_control`` if needed);
2. cgroup v1 ``cpu.cfs_quota_us`` / ``cpu.cfs_period_us``, in a child of this process's ``cpu`` hierarchy.

Both need write access to the cgroup file system (root, or a delegated subtree: ``systemd-run --user --scope -p
CPUQuota=80% mocapd demo`` is the unprivileged equivalent, said in the error). The budget's cgroup is removed on
:meth:`CpuBudget.close`; its throttling counters (``cpu.stat``) say how often the budget bit.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from mocapd.errors import ConfigError

PERIOD_US = 10_000  # 10 ms: a slower CPU is slower all the time, not frozen for most of every 100 ms period
SLICES = 2  # the quota holds at least this many of the kernel's bandwidth slices: one for each of two CPUs
DEFAULT_SLICE_US = 5_000  # the kernel's sched_cfs_bandwidth_slice_us where it cannot be read
MIN_CORES = 0.1  # the kernel wants a quota of at least 1 ms: 0.1 of the 10 ms period
_held: list[CpuBudget] = []  # the process-wide budget (one at most): what exempt() refers to


@dataclass(frozen=True)
class _Hierarchy:
    version: int  # 1 or 2
    parent: Path  # this process's cgroup directory in the hierarchy with the cpu controller


def _mounts(mountinfo: str) -> list[tuple[str, str, str]]:
    """(mount point, file system type, super options) of each mount in ``/proc/self/mountinfo`` text."""
    out = []
    for line in mountinfo.splitlines():
        left, _, right = line.partition(" - ")
        fields, rest = left.split(), right.split()
        if len(fields) >= 5 and len(rest) >= 3:
            out.append((fields[4], rest[0], rest[2]))
    return out


def find_hierarchies(proc_cgroup: str, mountinfo: str) -> list[_Hierarchy]:
    """Where this process's CPU bandwidth can be set, in the order tried: the v2 cgroup with a ``cpu`` controller,
    then the v1 ``cpu`` hierarchy, from the texts of ``/proc/self/cgroup`` and ``/proc/self/mountinfo``."""
    mounts = _mounts(mountinfo)
    paths: dict[str, str] = {}
    for line in proc_cgroup.splitlines():
        parts = line.split(":", 2)
        if len(parts) == 3:
            paths[parts[1]] = parts[2]
    out = []
    if "" in paths:
        for point, fstype, _ in mounts:
            if fstype != "cgroup2":
                continue
            here = Path(point) / paths[""].lstrip("/")
            listed = here / "cgroup.controllers"
            if listed.exists() and "cpu" in listed.read_text().split():
                out.append(_Hierarchy(2, here))
                break
    for point, fstype, options in mounts:
        key = next((k for k in paths if "cpu" in k.split(",")), None)
        if fstype == "cgroup" and "cpu" in options.split(",") and key is not None:
            out.append(_Hierarchy(1, Path(point) / paths[key].lstrip("/")))
            break
    return out


def bandwidth_slice_us(path: Path = Path("/proc/sys/kernel/sched_cfs_bandwidth_slice_us")) -> int:
    """The kernel's CFS bandwidth slice (µs): how much of a quota a CPU takes at a time."""
    try:
        return int(path.read_text())
    except (OSError, ValueError):
        return DEFAULT_SLICE_US


def period_for(cores: float, slice_us: int) -> int:
    """The CFS period (µs) for a budget of ``cores``: :data:`PERIOD_US`, or longer where that period's quota would
    hold fewer than :data:`SLICES` bandwidth slices of ``slice_us`` (the module's docstring says why)."""
    return max(PERIOD_US, round(SLICES * slice_us / cores))


class CpuBudget:
    """This process (all its threads, and the children it starts unless :meth:`exempt`) held to ``cores`` CPUs.

    Raises
    ------
    ConfigError
        ``cores`` out of range, or no cgroup CPU controller this process may write (the message says what to run
        instead).
    """

    def __init__(self, cores: float, *, pid: int | None = None, period_us: int | None = None) -> None:
        if not MIN_CORES <= cores <= (os.cpu_count() or 1):
            raise ConfigError(
                f"--cpu-budget {cores:g}: allowed {MIN_CORES:g} .. {os.cpu_count()} (this machine's cores)"
            )
        found = find_hierarchies(Path("/proc/self/cgroup").read_text(), Path("/proc/self/mountinfo").read_text())
        if not found:
            raise ConfigError(_unavailable("no cgroup file system with a cpu controller is mounted"))
        self.cores = cores
        self.slice_us = bandwidth_slice_us()
        self.period_us = period_for(cores, self.slice_us) if period_us is None else period_us
        self.quota_us = round(cores * self.period_us)
        errors = []
        for h in found:
            self.version, self.parent = h.version, h.parent
            self.path = h.parent / f"mocapd-budget-{os.getpid()}"
            try:
                self._enter(self.quota_us, self.period_us, pid if pid is not None else os.getpid())
                return
            except OSError as exc:
                errors.append(f"{self.path}: {exc.strerror or exc}")
                with contextlib.suppress(OSError):
                    self.path.rmdir()
        raise ConfigError(_unavailable("; ".join(errors)))

    def _enter(self, quota_us: int, period_us: int, pid: int) -> None:
        if self.version == 2:
            control = self.parent / "cgroup.subtree_control"
            if "cpu" not in control.read_text().split():
                control.write_text("+cpu")  # refused (EBUSY) where the parent holds processes itself
            self.path.mkdir(exist_ok=True)
            (self.path / "cpu.max").write_text(f"{quota_us} {period_us}")
        else:
            self.path.mkdir(exist_ok=True)
            (self.path / "cpu.cfs_period_us").write_text(str(period_us))
            (self.path / "cpu.cfs_quota_us").write_text(str(quota_us))
        (self.path / "cgroup.procs").write_text(str(pid))

    def exempt(self, pid: int) -> None:
        """Move process ``pid`` (a fake camera: hardware's stand-in) out of the budget, back to the parent cgroup."""
        with contextlib.suppress(OSError):  # it ended meanwhile
            (self.parent / "cgroup.procs").write_text(str(pid))

    def throttling(self) -> dict[str, float]:
        """The kernel's counters: periods run, periods throttled, time throttled (s)."""
        stat = {}
        with contextlib.suppress(OSError):
            for line in (self.path / "cpu.stat").read_text().splitlines():
                key, _, value = line.partition(" ")
                stat[key] = float(value)
        throttled_s = stat.get("throttled_usec", 0.0) / 1e6 or stat.get("throttled_time", 0.0) / 1e9
        return {"periods": stat.get("nr_periods", 0.0), "throttled_periods": stat.get("nr_throttled", 0.0),
                "throttled_s": round(throttled_s, 3)}  # fmt: skip

    def describe(self) -> dict[str, object]:
        """JSON-able: the budget and how it is held (for benchmark reports)."""
        knob = "cpu.max" if self.version == 2 else "cpu.cfs_quota_us"
        return {"cores": self.cores, "mechanism": f"cgroup v{self.version} {knob}", "cgroup": str(self.path),
                "quota_us": self.quota_us, "period_us": self.period_us, "slice_us": self.slice_us,
                **self.throttling()}  # fmt: skip

    def close(self) -> None:
        """This process back to its parent cgroup, the budget's cgroup removed."""
        self.exempt(os.getpid())
        with contextlib.suppress(OSError):
            self.path.rmdir()


def _unavailable(why: str) -> str:
    return (f"cannot hold mocapd to a CPU budget ({why}); it needs write access to a cgroup cpu controller "
            "(root, or a delegated cgroup: `systemd-run --user --scope -p CPUQuota=80% mocapd ...` does the same "
            "without --cpu-budget)")  # fmt: skip


def quota_cores(proc_cgroup: str | None = None, mountinfo: str | None = None) -> float | None:
    """The CPUs this process's cgroup lets it use per period (its CFS quota over its period: a ``--cpu-budget``, a
    systemd ``CPUQuota=``, a container's limit), None where no quota is set."""
    try:
        found = find_hierarchies(
            Path("/proc/self/cgroup").read_text() if proc_cgroup is None else proc_cgroup,
            Path("/proc/self/mountinfo").read_text() if mountinfo is None else mountinfo,
        )
    except OSError:
        return None
    for h in found:
        with contextlib.suppress(OSError, ValueError):
            if h.version == 2:
                quota, period = (h.parent / "cpu.max").read_text().split()[:2]
                if quota != "max":
                    return int(quota) / int(period)
            else:
                quota_us = int((h.parent / "cpu.cfs_quota_us").read_text())
                if quota_us > 0:
                    return quota_us / int((h.parent / "cpu.cfs_period_us").read_text())
    return None


@contextlib.contextmanager
def held(cores: float | None) -> Iterator[CpuBudget | None]:
    """``with held(cores):`` this process held to ``cores`` CPUs inside the block (None: not held)."""
    if cores is None:
        yield None
        return
    budget = hold(cores)
    try:
        yield budget
    finally:
        release()


def hold(cores: float) -> CpuBudget:
    """Hold this process to ``cores`` CPUs until :func:`release`; the budget :func:`exempt` refers to."""
    release()
    _held.append(CpuBudget(cores))
    return _held[0]


def active() -> CpuBudget | None:
    """The budget this process is held to (None: none)."""
    return _held[0] if _held else None


def exempt(pid: int) -> None:
    """Process ``pid`` (a stand-in for hardware, such as a fake camera) out of the active budget; no-op without."""
    for budget in _held:
        budget.exempt(pid)


def release() -> None:
    """End the active budget, if any."""
    while _held:
        _held.pop().close()
