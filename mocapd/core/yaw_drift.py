"""Each IMU's yaw drift, measured while it is still: a sensor at rest does not turn, so every change of its heading
then is drift (gyroscope bias; gravity holds the tilt, nothing holds the heading of a 6-axis sensor).

:class:`StillDrift` is given each sensor's newest samples now and then (the daemon: once a second). Where the
samples since the last look span at least ``min_still_s`` and the sensor was still over them — the specific
force's norm steady (``max_acc_std``) and its direction in the sensor frame steady (``max_tilt_deg``: no turn
about a horizontal axis) — the heading's change over them is drift: its slope (least squares over the span) is
accumulated with the span's length. The rate is the accumulated drift over the accumulated still time, reported
once ``min_total_s`` of stillness has been seen. A magnetometer-aided sensor (Xsens) measures about zero; a
SlimeVR tracker its gyroscope's bias.

The heading is the angle about the device frame's up (+Z, ENU) of whichever sensor axis is most horizontal at the
start of the span (a still sensor keeps its tilt, so the same axis serves the whole span). Pure: samples in,
numbers out.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from mocapd.core.rotations import quat_rotate

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class StillDriftOptions:
    min_still_s: float = 0.5
    """A span shorter than this is not used (too short to see a slope in the noise)."""
    max_acc_std: float = 0.1
    """Largest standard deviation of the specific force's norm over a still span (m/s²)."""
    max_tilt_deg: float = 1.0
    """Largest angle between the gravity direction (sensor frame) of the span's first and second half (deg)."""
    min_total_s: float = 5.0
    """Still time needed before a rate is reported (s)."""
    max_span_s: float = 5.0
    """Samples older than this before the newest are not looked at (s)."""


@dataclass
class _Sensor:
    last_ns: int | None = None
    still_s: float = 0.0
    drift_deg: float = 0.0
    spans: int = 0


@dataclass
class StillDrift:
    """Yaw drift per sensor from its still spans (see the module docstring)."""

    options: StillDriftOptions = field(default_factory=StillDriftOptions)
    sensors: dict[str, _Sensor] = field(default_factory=dict)

    def observe(self, sensor: str, t_ns: IntArray, quat: FloatArray, acc: FloatArray) -> bool:
        """Look at ``sensor``'s newest samples; returns True when a still span was used.

        Parameters
        ----------
        t_ns : array, shape (n,)
            Increasing sample times.
        quat : array, shape (n, 4)
            Sensor orientation in its device's frame (+Z up), (w, x, y, z).
        acc : array, shape (n, 3)
            Specific force in the sensor frame (m/s²).
        """
        o = self.options
        s = self.sensors.setdefault(sensor, _Sensor())
        t = np.asarray(t_ns, dtype=np.int64)
        if t.size == 0:
            return False
        keep = t > max(s.last_ns if s.last_ns is not None else t[0] - 1, int(t[-1]) - round(o.max_span_s * 1e9))
        s.last_ns = int(t[-1])
        t, q, a = t[keep], np.asarray(quat, dtype=np.float64)[keep], np.asarray(acc, dtype=np.float64)[keep]
        if t.size < 4 or (t[-1] - t[0]) / 1e9 < o.min_still_s:
            return False
        norm = np.linalg.norm(a, axis=1)
        if float(norm.std()) > o.max_acc_std or not np.all(np.isfinite(q)):
            return False
        half = len(a) // 2
        g0, g1 = a[:half].mean(axis=0), a[half:].mean(axis=0)
        cos = float(np.dot(g0, g1) / max(np.linalg.norm(g0) * np.linalg.norm(g1), 1e-12))
        if np.degrees(np.arccos(min(1.0, max(-1.0, cos)))) > o.max_tilt_deg:
            return False
        yaw = _heading(q)
        ts = (t - t[0]) / 1e9
        slope = float(np.polyfit(ts, yaw, 1)[0])  # rad/s
        span = float(ts[-1])
        s.still_s += span
        s.drift_deg += float(np.degrees(slope)) * span
        s.spans += 1
        return True

    def status(self, sensor: str) -> dict[str, float | int | None]:
        """Still time seen (s), the drift measured over it (deg) and the rate (deg/min, None before
        ``min_total_s``)."""
        s = self.sensors.get(sensor, _Sensor())
        rate = 60.0 * s.drift_deg / s.still_s if s.still_s >= self.options.min_total_s else None
        return {"still_s": round(s.still_s, 1), "still_drift_deg": round(s.drift_deg, 2),
                "rate_when_still_deg_per_min": None if rate is None else round(rate, 2)}  # fmt: skip


def _heading(q: FloatArray) -> FloatArray:
    """Unwrapped heading about +Z (rad) of the sensor axis most horizontal at the first sample, shape (n,)."""
    axes = np.eye(3)
    first = quat_rotate(np.broadcast_to(q[0], (3, 4)), axes)
    k = int(np.argmin(np.abs(first[:, 2])))
    v = quat_rotate(q, np.broadcast_to(axes[k], (len(q), 3)))
    out: FloatArray = np.unwrap(np.arctan2(v[:, 1], v[:, 0]))
    return out
