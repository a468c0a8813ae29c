"""Ending a daemon process quickly once it has closed everything it opened (see :mod:`mocapd.io.lifecycle`)."""

from __future__ import annotations

from mocapd.io.lifecycle import exit_now

__all__ = ["exit_now"]
