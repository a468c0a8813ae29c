"""A suit wearer in the synthetic rig, fed to the scheduler tick by tick (no clocks, no ptys): the harness of the
heading-correction and predicted-output tests, and the load-independent half of ``tools/bench_prediction.py``.

Cameras deliver at 30 Hz with spread phases and 50 ms detection delay (as :class:`SyntheticKeypointSource`);
each IMU sample is buffered at its own instant (100 Hz), orientations through the simulated device's heading
fault when one is given (:class:`mocapd.sim.xsens.HeadingFault`, the function the simulated Xsens devices use).
World time is ``now / 1e9``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mocapd.core.people import PeopleTracker
from mocapd.core.prior import PcaPrior
from mocapd.core.solver import LMOptions
from mocapd.core.sorting import Detections2D, DetectionSorter
from mocapd.core.suit_binding import SuitBinder
from mocapd.core.terms import CostOptions
from mocapd.core.tracking import SubjectTracker, TrackingOptions
from mocapd.pipeline.imu_ingest import ImuIngest
from mocapd.pipeline.scheduler import FixedLatencyScheduler, PoseFrame, SchedulerOptions, Suit
from mocapd.sim.world import SyntheticWorld
from mocapd.sim.xsens import HeadingFault

S = 1_000_000_000
MS = 1_000_000


@dataclass
class SuitLockstep:
    """The scheduler, its world and IMU buffers, and what is fed to it; :meth:`tick` advances one output period."""

    world: SyntheticWorld
    scheduler: FixedLatencyScheduler
    ingest: ImuIngest
    faults: dict[str, HeadingFault] = field(default_factory=dict)
    live_cameras: set[int] | None = None  # None: all
    rate_hz: int = 60
    ticks: int = 0

    def __post_init__(self) -> None:
        n = len(self.world.cameras)
        self.next_cam = [S + k * (S // 30) // n for k in range(n)]
        self.pending: list[tuple[int, int, int, Detections2D]] = []
        self.imu_next = S
        self.imu = [self.world.imu_motion(s, 100.0) for s in self.world.suits]
        self.rng = np.random.default_rng(0)

    @property
    def now_ns(self) -> int:
        return S + self.ticks * S // self.rate_hz

    def tick(self) -> PoseFrame:
        now = self.now_ns
        self.feed(now)
        frame = self.scheduler.tick(now)
        self.ticks += 1
        return frame

    def run(self, seconds: float) -> list[PoseFrame]:
        return [self.tick() for _ in range(round(seconds * self.rate_hz))]

    def feed(self, now: int) -> None:
        """Deliver every detection and IMU sample due by ``now`` (what :meth:`tick` does before solving)."""
        for c in range(len(self.world.cameras)):
            while self.next_cam[c] <= now:
                t = self.next_cam[c]
                if self.live_cameras is None or c in self.live_cameras:
                    self.pending.append((t + 50 * MS, c, t, self.world.detections(c, t / 1e9, self.rng)))
                self.next_cam[c] += S // 30
        for arrival, cam, capture, dets in sorted(self.pending, key=lambda p: p[0]):
            if arrival <= now:
                self.scheduler.add_detections(cam, capture, dets, arrival)
        self.pending = [p for p in self.pending if p[0] > now]
        while self.imu_next <= now:
            i = round(self.imu_next / 1e9 * 100.0)
            for suit, (q, a) in zip(self.world.suits, self.imu, strict=True):
                for j, sid in enumerate(suit.sensor_ids):
                    name = f"{sid:08X}"
                    quat = q[j, i % q.shape[1]]
                    fault = self.faults.get(name)
                    if fault is not None:
                        quat = fault.apply(quat, self.imu_next / 1e9)
                    self.ingest.add(name, self.imu_next, device_ticks=None, packet_counter=None,
                                    quat=tuple(quat), acc=tuple(a[j, i % q.shape[1]]))  # fmt: skip
            self.imu_next += 10 * MS


def suit_lockstep(
    options: SchedulerOptions | None = None,
    *,
    cost: CostOptions | None = None,
    lm: LMOptions | None = None,
    prior: PcaPrior | None = None,
    n_people: int = 1,
    keypoints: str = "coco17",
    rate_hz: int = 60,
    n_cams: int = 4,
) -> SuitLockstep:
    """The first person wears a 13-IMU suit; recorded motion; a ring of ``n_cams`` cameras (0: the suit alone).
    Pass the solver set-up of the configuration to measure (``cost``, ``lm``, ``prior``: the shipped
    ``config.toml``'s for realistic results)."""
    world = SyntheticWorld(n_cams=n_cams, n_people=n_people, n_suits=1, seed=0, motion="recorded", keypoints=keypoints)
    ingest = ImuIngest()
    tracker = PeopleTracker(
        SubjectTracker(DetectionSorter(world.cameras), TrackingOptions(enrol_after_s=0.3)),
        SuitBinder(world.skeleton, names=world.targets.names),
    )
    suits = [Suit.from_calibration(s.id, world.calibration(s), world.skeleton) for s in world.suits]
    options = options or SchedulerOptions(rate_hz=rate_hz)
    sched = FixedLatencyScheduler(world.cameras, world.skeleton, world.targets, tracker, prior=prior, ingest=ingest,
                                  suits=suits, options=options, cost=cost, lm=lm)  # fmt: skip
    return SuitLockstep(world, sched, ingest, rate_hz=round(options.rate_hz))
