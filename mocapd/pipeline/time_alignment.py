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
