"""The round-trip clock offset estimator (mocapd.core.clock_offset)."""

from __future__ import annotations

import numpy as np

from mocapd.core.clock_offset import ClockOffsetEstimator

OFFSET = 3_141_592_653  # remote clock ahead of ours, ns


def test_min_round_trip_wins_over_asymmetric_queueing() -> None:
    rng = np.random.default_rng(1)
    est = ClockOffsetEstimator(window=64, max_drift_ppm=0.0)
    t = 10**12
    for _ in range(64):
        up = 100_000 + int(rng.exponential(2_000_000))  # to the remote: queueing makes it long and one-sided
        down = 100_000 + int(rng.exponential(200_000))
        est.add(t, t + up + OFFSET, t + up + down)
        t += 500_000_000
    e = est.estimate(t)
    assert e is not None and e.samples == 64
    assert abs(e.offset_ns - OFFSET) <= e.uncertainty_ns  # the bound holds
    assert e.uncertainty_ns < 1_000_000  # and a short round trip was found among the queued ones
    assert e.uncertainty_ns == e.rtt_ns // 2


def test_the_bound_holds_for_any_split_of_the_round_trip() -> None:
    for up in (0, 1, 500_000, 1_000_000):
        est = ClockOffsetEstimator(window=4, max_drift_ppm=0.0)
        est.add(0, up + OFFSET, 1_000_000)
        e = est.estimate(1_000_000)
        assert e is not None and abs(e.offset_ns - OFFSET) <= e.uncertainty_ns == 500_000


def test_old_round_trips_age_by_the_drift_bound() -> None:
    est = ClockOffsetEstimator(window=8, max_drift_ppm=100.0)
    est.add(0, OFFSET + 50_000, 100_000)  # a short round trip, long ago
    est.add(100 * 10**9, 100 * 10**9 + OFFSET + 500_000, 100 * 10**9 + 1_000_000)  # a longer one, just now
    e = est.estimate(100 * 10**9 + 1_000_000)
    assert e is not None and e.rtt_ns == 1_000_000  # 100 s * 100 ppm = 10 ms of possible drift beat 0.45 ms
    assert est.estimate(0) is not None and est.estimate(0).rtt_ns == 100_000  # type: ignore[union-attr]


def test_window_forgets_and_nonsense_is_counted() -> None:
    est = ClockOffsetEstimator(window=2, max_drift_ppm=0.0)
    assert est.estimate(0) is None
    est.add(0, 10, 2)
    est.add(10, 30, 20)
    est.add(20, 50, 40)
    e = est.estimate(40)
    assert e is not None and e.samples == 2 and e.rtt_ns == 10  # the 2 ns round trip left the window
    assert not est.add(5, 0, 4) and est.rejected == 1
    est.reset()
    assert est.estimate(0) is None
