"""Lag estimation by normalised cross-correlation."""

from __future__ import annotations

import numpy as np

from mocapd.pipeline.time_alignment import estimate_lag

MS = 1_000_000


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
