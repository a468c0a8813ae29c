"""Time-offset estimation by correlation (camera ↔ camera from vertical keypoint velocities).

Two cameras watching the same motion see their people's keypoints move up and down together; if one camera's
time stamps run ``d`` ahead, its signal is the other's shifted by ``d``. :func:`estimate_lag` finds ``d`` as the
peak of the normalised cross-correlation of the two signals resampled on a common grid (parabolic refinement
between grid steps). :func:`keypoint_speed` turns a camera's detected frames into such a signal (mean vertical
image velocity of the people matched between consecutive frames).

Pure: time stamps are arguments. The daemon reports the estimates as suggestions in /status; the configured
``[daemon.offsets]`` stay in charge (an estimate from a still scene is meaningless, and the ``quality`` says so).

Each estimate also comes as steps (``*_steps``: a generator that yields after a bounded piece of work, about a
millisecond, and returns the result; :func:`drain` runs one to its end). The daemon runs them on its event loop
between ticks (issue 45): run in a thread, the estimate's thousands of small NumPy calls competed with the tick for
the interpreter lock, and every time the tick let go of it (a compiled kernel, a socket) it waited a switch interval
(5 ms) to get it back, so each estimate slowed the output for seconds.
"""

from __future__ import annotations

from collections.abc import Generator
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray

from mocapd.core.band_pass import band_pass
from mocapd.core.sorting import Detections2D

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
IntArray = NDArray[np.int64]
T = TypeVar("T")
Steps = Generator[None, None, T]
"""Work that yields after each bounded piece and returns its result."""

FRAMES_PER_STEP = 64
"""Frame pairs of keypoint speed per step (worked out together in array operations, well under a millisecond on a
laptop core for two people)."""
POINTS_PER_STEP = 40_000
"""Interpolated samples per step of a lag search (candidate lags x grid points; ~0.5 ms on a laptop core): 30 s of
keypoints on a 2 ms grid is 15 000 points per candidate lag, so a step scores two or three of the 201 lags."""


def drain(steps: Steps[T]) -> T:
    """Run ``steps`` to its end at once; its result."""
    while True:
        try:
            next(steps)
        except StopIteration as done:
            result: T = done.value
            return result


@dataclass(frozen=True, slots=True)
class LagEstimate:
    """``lag_ns``: how far signal b's time stamps run ahead of a's; ``quality``: the correlation peak (0..1)."""

    lag_ns: int
    quality: float


def keypoint_speed(
    times_ns: IntArray, frames: list[Detections2D], match_px: float = 80.0
) -> tuple[IntArray, FloatArray]:
    """:func:`keypoint_speed_steps` at once."""
    return drain(keypoint_speed_steps(times_ns, frames, match_px))


def keypoint_speed_steps(
    times_ns: IntArray, frames: list[Detections2D], match_px: float = 80.0
) -> Steps[tuple[IntArray, FloatArray]]:
    """Mean vertical image velocity (px/s, +down) of the people matched between consecutive frames, at the
    frames' midpoints. Vertical, because in a rig of upright cameras image "down" is world down in every view:
    the signal has the same sign and shape from every camera (speed magnitudes depend on the viewpoint).

    Each person of a frame is matched to the nearest person of the next
    (:func:`~mocapd.pipeline.keypoint_timeline.person_distances`, accepted within ``match_px``); a frame pair's
    velocity is the mean over its matched people of the mean vertical step of the keypoints both frames saw, over
    the time between them. The frames are stacked once (people padded to the most any frame has) and
    :data:`FRAMES_PER_STEP` pairs are worked out per step in array operations: the loop over frame pairs and
    people was 9.6 % of the camera rig's event loop (issue 39). The means sum the same numbers in the same order as
    one :func:`numpy.mean` per person and per frame did (rows of equal length summed together), so the floats are
    the same (``tests/test_keypoint_speed_bitwise.py``).

    Returns
    -------
    times : int array, shape (n,)
    velocity : array, shape (n,)
        Frames without a matched person are left out.
    """
    t = np.asarray(times_ns, dtype=np.int64)
    kp, cf, count = _stacked(frames)
    out_t: list[IntArray] = []
    out_v: list[FloatArray] = []
    for k0 in range(1, len(frames), FRAMES_PER_STEP):
        k = np.arange(k0, min(k0 + FRAMES_PER_STEP, len(frames)))
        pair_t, pair_v = _pair_speeds(t[k - 1], t[k], kp[k - 1], cf[k - 1], count[k - 1], kp[k], cf[k], count[k],
                                      match_px)  # fmt: skip
        out_t.append(pair_t)
        out_v.append(pair_v)
        yield
    if not out_t:
        return np.zeros(0, dtype=np.int64), np.zeros(0)
    return np.concatenate(out_t), np.concatenate(out_v)


def _stacked(frames: list[Detections2D]) -> tuple[FloatArray, FloatArray, IntArray]:
    """Every frame's people in one array, padded with nobody (confidence 0) to the most any frame has.

    Returns
    -------
    keypoints : array, shape (n_frames, n_people, n_kp, 2)
    confidences : array, shape (n_frames, n_people, n_kp)
    count : int array, shape (n_frames,)
        People in each frame.
    """
    count = np.array([f.keypoints.shape[0] for f in frames], dtype=np.int64)
    n_kp = frames[0].keypoints.shape[1] if frames else 0
    n_people = int(count.max()) if frames else 0
    kp = np.zeros((len(frames), n_people, n_kp, 2))
    cf = np.zeros((len(frames), n_people, n_kp))
    if n_people:
        frame_of = np.repeat(np.arange(len(frames)), count)
        person = np.arange(frame_of.size) - np.repeat(np.cumsum(count) - count, count)
        kp[frame_of, person] = np.concatenate([f.keypoints for f in frames])
        cf[frame_of, person] = np.concatenate([f.confidences for f in frames])
    return kp, cf, count


def _pair_speeds(
    t_a: IntArray, t_b: IntArray, kp_a: FloatArray, cf_a: FloatArray, n_a: IntArray, kp_b: FloatArray,
    cf_b: FloatArray, n_b: IntArray, match_px: float,
) -> tuple[IntArray, FloatArray]:  # fmt: skip
    """:func:`keypoint_speed_steps` for frame pairs (a, b), stacked as :func:`_stacked` gives them: the pairs'
    midpoints and velocities, pairs without a matched person left out."""
    if kp_a.shape[1] == 0:  # nobody in any frame
        return np.zeros(0, dtype=np.int64), np.zeros(0)
    dt = (t_b - t_a) / 1e9
    # person_distances of every pair at once (the same sums over the same keypoint axis: the same floats)
    shared = (cf_a[:, :, None, :] > 0.0) & (cf_b[:, None, :, :] > 0.0)  # (pairs, a's people, b's people, n_kp)
    d = np.linalg.norm(kp_a[:, :, None] - kp_b[:, None, :], axis=-1)
    n = shared.sum(axis=-1)
    total = np.where(shared, d, 0.0).sum(axis=-1)
    dist = np.where(n > 0, total / np.maximum(n, 1), np.inf)  # padding is nobody: inf, after every real person
    j = np.argmin(dist, axis=2)  # the first of equals, and padding only where a row is all inf (unmatched)
    near = np.take_along_axis(dist, j[..., None], axis=2)[..., 0]
    people = np.arange(dist.shape[1])
    usable = (n_a > 0) & (n_b > 0) & (dt > 0)
    matched = (near <= match_px) & (people[None, :] < n_a[:, None]) & usable[:, None]
    pair, i = np.nonzero(matched)  # pairs in order, a's people in order within each: the loop's order
    jj = j[pair, i]
    both = (cf_a[pair, i] > 0.0) & (cf_b[pair, jj] > 0.0)  # (rows, n_kp)
    step = kp_b[pair, jj, :, 1] - kp_a[pair, i, :, 1]
    v = _row_means(step, both) / dt[pair]
    per_pair = np.zeros(matched.shape)
    per_pair[pair, i] = v
    has = matched.any(axis=1)
    mids = t_a[has] + (t_b[has] - t_a[has]) // 2  # (t_a + t_b) // 2 without the sum's overflow
    return mids, _row_means(per_pair[has], matched[has])


def _row_means(x: FloatArray, mask: BoolArray) -> FloatArray:
    """Per row of ``x`` (rows, n), the mean of its elements where ``mask``: rows with the same number of them are
    summed as one contiguous (rows, count) block, so each sum runs over the same numbers in the same order as
    ``np.mean(row[mask_row])`` does (the same floats, not just close ones). Every row has at least one."""
    count = mask.sum(axis=1)
    out = np.empty(x.shape[0])
    for c in np.unique(count):
        rows = count == c
        out[rows] = x[rows][mask[rows]].reshape(-1, int(c)).sum(axis=1) / c
    return out


def estimate_lag(
    t_a: IntArray,
    a: FloatArray,
    t_b: IntArray,
    b: FloatArray,
    *,
    max_lag_ns: int = 200_000_000,
    step_ns: int = 2_000_000,
) -> LagEstimate | None:
    """The shift of signal ``b`` relative to ``a`` that best aligns them (None: too little overlap).

    ``b(t + lag) ≈ a(t)``: a positive lag means b's time stamps run ahead.
    """
    return drain(estimate_lag_steps(t_a, a, t_b, b, max_lag_ns=max_lag_ns, step_ns=step_ns))


def estimate_lag_steps(
    t_a: IntArray,
    a: FloatArray,
    t_b: IntArray,
    b: FloatArray,
    *,
    max_lag_ns: int = 200_000_000,
    step_ns: int = 2_000_000,
) -> Steps[LagEstimate | None]:
    """:func:`estimate_lag` in steps of :data:`POINTS_PER_STEP` interpolated samples: a block of candidate lags
    scored in one array operation."""
    if len(t_a) < 8 or len(t_b) < 8:
        return None
    lo = max(int(t_a[0]), int(t_b[0]) - max_lag_ns)
    hi = min(int(t_a[-1]), int(t_b[-1]) + max_lag_ns)
    grid = np.arange(lo + max_lag_ns, hi - max_lag_ns, step_ns, dtype=np.int64)
    if grid.size < 16:
        return None
    sa = np.interp(grid, t_a, a)
    sa = (sa - sa.mean()) / (sa.std() + 1e-12)
    lags = np.arange(-max_lag_ns, max_lag_ns + 1, step_ns, dtype=np.int64)
    scores = np.empty(lags.size)
    per_step = max(1, POINTS_PER_STEP // grid.size)
    # Times as floats once (np.interp converts integer times on every call); exact below 2^53 ns (104 days).
    grid_f, lags_f, tb_f = grid.astype(np.float64), lags.astype(np.float64), np.asarray(t_b, dtype=np.float64)
    for i in range(0, lags.size, per_step):
        block = lags_f[i : i + per_step]
        sb = np.interp(grid_f[None, :] + block[:, None], tb_f, b)  # (lags, grid): b shifted by each lag
        sb = (sb - sb.mean(axis=1, keepdims=True)) / (sb.std(axis=1, keepdims=True) + 1e-12)
        scores[i : i + block.size] = np.mean(sa[None, :] * sb, axis=1)
        yield
    k = int(np.argmax(scores))
    frac = 0.0
    if 0 < k < len(scores) - 1:
        y0, y1, y2 = scores[k - 1], scores[k], scores[k + 1]
        denom = y0 - 2 * y1 + y2
        frac = 0.5 * (y0 - y2) / denom if denom < 0 else 0.0
    return LagEstimate(round(float(lags[k]) + frac * step_ns), float(scores[k]))


def estimate_imu_lag(
    cam_t_ns: IntArray,
    height_m: FloatArray,
    imu_t_ns: IntArray,
    vertical_acc: FloatArray,
    *,
    rate_hz: float = 100.0,
    band_hz: tuple[float, float] = (0.3, 5.0),
    max_lag_ns: int = 200_000_000,
) -> LagEstimate | None:
    """:func:`estimate_imu_lag_steps` at once."""
    return drain(estimate_imu_lag_steps(cam_t_ns, height_m, imu_t_ns, vertical_acc, rate_hz=rate_hz,
                                        band_hz=band_hz, max_lag_ns=max_lag_ns))  # fmt: skip


def estimate_imu_lag_steps(
    cam_t_ns: IntArray,
    height_m: FloatArray,
    imu_t_ns: IntArray,
    vertical_acc: FloatArray,
    *,
    rate_hz: float = 100.0,
    band_hz: tuple[float, float] = (0.3, 5.0),
    max_lag_ns: int = 200_000_000,
) -> Steps[LagEstimate | None]:
    """How far an IMU's time stamps run ahead of the cameras', from vertical motion seen by both.

    The camera side is the height of the IMU's body site as solved from the cameras (host time, camera offsets
    applied), differentiated to a velocity; the IMU side is its free vertical acceleration (world frame, gravity
    removed), integrated to a velocity. Both are resampled on one ``rate_hz`` grid and band-passed by the same
    zero-phase filter (the integration drift and the differentiation noise are outside the band, and a filter
    with no phase delay leaves the lag unbiased), then :func:`estimate_lag` finds the shift. Velocity rather
    than acceleration: a second difference of solved positions amplifies their noise too much at 60 Hz.

    Parameters
    ----------
    cam_t_ns : int array, shape (n,)
        Solve times of the heights, increasing.
    height_m : array, shape (n,)
    imu_t_ns : int array, shape (m,)
        The IMU's sample time stamps (as buffered, before any configured offset), increasing.
    vertical_acc : array, shape (m,)
        Free vertical acceleration (m/s², +up).

    Returns
    -------
    LagEstimate or None
        None when the records overlap too little (under ~3 s) or one of them is still.
    """
    lo = max(int(cam_t_ns[0]), int(imu_t_ns[0])) if len(cam_t_ns) and len(imu_t_ns) else 0
    hi = min(int(cam_t_ns[-1]), int(imu_t_ns[-1])) if len(cam_t_ns) and len(imu_t_ns) else 0
    step = round(1e9 / rate_hz)
    if hi - lo < 3_000_000_000:
        return None
    grid = np.arange(lo, hi, step, dtype=np.int64)
    v_cam = np.gradient(np.interp(grid, cam_t_ns, height_m), step / 1e9)
    a_imu = np.interp(grid, imu_t_ns, vertical_acc)
    # Trapezoidal, not a running sum: a running sum is half a sample (5 ms at 100 Hz) late.
    v_imu = np.concatenate([[0.0], np.cumsum(0.5 * (a_imu[1:] + a_imu[:-1]))]) * (step / 1e9)
    v_cam = band_pass(v_cam, rate_hz, *band_hz)
    yield
    v_imu = band_pass(v_imu, rate_hz, *band_hz)
    if v_cam.std() < 1e-3 or v_imu.std() < 1e-3:  # under 1 mm/s: nobody is moving, any lag would fit
        return None
    yield
    return (yield from estimate_lag_steps(grid, v_cam, grid, v_imu, max_lag_ns=max_lag_ns))
