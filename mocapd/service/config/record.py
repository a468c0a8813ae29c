"""The ``[record]`` section: record-and-stream sessions (see ``docs/sessions.md``)."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field

from mocapd.service.config.schema import Allowed, PathStr, Section

MAX_QUEUE = 1_000_000
"""Most records waiting for the writer: ~200 s of a 4-person, 4-camera, 13-IMU rig, a few GB at worst."""


class RecordConfig(Section):
    """Where and how sessions are recorded."""

    enabled: bool = False
    """Record every ``mocapd run`` / ``mocapd demo`` (``--record DIR`` records one run regardless)."""
    directory: PathStr = Field("sessions", min_length=1)
    """Parent directory of the session directories (named ``session-YYYYmmdd-HHMMSS``); relative to the cwd."""
    flush_interval_s: float = Field(0.25, gt=0.0, le=1.0)
    """Streams are flushed (and fsynced) this often: the most a crash or power cut can lose, s in (0, 1]."""
    fsync: bool = True
    """fsync after each flush (survives a power cut) or only flush to the OS (survives a process crash)."""
    queue_size: int = Field(100_000, ge=100, le=MAX_QUEUE)
    """Records waiting for the writer thread before new ones are dropped (and counted)."""
    video: Annotated[Literal[False], Allowed("false (recording camera frames as video is not supported yet)")] = False
    """Camera frames as video: not supported yet (true is rejected); ``frames`` records downscaled stills."""
    frames: bool = False
    """Record downscaled camera frames (JPEG, ``frames`` stream) for the camera panels of ``mocapd replay``."""
    frames_hz: float = Field(2.0, ge=0.1, le=30.0)
    """Recorded frames per second per camera."""
    frames_width: int = Field(320, ge=16, le=4096)
    """Width (pixels) recorded frames are downscaled to."""
    frames_quality: int = Field(70, ge=1, le=100)
    """JPEG quality of recorded frames."""
