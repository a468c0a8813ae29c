"""The live plausibility monitor deciding in plain floats (issue 39: it runs per person and tick on the event loop)
counts what the array arithmetic counted: the monitor before issue 39 (kept here verbatim as the oracle) and the
new one step through the same poses, and after every step their events, seconds, worst bends (bit for bit) and
running checks are equal; on smooth random motion with wrong-way bends and a pelvis turned round, on poses put
within a few ulps of every threshold, and on poses with NaN."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from mocapd.core.plausibility import (
    _MONITORED,
    _MONITORED_IDX,
    HINGES,
    PlausibilityMonitor,
    PlausibilityOptions,
    _flexion,
    _Run,
)
from mocapd.core.rotations import matrix_from_rotvec
from mocapd.core.skeleton import BONE_INDEX, N_BONES, POSE_DIM

FloatArray = NDArray[np.float64]


@dataclass
class OldMonitor:
    """``PlausibilityMonitor`` before issue 39 (its state and ``step``), verbatim."""

    options: PlausibilityOptions = field(default_factory=PlausibilityOptions)
    events: dict[str, int] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)
    worst_deg: dict[str, float] = field(default_factory=dict)
    _runs: dict[str, _Run] = field(default_factory=dict)
    _roots: list[tuple[float, FloatArray]] = field(default_factory=list)
    _last_s: float | None = None

    def step(self, t_s: float, theta: FloatArray) -> None:
        """One solved pose θ (66,) at time ``t_s`` (s, increasing)."""
        th = np.asarray(theta, dtype=np.float64)
        dt = 0.0 if self._last_s is None else max(0.0, t_s - self._last_s)
        self._last_s = t_s
        # One conversion for every bone the checks read (this runs per person and tick in the daemon).
        R = dict(zip(_MONITORED, matrix_from_rotvec(th[3:].reshape(N_BONES, 3)[_MONITORED_IDX]), strict=True))
        for name, (_, bone) in HINGES.items():
            a = float(_flexion(R[bone], name))
            self._advance(name, t_s, dt, a < -self.options.wrong_way_deg, -a, self.options.min_duration_s)
        self._advance("pelvis_backwards", t_s, dt, self._pelvis_backwards(t_s, th, R), 0.0, self.options.backwards_s)

    def _pelvis_backwards(self, t_s: float, th: FloatArray, R: dict[str, FloatArray]) -> bool:
        o = self.options
        self._roots.append((t_s, th[:3].copy()))
        while self._roots and self._roots[0][0] < t_s - o.travel_window_s:
            self._roots.pop(0)
        t0, r0 = self._roots[0]
        if t_s - t0 < 0.5 * o.travel_window_s:
            return False
        v = (th[:3] - r0) / (t_s - t0)
        travel = np.array([v[0], v[2]])
        speed = float(np.linalg.norm(travel))
        if speed < o.min_speed:
            return False
        hips = R["Hips"]
        facing = hips[[0, 2], 2]
        legs = np.zeros(2)
        for b in ("LeftUpperLeg", "RightUpperLeg"):
            legs += (hips @ R[b])[[0, 2], 2]
        cos_max = math.cos(math.radians(o.backwards_deg))

        def cos(a: FloatArray) -> float:
            n = float(np.linalg.norm(a))
            return float(a @ travel) / (n * speed) if n > 1e-6 else 0.0

        return cos(facing) < cos_max and cos(legs) > -cos_max

    def _advance(self, name: str, t_s: float, dt: float, bad: bool, amount: float, min_s: float) -> None:
        run = self._runs.setdefault(name, _Run())
        if not bad:
            run.start_s, run.worst, run.counted = None, 0.0, False
            return
        if run.start_s is None:
            run.start_s = t_s
        run.worst = max(run.worst, amount)
        length = t_s - run.start_s + dt
        if not run.counted and length >= min_s:
            run.counted = True
            self.events[name] = self.events.get(name, 0) + 1
            self.seconds[name] = self.seconds.get(name, 0.0) + length - dt
        if run.counted:
            self.seconds[name] = self.seconds.get(name, 0.0) + dt
            self.worst_deg[name] = max(self.worst_deg.get(name, 0.0), run.worst)


def _same_after_every_step(poses: FloatArray, t_s: FloatArray) -> OldMonitor:
    old, new = OldMonitor(), PlausibilityMonitor()
    for t, th in zip(t_s.tolist(), poses, strict=True):
        old.step(t, th)
        new.step(t, th)
        assert (new.events, new.seconds, new.worst_deg) == (old.events, old.seconds, old.worst_deg)
        assert {k: vars(r) for k, r in new._runs.items()} == {k: vars(r) for k, r in old._runs.items()}
    return old


def _smooth(rng: np.random.Generator, n: int, dims: int, scale: float) -> FloatArray:
    """Random motion: white noise summed and smoothed, so that a bend lasts long enough to be an event."""
    x = np.cumsum(rng.normal(0.0, scale, (n + 30, dims)), axis=0)
    return np.asarray(np.stack([np.convolve(x[:, d], np.ones(30) / 30, "valid")[:n] for d in range(dims)], axis=1))


def test_random_motion_counts_the_same_events_seconds_and_worst_bends() -> None:
    counted: dict[str, int] = {}
    for seed in range(4):
        rng = np.random.default_rng(seed)
        n = 1500
        th = np.zeros((n, POSE_DIM))
        th[:, 3:] = _smooth(rng, n, POSE_DIM - 3, 0.04)
        root = np.cumsum(_smooth(rng, n, 3, 0.004), axis=0)  # walking pace and direction drifting
        th[:, :3] = root
        th[n // 2 :, 4] += np.pi  # the pelvis turned round for the second half
        t_s = np.arange(n) / 60.0 + rng.uniform(0.0, 0.002, n)  # ticks a little uneven
        old = _same_after_every_step(th, t_s)
        for k, v in old.events.items():
            counted[k] = counted.get(k, 0) + v
    assert set(counted) == {*HINGES, "pelvis_backwards"}  # every check had events to count


def _knee_at(flexion_deg: float) -> FloatArray:
    """A pose whose left knee's flexion is ``flexion_deg``: the shank turned about the thigh's X axis."""
    th = np.zeros(POSE_DIM)
    th[3 + 3 * BONE_INDEX["LeftLowerLeg"]] = -math.radians(flexion_deg)
    return th


def test_poses_within_ulps_of_the_thresholds_count_the_same() -> None:
    o = PlausibilityOptions()
    rng = np.random.default_rng(7)
    # Left knee flexions at the threshold and a few ulps either side, runs long enough to count.
    base = -o.wrong_way_deg
    angles = [base + k * math.ulp(base) for k in range(-4, 5)] * 40
    poses = np.stack([_knee_at(a) for a in angles])
    assert {float(_flexion(matrix_from_rotvec(p[3 + 3 * BONE_INDEX["LeftLowerLeg"] :][:3]), "left_knee"))
            for p in poses} != {base}  # fmt: skip
    _same_after_every_step(poses, np.arange(len(poses)) / 60.0)
    # A knee folded to ±180° (atan2's cut: the sign of an entry ~1e-16 decides between no event and the worst bend).
    folded = np.stack([_knee_at(a) for a in np.repeat([180.0 + k * 1e-14 for k in range(-6, 7)], 20)])
    folded[:, 3 + 3 * BONE_INDEX["LeftLowerLeg"] :][:, 1:3] = rng.normal(0.0, 1e-15, (len(folded), 2))
    assert _same_after_every_step(folded, np.arange(len(folded)) / 60.0).events["left_knee"] > 0
    # The root travelling at the speed limit, and the pelvis at the backwards angle, to a few ulps.
    n = 400
    th = np.zeros((n, POSE_DIM))
    t_s = np.arange(n) / 60.0
    speed = o.min_speed * (1.0 + rng.integers(-3, 4, n) * 2e-16)
    th[:, 2] = np.cumsum(speed / 60.0)
    yaw = math.radians(o.backwards_deg) + rng.integers(-3, 4, n) * 1e-16
    th[:, 4] = yaw
    _same_after_every_step(th, t_s)
    th[:, 4] = np.pi
    th[:, 3 + 3 * BONE_INDEX["LeftUpperLeg"] + 1] = math.pi - math.radians(o.backwards_deg) + rng.normal(0, 1e-16, n)
    _same_after_every_step(th, t_s)


def test_poses_with_nan_count_the_same() -> None:
    rng = np.random.default_rng(3)
    n = 600
    th = np.zeros((n, POSE_DIM))
    th[:, 3:] = _smooth(rng, n, POSE_DIM - 3, 0.05)
    th[:, 2] = np.arange(n) / 60.0
    th[:, 4] = np.pi
    th[rng.choice(n, 40, replace=False), rng.integers(0, POSE_DIM, 40)] = np.nan
    th[100:130, :3] = np.nan
    _same_after_every_step(th, np.arange(n) / 60.0)
