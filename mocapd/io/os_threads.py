"""Threads as the OS sees them: their names (for ``top -H``, ``ps -L`` and the benchmark's CPU accounting) and
their CPU priority, so that the daemon's throughput threads yield the CPU to its event loop.

The event loop runs the output tick, which has a deadline every output period; the detector, the keypoint tracking
and the cameras' capture threads do throughput work with none. On a 2-core laptop they all want the CPU at once and
the kernel shares it fairly, so a tick that needs 6 ms of CPU took 10-15 ms of wall time and missed its period
(``mocapd bench latency --rig cameras``, docs/daemon.md "Thread priorities"). A nicer worker thread gets the CPU
whenever the loop does not want it, so the work still gets done, a little later.

On Linux the nice value is a per-thread attribute (setpriority(2) on a thread id: NPTL's documented deviation from
POSIX) and threads inherit it when created, so onnxruntime's intra-op threads, started by a detector worker thread,
run at that thread's nice value. Elsewhere nice is per process and this does nothing: lowering the whole process
would lower the loop too.
"""

from __future__ import annotations

import ctypes
import logging
import os
import sys
import threading

log = logging.getLogger(__name__)

MAX_NICE = 19
CAPTURE_THREAD = "mocapd-capture"
"""OS-level name of the cameras' capture threads (once their device is open)."""


def name_os_thread(name: str) -> None:
    """Give the calling thread an OS-level name (``/proc/.../comm``, 15 bytes; Python's thread names stay in
    Python).

    Threads the named thread starts inherit the name (Linux), onnxruntime's intra-op pool included. A no-op where
    ``prctl`` is missing.
    """
    libc = ctypes.CDLL(None, use_errno=True)
    prctl = getattr(libc, "prctl", None)
    if prctl is not None:
        prctl(15, name.encode()[:15], 0, 0, 0)  # 15 = PR_SET_NAME


def nice_this_thread(increment: int) -> int:
    """Make the calling thread ``increment`` nicer (0..19; the result capped at 19); returns its nice value now.

    A no-op returning the process's nice value where nice is per process (not Linux) or ``increment`` is 0. An
    unprivileged thread can always lower its own priority; it could not raise it back, so this is for threads
    that keep the lower priority for life.
    """
    if increment < 0:
        raise ValueError(f"increment must be >= 0, got {increment}")
    now = thread_nice()
    if increment == 0 or not sys.platform.startswith("linux"):
        return now
    target = min(MAX_NICE, now + increment)
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), target)
    except OSError as exc:  # a seccomp'd sandbox may refuse even this; the thread then keeps its priority
        log.warning("could not lower thread %s's priority (nice %d -> %d): %s", threading.current_thread().name,
                    now, target, exc)  # fmt: skip
        return now
    return target


def worker_thread_setup(name: str, nice: int = 0) -> None:
    """A worker thread's initializer: its OS-level name (:func:`name_os_thread`) and ``nice`` more niceness
    (:func:`nice_this_thread`), both inherited by the threads it starts."""
    name_os_thread(name)
    nice_this_thread(nice)


def thread_nice() -> int:
    """The calling thread's nice value."""
    if not sys.platform.startswith("linux"):
        return os.getpriority(os.PRIO_PROCESS, 0)
    return os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
