"""``mocapd replay``: publish a recorded session's pose frames through pose sinks at the recorded pace.

The sinks are the daemon's :class:`~mocapd.service.daemon.PoseSink` s (WebSocket, UDP, ... whatever
:func:`stream_sinks` builds from the config), so clients see a replay exactly as they see a live session:
same frame counters, solve times, identities and poses. Frame ``i`` goes out at ``start + (t_i - t_0) / speed``
on the host clock (``t`` the recorded solve time); a replay that falls behind publishes late rather than
skipping frames, and counts them.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mocapd.errors import InputError
from mocapd.pipeline.scheduler import PersonPose, PoseFrame
from mocapd.protocols.session_format import PoseRecord
from mocapd.service.daemon import PoseSink


def pose_frame(r: PoseRecord) -> PoseFrame:
    """A recorded frame as the daemon published it."""
    people = [
        PersonPose(p.identity, p.track, p.suit, np.array(p.theta), np.array(p.joints), p.confidence, p.views,
                   p.imus, p.iterations, p.converged, p.skeleton, p.t_pose_ns)
        for p in r.people
    ]  # fmt: skip
    return PoseFrame(r.frame, r.t_solve_ns, r.tick_ns, people, r.missing_cameras, r.output)


@dataclass
class ReplayStats:
    frames: int = 0
    late: int = 0
    """Frames published more than one output period after their due time."""
    wall_s: float = 0.0


async def replay(
    frames: list[PoseRecord],
    sinks: list[PoseSink],
    *,
    speed: float = 1.0,
    clock: Callable[[], int] = time.monotonic_ns,
    on_frame: Callable[[PoseFrame], None] | None = None,
) -> ReplayStats:
    """Start the sinks, publish every frame at its recorded time (scaled by 1/``speed``), close the sinks."""
    if not (np.isfinite(speed) and speed > 0):
        raise InputError(f"replay speed must be a positive number, got {speed!r}")
    stats = ReplayStats()
    for s in sinks:
        await s.start()
    try:
        if frames:
            t0 = frames[0].t_solve_ns
            start = clock()
            period = np.median(np.diff([f.t_solve_ns for f in frames])) if len(frames) > 1 else 0.0
            for r in frames:
                due = start + round((r.t_solve_ns - t0) / speed)
                delay = (due - clock()) / 1e9
                if delay > 0:
                    await asyncio.sleep(delay)
                elif -delay * 1e9 > period / speed:
                    stats.late += 1
                frame = pose_frame(r)
                for s in sinks:
                    s.publish(frame)
                if on_frame is not None:
                    on_frame(frame)
                stats.frames += 1
            stats.wall_s = (clock() - start) / 1e9
    finally:
        for s in sinks:
            await s.aclose()
    return stats
