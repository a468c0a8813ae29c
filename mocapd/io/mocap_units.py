"""Helpers shared by the motion-file readers: Euler angles and length-unit detection."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mocapd.core.rotations import quat_from_rotvec, quat_multiply

FloatArray = NDArray[np.float64]

_AXES = {"x": np.array([1.0, 0.0, 0.0]), "y": np.array([0.0, 1.0, 0.0]), "z": np.array([0.0, 0.0, 1.0])}

CANDIDATE_UNITS: dict[str, float] = {
    "m": 1.0,
    "cm": 0.01,
    "mm": 0.001,
    "inch": 0.0254,
    "cmu": 0.0254 / 0.45,  # CMU: ASF `length 0.45` — 1 unit = 1/0.45 inch
}
"""Length units a motion file may use, metres per unit."""

LEG_LENGTH_M = 0.85
"""Typical adult hip-to-ankle length (m) used to recognise a file's unit when the file does not say."""


def quat_from_euler(angles_deg: FloatArray, order: str) -> FloatArray:
    """Quaternions of intrinsic Euler rotations applied in ``order`` (e.g. "zyx": R = Rz Ry Rx).

    Parameters
    ----------
    angles_deg : array, shape (..., len(order))
        Angles in degrees, one column per letter of ``order``.

    Returns
    -------
    array, shape (..., 4)
    """
    a = np.deg2rad(np.asarray(angles_deg, dtype=np.float64))
    q = np.zeros((*a.shape[:-1], 4))
    q[..., 0] = 1.0
    for k, axis in enumerate(order.lower()):
        q = quat_multiply(q, quat_from_rotvec(a[..., k, None] * _AXES[axis]))
    return q


def detect_unit(leg_length_units: float) -> tuple[str, float]:
    """The candidate unit that makes a hip-to-ankle length closest (in log) to an adult's, with its scale."""
    if not (np.isfinite(leg_length_units) and leg_length_units > 0):
        return "m", 1.0
    best = min(CANDIDATE_UNITS.items(), key=lambda kv: abs(np.log(leg_length_units * kv[1] / LEG_LENGTH_M)))
    return best
