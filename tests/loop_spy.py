"""A spy on a real event loop's ``call_soon_threadsafe``: which callbacks other threads woke it for (one self-pipe
write each)."""

from __future__ import annotations

import asyncio
import contextvars
import threading
from collections.abc import Callable
from typing import Any


def spy_wakeups(loop: asyncio.AbstractEventLoop) -> list[str]:
    """Wrap ``loop.call_soon_threadsafe`` (the real one still runs) and return the list it fills: the name of each
    callback handed over from a thread other than the loop's."""
    names: list[str] = []
    real = loop.call_soon_threadsafe
    owner = threading.get_ident()

    def spy(callback: Callable[..., object], *args: Any, context: contextvars.Context | None = None) -> asyncio.Handle:
        if threading.get_ident() != owner:
            names.append(getattr(callback, "__name__", repr(callback)))
        return real(callback, *args, context=context)

    loop.call_soon_threadsafe = spy  # type: ignore[method-assign, assignment]  # a spy on this one loop
    return names
