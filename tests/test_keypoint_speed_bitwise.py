"""The cameras' offset estimate's keypoint speeds, worked out in array operations (issue 39), give the same floats
as the per-frame-pair loop they replace, kept here verbatim as the oracle."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mocapd.core.sorting import Detections2D
from mocapd.pipeline.keypoint_timeline import person_distances
from mocapd.pipeline.scheduler import estimate_camera_offsets
from mocapd.pipeline.time_alignment import FRAMES_PER_STEP, estimate_lag, keypoint_speed, keypoint_speed_steps
from tools.bench_offset_estimate import recorded_frames

MS = 1_000_000


def old_keypoint_speed(
    times_ns: NDArray[np.int64], frames: list[Detections2D], match_px: float = 80.0
) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """``keypoint_speed_steps`` before issue 39, verbatim but for the yields (which did no work)."""
    out_t: list[int] = []
    out_v: list[float] = []
    for k in range(1, len(frames)):
        a, b = frames[k - 1], frames[k]
        dt = (int(times_ns[k]) - int(times_ns[k - 1])) / 1e9
        d = person_distances(a, b)
        if d.size == 0 or dt <= 0:
            continue
        vs = []
        for i in range(d.shape[0]):
            j = int(np.argmin(d[i]))
            if d[i, j] <= match_px:
                both = (a.confidences[i] > 0) & (b.confidences[j] > 0)
                vs.append(float(np.mean(b.keypoints[j, both, 1] - a.keypoints[i, both, 1])) / dt)
        if vs:
            out_t.append((int(times_ns[k]) + int(times_ns[k - 1])) // 2)
            out_v.append(float(np.mean(vs)))
    return np.asarray(out_t, dtype=np.int64), np.asarray(out_v)


def _same(new: tuple[np.ndarray, np.ndarray], old: tuple[np.ndarray, np.ndarray]) -> None:
    assert new[0].dtype == old[0].dtype and new[1].dtype == old[1].dtype
    assert np.array_equal(new[0], old[0])
    assert new[1].tobytes() == old[1].tobytes()  # bit for bit (NaN and the sign of zero included)


def test_synthetic_people_give_the_same_floats() -> None:
    for people, seed in ((1, 0), (2, 3), (3, 5)):
        _, frames = recorded_frames(6.0, people, seed, noise_seed=seed)
        for times, dets in frames:
            t = np.asarray(times, dtype=np.int64)
            _same(keypoint_speed(t, dets), old_keypoint_speed(t, dets))


def _random_frame(rng: np.random.Generator, n_kp: int, base: NDArray[np.float64]) -> Detections2D:
    """Up to four people near ``base`` (some far off, some with few or no shared keypoints, NaN where unseen)."""
    n = int(rng.integers(0, 5))
    kp = base[rng.integers(0, len(base), n)] + rng.normal(0.0, rng.choice([2.0, 30.0, 200.0]), (n, n_kp, 2))
    cf = np.where(rng.random((n, n_kp)) < rng.choice([0.1, 0.5, 0.95]), rng.uniform(0.05, 1.0, (n, n_kp)), 0.0)
    kp = np.where((cf == 0)[..., None] & (rng.random((n, n_kp, 1)) < 0.5), np.nan, kp)
    if n and rng.random() < 0.05:
        cf[0] = 0.0  # someone with no keypoint at all
    return Detections2D(kp, cf)


def test_edge_cases_give_the_same_floats() -> None:
    """Empty frames, unmatched and far-off people, a person of one frame nearest to two of the next, NaN keypoints,
    repeated and backwards time stamps, and every count of shared keypoints (each sum's length)."""
    rng = np.random.default_rng(7)
    for n_kp in (17, 26, 133):
        base = rng.uniform(0.0, 1000.0, (3, n_kp, 2))
        for _ in range(20):
            n = int(rng.integers(0, 200))
            t = np.cumsum(rng.choice([0, 33, 34, -5], n, p=[0.03, 0.45, 0.45, 0.07])).astype(np.int64) * MS
            frames = [_random_frame(rng, n_kp, base) for _ in range(n)]
            _same(keypoint_speed(t, frames), old_keypoint_speed(t, frames))
            _same(keypoint_speed(t, frames, match_px=20.0), old_keypoint_speed(t, frames, match_px=20.0))


def test_nobody_in_any_frame_and_no_frames() -> None:
    t = np.arange(10, dtype=np.int64) * 33 * MS
    empty = [Detections2D.empty(17) for _ in range(10)]
    _same(keypoint_speed(t, empty), old_keypoint_speed(t, empty))
    _same(keypoint_speed(t[:0], []), old_keypoint_speed(t[:0], []))
    _same(keypoint_speed(t[:1], empty[:1]), old_keypoint_speed(t[:1], empty[:1]))


def test_the_steps_are_bounded_and_the_estimate_unchanged() -> None:
    """The speeds come in steps of FRAMES_PER_STEP frame pairs (one step per FRAMES_PER_STEP
    pairs, not per 8 frames as before); the cameras' estimate built on them is the old speeds' estimate."""
    names, frames = recorded_frames(10.0, 2, 3, noise_seed=3)
    t = np.asarray(frames[0][0], dtype=np.int64)
    steps = keypoint_speed_steps(t, frames[0][1])
    yields = 0
    while True:
        try:
            next(steps)
        except StopIteration:
            break
        yields += 1
    assert yields == -(-(len(t) - 1) // FRAMES_PER_STEP)
    # the whole estimate: as the old speeds give it (camera_offset_steps' arithmetic on them)
    shifted = [frames[0], *(([x + 40 * MS for x in ts], d) for ts, d in frames[1:])]
    ref = old_keypoint_speed(t, frames[0][1])
    old = {}
    for name, (ts, dets) in zip(names[1:], shifted[1:], strict=True):
        lag = estimate_lag(*ref, *old_keypoint_speed(np.asarray(ts, dtype=np.int64), dets))
        assert lag is not None
        old[name] = {"offset_ms": round(lag.lag_ns / 1e6, 1), "quality": round(lag.quality, 3)}
    assert estimate_camera_offsets(names, shifted, ()) == old
