"""How busy this machine is, for the few end-to-end tests that must bound a wait (issue 46).

Tests wait on events (a frame, a log line, a status field), not on wall-clock sleeps; where a wait still needs a
bound so that a broken daemon fails the test instead of hanging it, the bound is scaled by :func:`load_factor`: a
machine whose run queue is 6 times its cores (load 12 on 2 cores, a shared CI runner) gives every process about a
sixth of a core, and whatever a test waits for takes about 6 times as long.
"""

from __future__ import annotations

import os

#: the largest factor a bound is scaled by: beyond it a machine is too busy for any real-time test to mean much
MAX_FACTOR = 10.0


def load_factor() -> float:
    """The 1-minute load average per usable core, at least 1 (a quiet machine) and at most :data:`MAX_FACTOR`."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return min(MAX_FACTOR, max(1.0, os.getloadavg()[0] / max(cores, 1)))
