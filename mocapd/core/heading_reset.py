"""Heading reset of IMUs without cameras, and the yaw drift it reveals.

A 6-axis tracker (SlimeVR class: no magnetometer) knows its vertical from gravity but integrates its heading from
the gyroscope, which drifts (degrees a minute); no single measurement can tell where it drifted to. Its users
rely on a reset they trigger themselves: they stand straight facing forward — the direction they faced when the
suit was calibrated — and the server turns every sensor about the vertical so that its bone faces forward again
(SlimeVR's "yaw reset"). mocapd does the same, for any IMU: :func:`reset_yaws` gives, for each calibrated bone
orientation, the turn about world up that brings its heading back to the rest pose's (the T-pose faces +Z, its
left is +X; a bone standing straight has the rest heading whether the arms are out or hang down).

The heading of a bone is that of whichever of its two horizontal rest axes, forward (+Z) or left (+X), is more
horizontal now: standing straight both are (legs, torso, feet), with the arms hanging down only the forward axis
is, and the other's small horizontal part would then come from a tilt, not a heading.

Each reset also measures how far each sensor had drifted since the previous one: :class:`ResetHistory` keeps the
corrections and times and estimates each sensor's drift rate, and how far it has drifted since the last reset.
Pure: times are arguments.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from mocapd.core.rotations import quat_conjugate, quat_from_rotvec, quat_multiply, quat_rotate

FloatArray = NDArray[np.float64]

_X = np.array([1.0, 0.0, 0.0])
_Z = np.array([0.0, 0.0, 1.0])


def reset_yaws(q_gb: FloatArray) -> FloatArray:
    """Turn about world +Y (radians, (-π, π]) that puts each bone's heading at the rest pose's.

    Parameters
    ----------
    q_gb : array, shape (n, 4)
        World orientations of the bones (w, x, y, z), rest pose = identity.

    Returns
    -------
    array, shape (n,)
        ``ψ`` such that ``R_y(ψ) · R_gb`` faces forward (+Z).
    """
    q = np.asarray(q_gb, dtype=np.float64).reshape(-1, 4)
    fwd = quat_rotate(q, np.broadcast_to(_Z, (len(q), 3)))
    left = quat_rotate(q, np.broadcast_to(_X, (len(q), 3)))
    use_fwd = np.hypot(fwd[:, 0], fwd[:, 2]) >= np.hypot(left[:, 0], left[:, 2])
    # The turn about +Y taking the axis' horizontal part onto its rest direction: forward lies at atan2(x, z) = 0,
    # left at atan2(x, z) = 90 deg.
    heading = np.where(use_fwd, np.arctan2(fwd[:, 0], fwd[:, 2]), np.arctan2(left[:, 0], left[:, 2]) - np.pi / 2)
    out: FloatArray = -np.angle(np.exp(1j * heading))
    return out


def enu_turn(q_ig: FloatArray, yaw: float) -> FloatArray:
    """The turn about the device frame's up axis that turns a sensor by ``yaw`` about world +Y (radians): the
    device heading ``δ`` with ``R_ig · R_z(δ) = R_y(yaw) · R_ig`` (``R_ig`` maps the device's up onto world up).

    Returns
    -------
    array, shape (4,)
    """
    y = quat_from_rotvec(np.array([0.0, float(yaw), 0.0]))
    out: FloatArray = quat_multiply(quat_multiply(quat_conjugate(q_ig), y), q_ig)
    return out


@dataclass
class SensorResets:
    """The resets of one sensor so far."""

    count: int = 0
    last_ns: int | None = None
    last_deg: float = 0.0
    """The correction of the last reset (how far it had drifted since the one before, or since it was first seen)."""
    rate_deg_per_min: float | None = None
    """Drift rate from the resets (corrections over the time between them), exponentially averaged."""


@dataclass
class ResetHistory:
    """Per sensor: the corrections of every heading reset, and the drift rate they reveal.

    ``since_ns`` is when a sensor's heading was last known right without a reset (its calibration, or when the
    daemon started): the first reset's correction is its drift since then.
    """

    since_ns: int
    smoothing: float = 0.5
    """Weight of a new reset's rate in the running estimate."""
    sensors: dict[str, SensorResets] = field(default_factory=dict)

    def record(self, t_ns: int, corrections_deg: dict[str, float]) -> None:
        """A reset at ``t_ns`` turned each sensor by ``corrections_deg[sensor]`` degrees."""
        for sid, deg in corrections_deg.items():
            s = self.sensors.setdefault(sid, SensorResets())
            before = s.last_ns if s.last_ns is not None else self.since_ns
            minutes = (t_ns - before) / 60e9
            if minutes >= 1.0 / 60.0:  # a reset within a second of the last says nothing about a rate
                rate = -deg / minutes  # the sensor drifted by minus the turn that undid it
                s.rate_deg_per_min = rate if s.rate_deg_per_min is None else (
                    self.smoothing * rate + (1 - self.smoothing) * s.rate_deg_per_min)  # fmt: skip
            s.count += 1
            s.last_ns = t_ns
            s.last_deg = deg

    def status(self, sid: str, now_ns: int) -> dict[str, float | int | None]:
        """A sensor's resets: how many, when the last was (s ago), its correction (deg), the drift rate they show
        (deg/min) and the drift expected since the last (deg)."""
        s = self.sensors.get(sid, SensorResets())
        since = s.last_ns if s.last_ns is not None else self.since_ns
        minutes = (now_ns - since) / 60e9
        return {
            "resets": s.count,
            "last_reset_s_ago": None if s.last_ns is None else round((now_ns - s.last_ns) / 1e9, 1),
            "last_correction_deg": round(s.last_deg, 2),
            "rate_from_resets_deg_per_min": None if s.rate_deg_per_min is None else round(s.rate_deg_per_min, 2),
            "expected_since_reset_deg": None if s.rate_deg_per_min is None else round(s.rate_deg_per_min * minutes, 2),
        }
