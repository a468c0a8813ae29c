"""Time-offset estimation by correlation (camera ↔ camera from vertical keypoint velocities).

Two cameras watching the same motion see their people's keypoints move up and down together; if one camera's
time stamps run ``d`` ahead, its signal is the other's shifted by ``d``. :func:`estimate_lag` finds ``d`` as the
peak of the normalised cross-correlation of the two signals resampled on a common grid (parabolic refinement
between grid steps). :func:`keypoint_speed` turns a camera's detected frames into such a signal (mean vertical
image velocity of the people matched between consecutive frames).

Pure: time stamps are arguments. The daemon reports the estimates as suggestions in /status; the configured
``[daemon.offsets]`` stay in charge (an estimate from a still scene is meaningless, and the ``quality`` says so).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mocapd.core.sorting import Detections2D
from mocapd.pipeline.keypoint_timeline import person_distances

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True, slots=True)
class LagEstimate:
    """``lag_ns``: how far signal b's time stamps run ahead of a's; ``quality``: the correlation peak (0..1)."""

    lag_ns: int
    quality: float


def keypoint_speed(
    times_ns: IntArray, frames: list[Detections2D], match_px: float = 80.0
) -> tuple[IntArray, FloatArray]:
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
    for i, lag in enumerate(lags):
        sb = np.interp(grid + lag, t_b, b)
        sb = (sb - sb.mean()) / (sb.std() + 1e-12)
        scores[i] = float(np.mean(sa * sb))
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
    v_imu = _band_pass(v_imu, rate_hz, *band_hz)
    if v_cam.std() < 1e-3 or v_imu.std() < 1e-3:  # under 1 mm/s: nobody is moving, any lag would fit
        return None
    return estimate_lag(grid, v_cam, grid, v_imu, max_lag_ns=max_lag_ns)
