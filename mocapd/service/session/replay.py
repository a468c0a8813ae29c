"""``mocapd replay``: publish a recorded session's pose frames through pose sinks at the recorded pace.

The sinks are the daemon's :class:`~mocapd.service.daemon.PoseSink` s (WebSocket, UDP, ... whatever
:func:`stream_sinks` builds from the config), so clients see a replay exactly as they see a live session:
same frame counters, solve times, identities and poses. Frame ``i`` goes out at ``start + (t_i - t_0) / speed``
on the host clock (``t`` the recorded solve time); a replay that falls behind publishes late rather than
skipping frames, and counts them.

Camera panels (:func:`replay_camera_views`): the session's detections and, when it recorded them, its camera
frames are fed to a :class:`~mocapd.pipeline.camera_views.CameraViews` at their recorded moments on the same
timeline (a detection when the daemon received it, a frame when it was captured), so the viewer's camera panels
show the session as they showed it live.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial

import numpy as np

from mocapd.core.sorting import Detections2D
from mocapd.errors import InputError
from mocapd.io.session import Session
from mocapd.pipeline.camera_views import CameraViews, LatestSnapshot, Snapshot, SnapshotSource
from mocapd.pipeline.scheduler import PersonPose, PoseFrame
from mocapd.protocols.session_format import PoseRecord
from mocapd.service.daemon import PoseSink
from mocapd.service.session.solve import SessionRig


def pose_frame(r: PoseRecord) -> PoseFrame:
    """A recorded frame as the daemon published it."""
    people = [
        PersonPose(p.identity, p.track, p.suit, np.array(p.theta), np.array(p.joints), p.confidence, p.views,
                   p.imus, p.iterations, p.converged, p.skeleton, p.t_pose_ns, hands=p.hands)
        for p in r.people
    ]  # fmt: skip
    return PoseFrame(r.frame, r.t_solve_ns, r.tick_ns, people, r.missing_cameras, r.output)


def replay_camera_views(
    session: Session, rig: SessionRig, frames: Sequence[PoseRecord]
) -> tuple[CameraViews, list[tuple[int, Callable[[], None]]]]:
    """Camera views of a recorded session and the replay events that feed them (see the module doc).

    Events are placed on the solve-time axis of the replay: a detection that reached the daemon at ``arrival``
    is fed at the solve time of the recorded tick at ``arrival`` (interpolated between the recorded frames' (tick,
    solve) times: under ``latency_s = "auto"`` the delay between them moves), a frame at its capture time. The
    views' clock follows the replay: the tick time of the frame published last.
    """
    recorded = session.frames()
    n = len(rig.cameras)
    sources: list[SnapshotSource | None] = [LatestSnapshot() for _ in range(n)] if recorded else [None] * n
    tick = [frames[0].tick_ns if frames else 0]
    ticks = np.array([r.tick_ns for r in frames], dtype=np.float64)
    order = np.argsort(ticks, kind="stable")
    ticks = ticks[order]
    delays = ticks - np.array([r.t_solve_ns for r in frames], dtype=np.float64)[order]

    def on_solve_axis(arrival_ns: int) -> int:
        """Where a wall-clock arrival falls on the solve-time axis: the delay of the nearest recorded ticks."""
        return arrival_ns - int(np.interp(arrival_ns, ticks, delays)) if frames else arrival_ns

    def now() -> int:
        return tick[0]

    views = CameraViews(rig.cameras, rig.targets, rig.skeleton, sources, now=now)
    events: list[tuple[int, Callable[[], None]]] = []
    for r in frames:
        events.append((r.t_solve_ns, partial(tick.__setitem__, 0, r.tick_ns)))
    for k in session.keypoints():
        dets = Detections2D(k.keypoints, k.confidences)
        events.append(
            (on_solve_axis(k.arrival_ns), partial(views.on_detections, k.camera, k.capture_ns, dets, k.arrival_ns))
        )
    for f in recorded:
        src = sources[f.camera] if 0 <= f.camera < len(sources) else None
        if isinstance(src, LatestSnapshot):
            events.append((f.capture_ns, partial(src.put, Snapshot(f.capture_ns, jpeg=f.jpeg))))
    events.sort(key=lambda e: e[0])
    return views, events


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
    events: Sequence[tuple[int, Callable[[], None]]] = (),
    stop: asyncio.Event | None = None,
) -> ReplayStats:
    """Start the sinks, publish every frame at its recorded time (scaled by 1/``speed``) until the last one or
    ``stop``, close the sinks.

    ``events``: (time on the solve-time axis, action) in time order, each run just before the first frame solved
    at or after its time (the camera panels' inputs, :func:`replay_camera_views`)."""
    stop = stop if stop is not None else asyncio.Event()
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
            k = 0
            for r in frames:
                if stop.is_set():
                    break
                while k < len(events) and events[k][0] <= r.t_solve_ns:
                    events[k][1]()
                    k += 1
                due = start + round((r.t_solve_ns - t0) / speed)
                delay = (due - clock()) / 1e9
                if delay > 0:
                    with contextlib.suppress(TimeoutError):  # the frame's time came, or a stop
                        await asyncio.wait_for(stop.wait(), delay)
                    if stop.is_set():
                        break
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
