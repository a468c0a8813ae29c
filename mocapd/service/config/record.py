"""The ``[record]`` section: record-and-stream sessions (see ``docs/sessions.md``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from mocapd.errors import ConfigError

_KEYS = {
    "enabled", "directory", "flush_interval_s", "fsync", "queue_size", "video", "frames", "frames_hz",
    "frames_width", "frames_quality",
}  # fmt: skip


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
    frames: bool = False
    """Record downscaled camera frames (JPEG, ``frames`` stream) for the camera panels of ``mocapd replay``."""
    frames_hz: float = 2.0
    """Recorded frames per second per camera."""
    frames_width: int = 320
    """Width (pixels) recorded frames are downscaled to."""
    frames_quality: int = 70
    """JPEG quality of recorded frames (1..100)."""


def parse_record_config(t: dict[str, Any]) -> RecordConfig:
    unknown = set(t) - _KEYS
    if unknown:
        raise ConfigError(f"unknown key(s) {sorted(unknown)} in [record]; allowed: {sorted(_KEYS)}")
    out = RecordConfig()
    for key in ("enabled", "fsync", "video", "frames"):
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
    hz = t.get("frames_hz", out.frames_hz)
    if isinstance(hz, bool) or not isinstance(hz, int | float) or not 0.1 <= hz <= 30:
        raise ConfigError(f"record.frames_hz = {hz!r}; allowed: a number 0.1..30")
    width = t.get("frames_width", out.frames_width)
    if isinstance(width, bool) or not isinstance(width, int) or not 16 <= width <= 4096:
        raise ConfigError(f"record.frames_width = {width!r}; allowed: an integer 16..4096")
    quality = t.get("frames_quality", out.frames_quality)
    if isinstance(quality, bool) or not isinstance(quality, int) or not 1 <= quality <= 100:
        raise ConfigError(f"record.frames_quality = {quality!r}; allowed: an integer 1..100")
    return RecordConfig(
        frames=bool(t.get("frames", False)),
        frames_hz=float(hz),
        frames_width=width,
        frames_quality=quality,
        enabled=bool(t.get("enabled", False)),
        directory=directory,
        flush_interval_s=float(flush),
        fsync=bool(t.get("fsync", True)),
        queue_size=size,
        video=False,
    )
