"""Scoring the daemon's output against the synthetic world's truth, as it is published."""

from __future__ import annotations

from collections import deque

import numpy as np

from mocapd.pipeline.scheduler import PoseFrame
from mocapd.sim.world import SyntheticWorld

SCORE_EVERY = 4  # score every n-th published frame: a median needs no more, and scoring costs the tick ~1 ms


class TruthError:
    """A pose sink that scores each published person against the nearest true person: the mean distance of the 17
    keypoint sites (:meth:`SyntheticWorld.nearest_site_error`)."""

    name = "truth"

    def __init__(self, world: SyntheticWorld, epoch_ns: int) -> None:
        self.world = world
        self.epoch_ns = epoch_ns
        self.errors: deque[float] = deque(maxlen=54_000)  # the last hour of scored frames at 60 Hz
        self.frames = 0

    def publish(self, frame: PoseFrame) -> None:
        self.frames += 1
        if self.frames % SCORE_EVERY:
            return
        for person in frame.people:  # each pose against the truth at its own instant (later when predicted)
            t = (frame.pose_time_ns(person) - self.epoch_ns) / 1e9
            self.errors.append(self.world.nearest_site_error(person.theta, person.skeleton, t)[0])

    def recent_mm(self, n: int = 30) -> float | None:
        """Median error of the last ``n`` scored person-frames, mm (None before any)."""
        return 1e3 * float(np.median(list(self.errors)[-n:])) if self.errors else None

    def status_field(self) -> str:
        err = self.recent_mm()
        return f"keypoint error {'-' if err is None else f'{err:.1f}'} mm"

    async def start(self) -> None:
        return None

    async def aclose(self) -> None:
        return None


class RootRelativeError:
    """A pose sink that scores each published suit wearer against the truth of the person wearing the suit: the
    mean distance of the 21 joints after moving both roots to the origin (mm). Without cameras nothing fixes the
    root's place in the room, so its drift is left out: this is how well the suit poses the body."""

    name = "truth"

    def __init__(self, world: SyntheticWorld, epoch_ns: int) -> None:
        self.world = world
        self.epoch_ns = epoch_ns
        self.person = {s.id: s.person for s in world.suits}
        self.errors: deque[float] = deque(maxlen=54_000)
        self.frames = 0

    def publish(self, frame: PoseFrame) -> None:
        self.frames += 1
        if self.frames % SCORE_EVERY:
            return
        for person in frame.people:
            who = self.person.get(person.suit or "")
            if who is None:
                continue
            truth = self.world.joints_at(who, (frame.pose_time_ns(person) - self.epoch_ns) / 1e9)
            solved = person.joints - person.joints[0]
            self.errors.append(float(np.linalg.norm(solved - (truth - truth[0]), axis=1).mean()))

    def recent_mm(self, n: int = 30) -> float | None:
        """Median error of the last ``n`` scored person-frames, mm (None before any)."""
        return 1e3 * float(np.median(list(self.errors)[-n:])) if self.errors else None

    def status_field(self) -> str:
        err = self.recent_mm()
        return f"root-relative joint error {'-' if err is None else f'{err:.1f}'} mm"

    async def start(self) -> None:
        return None

    async def aclose(self) -> None:
        return None
