"""Lag estimation by normalised cross-correlation."""

from __future__ import annotations

from collections.abc import Generator
from typing import TypeVar

import numpy as np

from mocapd.pipeline.time_alignment import (
    FRAMES_PER_STEP,
    POINTS_PER_STEP,
    estimate_lag,
    estimate_lag_steps,
    keypoint_speed,
    keypoint_speed_steps,
)

MS = 1_000_000
T = TypeVar("T")


def _signal(t_ns: np.ndarray) -> np.ndarray:
    t = t_ns / 1e9
    return np.sin(2 * np.pi * 1.3 * t) + 0.5 * np.sin(2 * np.pi * 2.9 * t + 1.0) + 0.3 * np.sin(2 * np.pi * 0.7 * t)


def test_recovers_a_known_shift_between_unevenly_sampled_signals() -> None:
    rng = np.random.default_rng(0)
    t_a = np.cumsum(rng.uniform(25, 40, 200)).astype(np.int64) * MS
    t_b = np.cumsum(rng.uniform(25, 40, 200)).astype(np.int64) * MS
    for lag in (-73 * MS, 0, 37 * MS):
        b = _signal(t_b - lag) + rng.normal(scale=0.05, size=t_b.size)  # b's stamps run `lag` ahead
        est = estimate_lag(t_a, _signal(t_a), t_b, b)
        assert est is not None
        assert abs(est.lag_ns - lag) < 3 * MS and est.quality > 0.9


def test_too_little_data_gives_no_estimate() -> None:
    t = np.arange(5, dtype=np.int64) * 30 * MS
    assert estimate_lag(t, np.ones(5), t, np.ones(5)) is None


def _stepped(steps: Generator[None, None, T]) -> tuple[T, int]:
    """Run work given as steps: its result and how many times it yielded."""
    yields = 0
    while True:
        try:
            next(steps)
        except StopIteration as done:
            result: T = done.value
            return result, yields
        yields += 1


def _scores_one_lag_at_a_time(t_a: np.ndarray, a: np.ndarray, t_b: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The lag search as it was (one interpolation per candidate lag): the oracle of the stepped one."""
    max_lag, step = 200 * MS, 2 * MS
    grid = np.arange(max(t_a[0], t_b[0] - max_lag) + max_lag, min(t_a[-1], t_b[-1] + max_lag) - max_lag, step)
    sa = np.interp(grid, t_a, a)
    sa = (sa - sa.mean()) / (sa.std() + 1e-12)
    scores = []
    for lag in range(-max_lag, max_lag + 1, step):
        sb = np.interp(grid + lag, t_b, b)
        scores.append(float(np.mean(sa * (sb - sb.mean()) / (sb.std() + 1e-12))))
    return np.array(scores)


def test_the_stepped_lag_search_gives_the_same_answer_in_bounded_steps() -> None:
    """Issue 45's hiccup: the daemon runs the search between ticks, one step per event-loop iteration, so a step's
    work must be bounded (at most POINTS_PER_STEP interpolated samples) whatever the record's length, and the
    answer must be the one-lag-at-a-time search's."""
    rng = np.random.default_rng(1)
    for seconds in (6, 30):  # 30 s of 30 Hz keypoints: what a timeline keeps on a quiet machine
        n = seconds * 30
        t_a = np.cumsum(rng.uniform(30, 37, n)).astype(np.int64) * MS
        t_b = np.cumsum(rng.uniform(30, 37, n)).astype(np.int64) * MS
        a, b = _signal(t_a), _signal(t_b - 23 * MS) + rng.normal(scale=0.05, size=n)
        est, yields = _stepped(estimate_lag_steps(t_a, a, t_b, b))
        assert est is not None
        scores = _scores_one_lag_at_a_time(t_a, a, t_b, b)
        grid_points = int((min(t_a[-1], t_b[-1]) - max(t_a[0], t_b[0])) / (2 * MS))
        # every step scored at most POINTS_PER_STEP samples: the 201 lags took at least this many steps
        assert yields >= 201 * grid_points / POINTS_PER_STEP - 1, (seconds, yields)
        assert est == estimate_lag(t_a, a, t_b, b)
        k = int(np.argmax(scores))
        assert abs(est.lag_ns - (k - 100) * 2 * MS) <= 1 * MS and abs(est.quality - scores[k]) < 1e-9
        assert abs(est.lag_ns - 23 * MS) < 3 * MS


def test_keypoint_speed_yields_every_few_frames() -> None:
    """The other half of the cameras' estimate: matching people frame to frame, a step every FRAMES_PER_STEP."""
    from mocapd.core.sorting import Detections2D

    n = 100
    t = np.arange(n, dtype=np.int64) * 33 * MS
    frames = [Detections2D(np.full((1, 17, 2), 100.0 + k), np.ones((1, 17))) for k in range(n)]
    (times, speed), yields = _stepped(keypoint_speed_steps(t, frames))
    assert yields >= (n - 1) // FRAMES_PER_STEP
    assert times.size == n - 1 and np.allclose(speed, 1 / 0.033)
    assert all(np.array_equal(x, y) for x, y in zip((times, speed), keypoint_speed(t, frames), strict=True))
