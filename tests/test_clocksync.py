"""Device→host clock mapping on synthetic clocks: offset, drift, delay jitter, stalls, wraps, resets."""

from __future__ import annotations

import numpy as np
import pytest

from mocapd.pipeline.clocksync import ClockSync

MIN_DELAY_NS = 2_000_000  # fixed part of the transport delay


def _simulate(
    sync: ClockSync,
    *,
    seconds: float,
    drift_ppm: float,
    tick0: int,
    seed: int,
    rate_hz: float = 100.0,
) -> tuple[list[int], list[int], list[int]]:
    """Feed the estimator; return device ticks, true host times (+ min delay) and arrival times."""
    rng = np.random.default_rng(seed)
    host_offset = 5_000_000_000_000
    ticks, truth, arrivals = [], [], []
    for k in range(int(seconds * rate_hz)):
        t = k / rate_hz  # host-clock seconds of the measurement
        tick = (tick0 + round(t * 10_000 * (1.0 - drift_ppm * 1e-6))) % (1 << 32)
        true_host = host_offset + round(t * 1e9) + MIN_DELAY_NS
        delay = rng.exponential(1.5e6)  # ns, never negative
        if rng.random() < 0.02:
            delay += rng.uniform(5e6, 40e6)  # occasional USB / scheduler stall
        arrival = true_host + round(delay)
        sync.update(tick, arrival)
        ticks.append(tick)
        truth.append(true_host)
        arrivals.append(arrival)
    return ticks, truth, arrivals


@pytest.mark.parametrize("drift_ppm", [-150.0, 0.0, 80.0])
def test_tracks_offset_and_drift_removing_jitter(drift_ppm: float) -> None:
    sync = ClockSync()
    ticks, truth, arrivals = _simulate(sync, seconds=60, drift_ppm=drift_ppm, tick0=123_456, seed=1)
    assert sync.skew_ppm == pytest.approx(drift_ppm, abs=10.0)
    errors = np.array([sync.to_host_ns(t) - h for t, h in zip(ticks[-500:], truth[-500:], strict=True)])  # type: ignore[operator]
    raw = np.array(arrivals[-500:]) - np.array(truth[-500:])
    # The mapped times sit on the minimum-delay line: far tighter than the raw arrival stamps.
    assert np.median(np.abs(errors)) < 0.1e6
    assert np.max(np.abs(errors)) < 0.3e6
    assert np.std(errors) < 0.2 * np.std(raw)


def test_counter_wrap_is_unwrapped() -> None:
    sync = ClockSync()
    ticks, truth, _ = _simulate(sync, seconds=20, drift_ppm=30.0, tick0=(1 << 32) - 50_000, seed=2)
    assert ticks[-1] < ticks[0]  # wrapped during the run
    assert sync.resets == 0
    mapped = sync.to_host_ns(ticks[-1])
    assert mapped is not None and abs(mapped - truth[-1]) < 1e6
    # A stamp from just before the wrap still maps to the right side of it.
    before_wrap = next(i for i in range(1, len(ticks)) if ticks[i] < ticks[i - 1]) - 1
    mapped_before = sync.to_host_ns(ticks[before_wrap])
    assert mapped_before is not None and abs(mapped_before - truth[before_wrap]) < 1e6


def test_device_reset_restarts_the_estimate() -> None:
    sync = ClockSync()
    assert sync.to_host_ns(0) is None and not sync.ready
    _simulate(sync, seconds=5, drift_ppm=0.0, tick0=9_000_000, seed=3)
    sync.update(10, 9_000_000_000_000)  # counter went back to ~0: the device restarted
    assert sync.resets == 1
    mapped = sync.to_host_ns(10)
    assert mapped == 9_000_000_000_000
    assert sync.to_host_ns(110) == 9_000_000_000_000 + 10_000_000  # rate 1 until enough points


def test_offline_map_recovers_measurement_times_through_a_stalled_host() -> None:
    from mocapd.pipeline.clocksync import offline_clock_map

    rng = np.random.default_rng(3)
    n = 6000  # 60 s at 100 Hz
    ticks0 = (1 << 32) - 150_000  # wraps after 15 s
    raw = ticks0 + np.arange(n) * 100
    truth = 5_000_000_000 + np.round(np.arange(n) * 10_000_000 * (1 + 40e-6)).astype(np.int64)  # 40 ppm skew
    delay = 800_000 + rng.exponential(2_000_000, n)
    stall = slice(2000, 2600)  # 6 s of a starved host: arrivals up to a second late, growing
    delay[stall] += np.linspace(0, 1e9, 600)
    host = truth + delay.astype(np.int64)
    mapped = offline_clock_map(raw & 0xFFFFFFFF, host)
    assert mapped is not None
    err = mapped - truth
    assert np.abs(err - 800_000).max() < 300_000  # measurement + minimum delay, to a fraction of a ms
    assert offline_clock_map(np.array([5, 3, 4]), np.array([1, 2, 3])) is None  # counter reset
    assert offline_clock_map(np.array([5]), np.array([1])) is None
    assert offline_clock_map(np.arange(10) * 100, np.arange(10) * 20_000_000) is None  # rate off by 100 %
