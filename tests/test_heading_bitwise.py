"""The heading observation of every sensor at once and the estimator's windows kept as arrays (the daemon's event
loop observes a suit's 13 sensors 20 times a second): the same yaw and evidence floats, and the same estimates and
offsets, to the bit, as one bone at a time and deques of tuples gave. The old code is kept here, verbatim, as the
reference."""

from __future__ import annotations

import struct
from collections import deque
from collections.abc import Sequence

import numpy as np
import pytest

from mocapd.core.heading import (
    BoneVectors,
    HeadingEstimator,
    HeadingOptions,
    SensorHeading,
    bone_vectors,
    observe_headings,
    weighted_median,
    wrap,
    yaw_quat,
)
from mocapd.core.imu import IMU_SET_13
from mocapd.core.rotations import quat_multiply, quat_rotate
from tests.test_heading import _posed


def _old_observe_headings(
    q_gb: np.ndarray, vectors: Sequence[BoneVectors], points: np.ndarray, ok: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    n = len(vectors)
    yaw = np.full(n, np.nan)
    evidence = np.zeros(n)
    for k, bv in enumerate(vectors):
        use = ok[bv.first] & ok[bv.second]
        if not use.any() or not np.all(np.isfinite(q_gb[k])):
            continue
        a = quat_rotate(q_gb[k][None], bv.vectors[use])
        o = points[bv.second[use]] - points[bv.first[use]]
        c = float(np.sum(a[:, 0] * o[:, 0] + a[:, 2] * o[:, 2]))
        s = float(np.sum(a[:, 2] * o[:, 0] - a[:, 0] * o[:, 2]))
        evidence[k] = np.hypot(c, s)
        yaw[k] = np.arctan2(s, c)
    return yaw, evidence


@pytest.mark.parametrize("keypoints", ["coco17", "halpe26"])
def test_every_sensor_at_once_gives_what_one_bone_at_a_time_gave(keypoints: str) -> None:
    """Posed bodies with noisy keypoints, keypoints not triangulated, sensors missing (NaN orientations), subsets
    and orders of the sensors as the scheduler passes them (the measured ones)."""
    rng = np.random.default_rng(0)
    compared = 0
    for seed in range(40):
        skeleton, targets, q_true, points = _posed(seed, keypoints)
        vectors = bone_vectors(skeleton, targets, IMU_SET_13)  # type: ignore[arg-type]
        for _ in range(10):
            raw = quat_multiply(yaw_quat(rng.uniform(-np.pi, np.pi, 13)), q_true)
            raw[rng.random(13) < 0.1] = np.nan
            noisy = points + rng.normal(0.0, 0.02, points.shape)
            ok = rng.random(len(points)) > 0.15
            idx = np.flatnonzero(rng.random(13) > 0.2)
            got = observe_headings(raw[idx], [vectors[i] for i in idx], noisy, ok)
            want = _old_observe_headings(raw[idx], [vectors[i] for i in idx], noisy, ok)
            assert got[0].tobytes() == want[0].tobytes() and got[1].tobytes() == want[1].tobytes()
            compared += int(np.isfinite(want[0]).sum())
    assert compared > 2000


def test_many_pairs_on_one_bone_sum_as_before() -> None:
    """Bones with 1 to 40 pairs (np.sum's pairwise blocks start at 8): the same sums."""
    rng = np.random.default_rng(1)
    for _ in range(300):
        n = int(rng.integers(1, 6))
        n_kp = 60
        vectors = []
        for k in range(n):
            m = int(rng.integers(0, 41))
            vectors.append(
                BoneVectors(f"b{k}", rng.integers(0, n_kp, m), rng.integers(0, n_kp, m), rng.normal(size=(m, 3)))
            )
        q = rng.normal(size=(n, 4))
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        points = rng.normal(size=(n_kp, 3))
        ok = rng.random(n_kp) > 0.1
        got, want = observe_headings(q, vectors, points, ok), _old_observe_headings(q, vectors, points, ok)
        assert got[0].tobytes() == want[0].tobytes() and got[1].tobytes() == want[1].tobytes()


class _OldEstimator(HeadingEstimator):
    """The estimator as it was: each sensor's window a deque of (t_ns, yaw, evidence) tuples, made an array at every
    observation (verbatim but for where the deques are kept)."""

    def __init__(self, options: HeadingOptions) -> None:
        super().__init__(options)
        self.windows: dict[str, deque[tuple[int, float, float]]] = {}

    def observe(self, t_ns: int, sensors: Sequence[str], yaw: np.ndarray, evidence: np.ndarray) -> None:
        o = self.options
        if not o.enabled:
            return
        window_ns = round(o.window_s * 1e9)
        for sid, y, e in zip(sensors, yaw, evidence, strict=True):
            s = self.sensors.setdefault(sid, SensorHeading())
            samples = self.windows.setdefault(sid, deque())
            if np.isfinite(y) and e >= o.min_evidence_m2:
                samples.append((t_ns, float(y), float(e)))
            while samples and samples[0][0] < t_ns - window_ns:
                samples.popleft()
            if len(samples) >= o.min_samples:
                s.estimate, s.inliers, s.rejected = self._old_robust(samples)
            if s.estimate is not None and s.observed_ns is not None:
                step = np.radians(o.max_rate_deg_s) * max(0, t_ns - s.observed_ns) / 1e9
                s.applied = float(wrap(s.applied + np.clip(wrap(s.estimate - s.applied), -step, step)))
            s.observed_ns = t_ns
            s.frozen = False

    def restart(self, sensors: Sequence[str]) -> None:
        super().restart(sensors)
        for sid in sensors:
            if sid in self.windows:
                self.windows[sid].clear()

    def _old_robust(self, samples: deque[tuple[int, float, float]]) -> tuple[float, int, int]:
        o = self.options
        arr = np.array(samples)
        y, w = arr[:, 1], arr[:, 2]
        ref = float(np.arctan2(np.sum(w * np.sin(y)), np.sum(w * np.cos(y))))
        d = wrap(y - ref)
        med = weighted_median(d, w)
        dev = np.abs(d - med)
        mad = 1.4826 * weighted_median(dev, w)
        keep = dev <= max(o.outlier_mads * mad, np.radians(o.outlier_floor_deg))
        mean = float(np.sum(w[keep] * d[keep]) / np.sum(w[keep]))
        return float(wrap(ref + mean)), int(keep.sum()), int((~keep).sum())


def _state(est: HeadingEstimator) -> list[tuple[str, bytes, int, int, bool]]:
    return [(sid, struct.pack("dd", s.applied, np.nan if s.estimate is None else s.estimate), s.inliers, s.rejected,
             s.frozen) for sid, s in sorted(est.sensors.items())]  # fmt: skip


def test_the_estimator_on_arrays_follows_the_old_one_to_the_bit() -> None:
    """13 sensors observed 20 times a second for 60 s (yaws near ±180° too, outliers, NaN and weak evidence, a
    solve time now and then earlier than the last, sensors frozen and restarted): after every observation every
    sensor's applied offset, estimate, inliers, outliers and state are the old estimator's."""
    rng = np.random.default_rng(3)
    options = HeadingOptions(window_s=4.0, min_samples=12, max_rate_deg_s=20.0)
    new, old = HeadingEstimator(options), _OldEstimator(options)
    sensors = [f"s{i:02d}" for i in range(13)]
    truth = rng.uniform(-np.pi, np.pi, 13)
    t = 0
    for k in range(1200):
        t += 50_000_000 if rng.random() > 0.02 else -30_000_000
        yaw = wrap(truth + rng.normal(0.0, 0.05, 13) + (rng.random(13) < 0.1) * rng.uniform(-2.0, 2.0, 13))
        yaw[rng.random(13) < 0.05] = np.nan
        evidence = rng.gamma(2.0, 0.01, 13)
        seen = np.flatnonzero(rng.random(13) > 0.1)
        for est in (new, old):
            est.observe(t, [sensors[i] for i in seen], yaw[seen], evidence[seen])
        if k % 97 == 0:
            for est in (new, old):
                est.freeze(sensors[:4])
        if k % 211 == 0:
            for est in (new, old):
                est.restart(sensors[5:8])
        assert _state(new) == _state(old), k
        assert [len(new.sensors[s].samples) for s in sorted(new.sensors)] == [
            len(old.windows[s]) for s in sorted(new.sensors)
        ]
    assert all(s.estimate is not None for s in new.sensors.values())
