"""The camera watch made cheaper for the event loop (the synthetic rig's loop spent ~19 % of its time in it): the
per-check levels read from time-ordered arrays (were lists built from deques of (time, residual) tuples and a median
per stretch), the left-out triangulations in one SVD call (were one call per camera) and the all-in residuals'
medians from one sort (were one ``np.median`` per camera) give the numbers the old code gave, to the bit. The old
code is kept here, verbatim but for names, as the reference."""

from __future__ import annotations

import struct
import warnings
from collections import deque
from dataclasses import replace
from typing import Any

import numpy as np

from mocapd.core.camera import triangulate_projections
from mocapd.core.camera_watch import (
    CameraWatch,
    WatchOptions,
    _column_nanmedians,
    _level_spread,
    _Series,
    residuals_all_in,
    residuals_left_out,
    row_medians,
    triangulate_left_out,
)
from mocapd.core.synthetic import ring_rig
from tests.test_camera_watch import bumped, take

FloatArray = np.ndarray


def _old_residuals_left_out(
    P: FloatArray, uv: FloatArray, conf: FloatArray, *, min_confidence: float, min_keypoints: int
) -> tuple[FloatArray, list[tuple[FloatArray, FloatArray]]]:
    n_cams = P.shape[0]
    w = np.where((conf >= min_confidence) & np.all(np.isfinite(uv), axis=-1), conf, 0.0)
    out = np.full(n_cams, np.nan)
    matches: list[tuple[FloatArray, FloatArray]] = []
    for c in range(n_cams):
        others = np.ones(n_cams, dtype=bool)
        others[c] = False
        seen = w[c] > 0
        if others.sum() < 2 or seen.sum() < min_keypoints:
            matches.append((np.zeros((0, 3)), np.zeros((0, 2))))
            continue
        X, ok = triangulate_projections(P[others], uv[others], w[others])
        ok &= seen
        if ok.sum() < min_keypoints:
            matches.append((np.zeros((0, 3)), np.zeros((0, 2))))
            continue
        h = np.c_[X[ok], np.ones(int(ok.sum()))] @ P[c].T
        front = h[:, 2] > 1e-9
        proj = h[:, :2] / np.where(front, h[:, 2], 1.0)[:, None]
        err = np.where(front, np.linalg.norm(proj - uv[c, ok], axis=1), np.inf)
        out[c] = float(np.median(err))
        matches.append((X[ok][front], uv[c, ok][front]))
    return out, matches


def _old_residuals_all_in(
    P: FloatArray, uv: FloatArray, conf: FloatArray, *, min_confidence: float, min_keypoints: int
) -> FloatArray:
    w = np.where((conf >= min_confidence) & np.all(np.isfinite(uv), axis=-1), conf, 0.0)
    out = np.full(P.shape[0], np.nan)
    X, ok = triangulate_projections(P, uv, w, min_views=3, normal_equations=True)
    if ok.sum() < min_keypoints:
        return out
    h = P[:, None, :, :3] @ X[ok][None, :, :, None] + P[:, None, :, 3:]  # (n_cams, n_ok, 3, 1)
    front = h[..., 2, 0] > 1e-9
    d = h[..., :2, 0] / np.where(front, h[..., 2, 0], 1.0)[..., None] - uv[:, ok]
    err = np.sqrt(d[..., 0] ** 2 + d[..., 1] ** 2)
    use = front & (w[:, ok] > 0)
    for c in np.flatnonzero(use.sum(axis=1) >= min_keypoints):
        out[c] = float(np.median(err[c, use[c]]))
    return out


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


def _same(a: FloatArray, b: FloatArray) -> bool:
    """The same floats to the bit, NaN where NaN (whatever its sign bit: ``np.median`` of nothing gives -NaN)."""
    nan = np.isnan(a)
    return a.shape == b.shape and np.array_equal(nan, np.isnan(b)) and a[~nan].tobytes() == b[~nan].tobytes()


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


def _people(n_cams: int, seed: int) -> list[tuple[FloatArray, FloatArray, FloatArray]]:
    """(P, uv, conf) of two people walking before a ring of ``n_cams`` with detector-like noise, roughed up: views
    dropped, keypoints unseen or NaN, a camera's keypoints shifted, confidences under the threshold."""
    truth = ring_rig(n_cams)
    P = np.stack([c.projection_matrix for c in truth])
    rng = np.random.default_rng(seed)
    out = []
    for _, uv0, cf0 in take(truth, 3.0, seed=seed):
        uv, cf = uv0.copy(), cf0.copy()
        cf[rng.random(cf.shape) < 0.15] = 0.0
        cf[rng.integers(n_cams)] *= rng.random() < 0.3  # a camera that sees nobody, now and then
        uv[rng.random(cf.shape) < 0.03] = np.nan
        uv[rng.integers(n_cams)] += rng.normal(0.0, 20.0, 2) * (rng.random() < 0.3)
        cf[rng.random(cf.shape) < 0.1] = 0.2
        out.append((P, uv, cf))
    return out


def test_the_left_out_triangulations_are_each_cameras_own_call_to_the_bit() -> None:
    """On 3 to 6 cameras, roughed-up people: the batched left-out points and the residuals and matches built on
    them are what one ``triangulate_projections`` call per camera gave."""
    compared = 0
    for n_cams in (3, 4, 5, 6):
        for P, uv, cf in _people(n_cams, seed=n_cams):
            w = np.where((cf >= 0.3) & np.all(np.isfinite(uv), axis=-1), cf, 0.0)
            X, ok = triangulate_left_out(P, uv, w)
            for c in range(n_cams):
                others = np.arange(n_cams) != c
                X_c, ok_c = triangulate_projections(P[others], uv[others], w[others])
                assert np.array_equal(ok[c], ok_c) and X[c].tobytes() == X_c.tobytes()
            for k in (1, 6, 12):
                new, new_m = residuals_left_out(P, uv, cf, min_confidence=0.3, min_keypoints=k)
                old, old_m = _old_residuals_left_out(P, uv, cf, min_confidence=0.3, min_keypoints=k)
                assert new.tobytes() == old.tobytes()
                assert all(a.tobytes() == b.tobytes() for m, n in zip(new_m, old_m, strict=True)
                           for a, b in zip(m, n, strict=True))  # fmt: skip
                compared += int(np.isfinite(old).sum())
    assert compared > 1500


def test_the_left_out_points_needed_are_those_of_the_whole_call_to_the_bit() -> None:
    """``triangulate_left_out`` with ``need`` (the residuals' own keypoints, or any mask) solves only those systems:
    the points it solves are the whole call's, bit for bit, and the others are NaN and not ok."""
    solved = 0
    for n_cams in (3, 4, 6):
        rng = np.random.default_rng(20 + n_cams)
        for P, uv, cf in _people(n_cams, seed=20 + n_cams):
            w = np.where((cf >= 0.3) & np.all(np.isfinite(uv), axis=-1), cf, 0.0)
            X, ok = triangulate_left_out(P, uv, w)
            for need in (w > 0, rng.random(w.shape) < 0.5):
                X_n, ok_n = triangulate_left_out(P, uv, w, need)
                assert np.array_equal(ok_n, ok & need)
                assert X_n[ok_n].tobytes() == X[ok_n].tobytes() and np.isnan(X_n[~(ok & need)]).all()
                solved += int(ok_n.sum())
    assert solved > 5000


def test_the_all_in_residuals_are_the_per_camera_medians_to_the_bit() -> None:
    """On 3 to 6 cameras, roughed-up people, any ``min_keypoints`` (0: cameras that see nothing get NaN)."""
    compared = 0
    for n_cams in (3, 4, 5, 6):
        for P, uv, cf in _people(n_cams, seed=10 + n_cams):
            for k in (0, 1, 6, 12):
                new = residuals_all_in(P, uv, cf, min_confidence=0.3, min_keypoints=k)
                with np.errstate(all="ignore"), warnings.catch_warnings():
                    warnings.simplefilter("ignore")  # k = 0: np.median of nothing warns (and gives NaN)
                    old = _old_residuals_all_in(P, uv, cf, min_confidence=0.3, min_keypoints=k)
                assert _same(new, old)
                compared += int(np.isfinite(old).sum())
    assert compared > 1500


def test_row_medians_are_np_median_to_the_bit() -> None:
    """Rows of 0 to 40 used entries among others, odd and even counts, ties, infinities and NaN."""
    rng = np.random.default_rng(2)
    for _ in range(2000):
        n, m = int(rng.integers(1, 6)), int(rng.integers(1, 40))
        values = rng.gamma(2.0, 5.0, (n, m))
        values[rng.random((n, m)) < 0.1] = 4.0
        values[rng.random((n, m)) < 0.02] = np.inf
        values[rng.random((n, m)) < 0.02] = np.nan
        use = rng.random((n, m)) < 0.7
        use[np.arange(n), rng.integers(m, size=n)] = rng.random(n) < 0.9  # now and then a row of nothing
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # np.median of nothing warns (and gives NaN)
            want = np.array([np.median(values[i, use[i]]) for i in range(n)])
        assert _same(row_medians(values, use), want)


def test_column_nanmedians_are_np_nanmedian_to_the_bit() -> None:
    """1 to 6 people by 3 to 8 cameras of residuals with NaN (a camera a person's check did not measure) and
    infinities (keypoints behind a camera), every column with something that is not NaN, as the watch pools them."""
    rng = np.random.default_rng(4)
    for _ in range(3000):
        res = rng.gamma(2.0, 5.0, (int(rng.integers(1, 7)), int(rng.integers(3, 9))))
        res[rng.random(res.shape) < 0.1] = 9.0
        res[rng.random(res.shape) < 0.3] = np.nan
        res[rng.random(res.shape) < 0.03] = np.inf
        res[rng.integers(len(res), size=res.shape[1]), np.arange(res.shape[1])] = rng.gamma(2.0, 5.0, res.shape[1])
        assert _same(_column_nanmedians(res), np.nanmedian(res, axis=0))
