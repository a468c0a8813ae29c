"""The camera watch's per-check levels read from time-ordered arrays (the synthetic rig's event loop spent ~8 % of
its time building lists from the deques of (time, residual) tuples and taking a median per stretch): the same
numbers as the list-and-deque code they replaced, to the bit. The old code is kept here, verbatim but for names, as
the reference."""

from __future__ import annotations

import struct
from collections import deque
from dataclasses import replace
from typing import Any

import numpy as np

from mocapd.core.camera_watch import CameraWatch, WatchOptions, _level_spread, _Series
from mocapd.core.synthetic import ring_rig
from tests.test_camera_watch import bumped, take


def _old_level_spread(samples: deque[tuple[int, float]], split_ns: int, window_s: float) -> float:
    t = np.array([s[0] for s in samples if s[0] < split_ns], dtype=np.int64)
    r = np.array([s[1] for s in samples if s[0] < split_ns])
    if not len(t):
        return float("nan")
    stretch = (split_ns - t) // round(window_s * 1e9)
    levels = [float(np.median(r[stretch == k])) for k in np.unique(stretch) if np.count_nonzero(stretch == k) >= 3]
    if len(levels) < 3:
        return float("nan")
    return float(np.std(levels, ddof=1))


def _old_levels(cam: Any, samples: deque[tuple[int, float]], quick: deque[tuple[int, float]], t_ns: int,
                o: WatchOptions) -> tuple[float, float, float, float]:  # fmt: skip
    """The old ``CameraWatch._levels`` for one camera: (quick_baseline, current, baseline, spread) it set."""
    split = t_ns - round(o.window_s * 1e9)
    q = [r for t, r in quick if t < split]
    quick_span = (split - quick[0][0]) / 1e9 if q else 0.0
    quick_baseline = float(np.median(q)) if quick_span >= o.min_baseline_s else float("nan")
    old = [r for t, r in samples if t < split]
    new = [r for t, r in samples if t >= split]
    span = (split - samples[0][0]) / 1e9 if old else 0.0
    current = float(np.median(new)) if len(new) >= 3 else float("nan")
    baseline, spread = cam.baseline, cam.spread
    if cam.frozen_baseline is not None:
        baseline = cam.frozen_baseline
    else:
        baseline = float(np.median(old)) if span >= o.min_baseline_s else float("nan")
        spread = _old_level_spread(samples, split, o.window_s) if np.isfinite(baseline) else np.nan
    return quick_baseline, current, baseline, spread


def _bits(*values: float) -> bytes:
    return struct.pack(f"{len(values)}d", *values)


def _as_deque(series: _Series) -> deque[tuple[int, float]]:
    return deque(zip(series.times().tolist(), series.values().tolist(), strict=True))


def test_a_series_keeps_what_the_deque_with_popleft_kept() -> None:
    """Appends at non-decreasing times (several per time: a tick's people), old samples dropped: the same samples
    as the deque trimmed from the left, through many regrowths and compactions."""
    rng = np.random.default_rng(0)
    series, model = _Series(), deque[tuple[int, float]]()
    t = 0
    for _ in range(5000):
        t += int(rng.choice([0, 0, 100_000_000, 200_000_000]))
        value = float(rng.normal(10.0, 3.0))
        series.append(t, value)
        model.append((t, value))
        keep_from = t - int(rng.choice([2_100_000_000, 21_000_000_000]))
        series.drop_before(keep_from)
        while model and model[0][0] < keep_from:
            model.popleft()
        assert len(series) == len(model)
        assert _as_deque(series) == model


def test_level_spread_equals_the_median_per_stretch_to_the_bit() -> None:
    """Random windows (odd and even stretch sizes, repeated values and times, stretches under 3 samples, fewer
    than 3 stretches): the one-sort spread and the old per-stretch ``np.median`` spread are the same float."""
    rng = np.random.default_rng(1)
    compared = 0
    for _ in range(3000):
        n = int(rng.integers(0, 120))
        t = np.sort(rng.integers(0, 25_000_000_000, n)).astype(np.int64)
        t[rng.random(n) < 0.3] = t[0] if n else 0  # repeated times
        t = np.sort(t)
        r = rng.gamma(3.0, 3.0, n)
        r[rng.random(n) < 0.2] = 7.5  # ties
        split = int(rng.integers(20_000_000_000, 26_000_000_000))
        window = float(rng.choice([0.5, 1.0, 1.3]))
        before = t < split
        samples = deque(zip(t.tolist(), r.tolist(), strict=True))
        old = _old_level_spread(samples, split, window)
        new = _level_spread(t[before], r[before], split, window)
        assert _bits(new) == _bits(old), (n, split, window)
        compared += np.isfinite(old)
    assert compared > 1000  # most draws had three stretches or more


class _Checked(CameraWatch):
    """The watch with the old per-camera levels worked out beside the new ones at every check, from the same
    samples, and compared to the bit."""

    checks = 0

    def _levels(self, t_ns: int) -> None:
        before = [replace(c) for c in self._cams]  # what the old code started from (a frozen baseline, a spread)
        super()._levels(t_ns)
        for old_cam, cam in zip(before, self._cams, strict=True):
            want = _old_levels(old_cam, _as_deque(cam.samples), _as_deque(cam.quick), t_ns, self.options)
            got = (cam.quick_baseline, cam.current, cam.baseline, cam.spread)
            assert _bits(*got) == _bits(*want), (t_ns, got, want)
        type(self).checks += 1


def test_the_watch_sets_the_levels_the_old_code_set_through_a_bump() -> None:
    """Two people before four cameras, cam1 knocked 2° at 20 s (learning, ok, suspect with its baseline frozen,
    bumped, re-estimated): at every one of the 250 checks each camera's levels are those of the old code."""
    truth = ring_rig(4)
    moved = [bumped(c, 2.0, (1.0, 0.0, 0.0)) if i == 1 else c for i, c in enumerate(truth)]
    watch = _Checked(truth)
    for t, uv, cf in take(truth, 25.0, seed=1, bump_at=20.0, moved=moved):
        watch.observe(t, uv, cf)
    assert _Checked.checks >= 245
    assert watch.states()[1] == "bumped" and [e[2] for e in watch.events][:1] == ["bumped"]
