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

from mocapd.core.sorting import Detections2D
from mocapd.pipeline.keypoint_timeline import person_distances

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
T = TypeVar("T")
Steps = Generator[None, None, T]
"""Work that yields after each bounded piece and returns its result."""

FRAMES_PER_STEP = 8
"""Frames of keypoint speed per step (each: a person matching and a few NumPy calls, ~0.1 ms on a laptop core)."""
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

    Returns
    -------
    times : int array, shape (n,)
    velocity : array, shape (n,)
        Frames without a matched person are left out.
    """
    out_t: list[int] = []
    out_v: list[float] = []
    for k in range(1, len(frames)):
        if k % FRAMES_PER_STEP == 0:
            yield
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


def _band_pass(x: FloatArray, rate_hz: float, low_hz: float, high_hz: float) -> FloatArray:
    """Zero-phase (forward-backward) 2nd-order Butterworth band-pass: no delay, so no bias in the lag."""
    from scipy.signal import butter, sosfiltfilt

    sos = butter(2, [low_hz, high_hz], btype="bandpass", fs=rate_hz, output="sos")
    return np.asarray(sosfiltfilt(sos, x))


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
    v_cam = _band_pass(v_cam, rate_hz, *band_hz)
    yield
    v_imu = _band_pass(v_imu, rate_hz, *band_hz)
    if v_cam.std() < 1e-3 or v_imu.std() < 1e-3:  # under 1 mm/s: nobody is moving, any lag would fit
        return None
    yield
    return (yield from estimate_lag_steps(grid, v_cam, grid, v_imu, max_lag_ns=max_lag_ns))
