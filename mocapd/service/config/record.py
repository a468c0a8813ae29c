"""The ``[record]`` section: record-and-stream sessions (see ``docs/sessions.md``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from mocapd.errors import ConfigError

_KEYS = {"enabled", "directory", "flush_interval_s", "fsync", "queue_size", "video"}


@dataclass(frozen=True)
class RecordConfig:
    """Where and how sessions are recorded."""

    enabled: bool = False
    """Record every ``mocapd run`` / ``mocapd demo`` (``--record DIR`` records one run regardless)."""
    directory: str = "sessions"
    """Parent directory of the session directories (named ``session-YYYYmmdd-HHMMSS``); relative to the cwd."""
    flush_interval_s: float = 0.25
    """Streams are flushed (and fsynced) this often: the most a crash or power cut can lose, s in (0, 1]."""
    fsync: bool = True
    """fsync after each flush (survives a power cut) or only flush to the OS (survives a process crash)."""
    queue_size: int = 100_000
    """Records waiting for the writer thread before new ones are dropped (and counted)."""
    video: bool = False
    """Camera frames as video: not supported yet (true is rejected)."""


def parse_record_config(t: dict[str, Any]) -> RecordConfig:
    unknown = set(t) - _KEYS
    if unknown:
        raise ConfigError(f"unknown key(s) {sorted(unknown)} in [record]; allowed: {sorted(_KEYS)}")
    out = RecordConfig()
    for key in ("enabled", "fsync", "video"):
        if key in t and not isinstance(t[key], bool):
            raise ConfigError(f"record.{key} = {t[key]!r}; allowed: true or false")
    if t.get("video", False):
        raise ConfigError("record.video = true: recording camera frames as video is not supported yet; use false")
    directory = t.get("directory", out.directory)
    if not isinstance(directory, str) or not directory:
        raise ConfigError(f"record.directory = {directory!r}; allowed: a non-empty path")
    flush = t.get("flush_interval_s", out.flush_interval_s)
    if isinstance(flush, bool) or not isinstance(flush, int | float) or not 0 < flush <= 1.0:
        raise ConfigError(f"record.flush_interval_s = {flush!r}; allowed: a number in (0, 1] seconds")
    size = t.get("queue_size", out.queue_size)
    if isinstance(size, bool) or not isinstance(size, int) or not 100 <= size <= 10_000_000:
        raise ConfigError(f"record.queue_size = {size!r}; allowed: an integer in [100, 10000000]")
    return RecordConfig(
        enabled=bool(t.get("enabled", False)),
        directory=directory,
        flush_interval_s=float(flush),
        fsync=bool(t.get("fsync", True)),
        queue_size=size,
        video=False,
    )
