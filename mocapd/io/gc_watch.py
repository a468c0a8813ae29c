"""The interpreter's garbage collections as the daemon sees them: how many of each generation, and how long they
stopped every thread (the collector holds the interpreter lock, so a collection of the whole heap is a pause of the
output tick too).

A callback in :data:`gc.callbacks` times each collection from its "start" to its "stop" call. It costs two clock
reads and a few additions per collection (tens to hundreds a second, each far longer than that), so it stays on in
every run; ``/status`` carries the counts since start (``gc``), and ``tools/soak.py`` differences them every second
to put a collection beside a second of missed ticks.
"""

from __future__ import annotations

import gc
import time
from typing import Any

GENERATIONS = 3
"""CPython's generations (0, 1, 2: the whole heap)."""


class GcWatch:
    """Counts of the collections of each generation since :meth:`install`, their total and longest pause.

    Attributes
    ----------
    collections : list of int
        Collections of each generation, shape ``(3,)``.
    pause_ns : list of int
        Their summed pause (nanoseconds, monotonic clock), shape ``(3,)``.
    max_pause_ns : list of int
        The longest single pause of each generation, shape ``(3,)``.
    collected : list of int
        Objects freed by each generation's collections, shape ``(3,)``.
    """

    def __init__(self) -> None:
        self.collections = [0] * GENERATIONS
        self.pause_ns = [0] * GENERATIONS
        self.max_pause_ns = [0] * GENERATIONS
        self.collected = [0] * GENERATIONS
        self._started_ns: int | None = None
        #: objects :meth:`freeze` took out of every collection (counted then: see :meth:`freeze`)
        self.frozen = 0

    def install(self) -> None:
        """Start counting (idempotent)."""
        if self._callback not in gc.callbacks:
            gc.callbacks.append(self._callback)

    def freeze(self) -> None:
        """:func:`gc.freeze`: every object alive now out of every later collection, and how many there were.

        Counted here, once: :func:`gc.get_freeze_count` walks the whole frozen list each call, and in the daemon
        (~180 000 start-up objects, scattered over the heap by then) that took ~14 ms of the event loop each
        ``/status`` snapshot, once a second while the web viewer was open (py-spy, issue 39's camera demo): a
        tick or two missed every second on a slow machine.
        """
        gc.freeze()
        self.frozen = gc.get_freeze_count()

    def uninstall(self) -> None:
        """Stop counting (the counts stay)."""
        if self._callback in gc.callbacks:
            gc.callbacks.remove(self._callback)
        self._started_ns = None

    def _callback(self, phase: str, info: dict[str, Any]) -> None:
        if phase == "start":
            self._started_ns = time.perf_counter_ns()
            return
        started, self._started_ns = self._started_ns, None
        if started is None:  # installed while a collection ran
            return
        g = int(info.get("generation", GENERATIONS - 1))
        pause = time.perf_counter_ns() - started
        self.collections[g] += 1
        self.pause_ns[g] += pause
        self.max_pause_ns[g] = max(self.max_pause_ns[g], pause)
        self.collected[g] += int(info.get("collected", 0))

    def status(self) -> dict[str, Any]:
        """The counts for ``/status``: per generation ``collections``, ``pause_ms`` (the sum), ``max_pause_ms``,
        ``collected`` (objects freed), and ``frozen``, the objects :meth:`freeze` took out of every collection."""
        return {
            "generations": [
                {"collections": self.collections[g], "pause_ms": round(self.pause_ns[g] / 1e6, 3),
                 "max_pause_ms": round(self.max_pause_ns[g] / 1e6, 3), "collected": self.collected[g]}
                for g in range(GENERATIONS)
            ],
            "frozen": self.frozen,
        }  # fmt: skip
