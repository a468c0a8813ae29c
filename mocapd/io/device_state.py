"""The one thing the daemon asks every device before it reports READY: has it opened?"""

from __future__ import annotations

from typing import NamedTuple


class OpenState(NamedTuple):
    """A device's first opening: ``state`` is "open", "opening" or "failed" (``error`` says why)."""

    state: str
    error: str
