"""Supervision of the daemon's long-running tasks: a failure is logged with its traceback, counted, and the task is
restarted after a back-off that doubles up to a maximum, while every other task keeps running.

Cancellation (shutdown) is never caught: it ends the task. Only ``Exception`` is caught — a ``KeyboardInterrupt``
or ``SystemExit`` still ends the process.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any

log = logging.getLogger(__name__)


@dataclass
class TaskHealth:
    """What a supervised task has done."""

    name: str
    starts: int = 0
    failures: int = 0
    running: bool = False
    last_error: str | None = None
    errors: list[str] = field(default_factory=list)  # the last few, newest last

    def as_dict(self) -> dict[str, Any]:
        return {"starts": self.starts, "failures": self.failures, "running": self.running,
                "last_error": self.last_error}  # fmt: skip


class Supervisor:
    """Runs coroutine factories under restart supervision (inside the caller's TaskGroup)."""

    def __init__(self, restart_min_s: float = 0.5, restart_max_s: float = 10.0) -> None:
        self.restart_min_s = restart_min_s
        self.restart_max_s = restart_max_s
        self.tasks: dict[str, TaskHealth] = {}

    async def supervise(self, name: str, factory: Callable[[], Awaitable[None]], restart_on_exit: bool = True) -> None:
        """Run ``factory()`` until it returns (restarted if ``restart_on_exit``) or is cancelled."""
        health = self.tasks.setdefault(name, TaskHealth(name))
        backoff = self.restart_min_s
        while True:
            health.starts += 1
            health.running = True
            started = asyncio.get_running_loop().time()
            try:
                await factory()
            except Exception as exc:  # supervision boundary: logged with traceback, counted, restarted
                health.failures += 1
                health.last_error = f"{type(exc).__name__}: {exc}"
                health.errors = [*health.errors[-9:], health.last_error]
                log.error("task %s failed (%s); restarting in %.1f s", name, health.last_error, backoff, exc_info=exc)
            else:
                if not restart_on_exit:
                    health.running = False
                    return
                log.warning("task %s returned; restarting in %.1f s", name, backoff)
            finally:
                health.running = False
            if asyncio.get_running_loop().time() - started > 10 * self.restart_max_s:
                backoff = self.restart_min_s  # it ran well for a long time: start the back-off over
            await asyncio.sleep(backoff)
            backoff = min(2.0 * backoff, self.restart_max_s)
