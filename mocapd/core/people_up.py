"""The world's up axis and floor from the people in it: ``mocapd import keypoints --up auto``.

A calibration of another tool may say nothing usable about which way is up (a board held at an angle, a file whose
convention is unknown). People stand and walk upright: over many instants the median direction from the middle of a
person's ankles to the middle of their shoulders is the world's up to within a few degrees, and their lowest ankles
are an ankle's height above the floor. :func:`up_and_floor` measures both from triangulated people;
:func:`level_rotation` is the smallest rotation that turns that up onto +Y.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mocapd.errors import CalibrationError

FloatArray = NDArray[np.float64]

ANKLE_HEIGHT_FRACTION = 0.039
"""The ankle joint's height over the floor as a fraction of body height (Winter's anthropometric proportions)."""
MIN_PEOPLE_INSTANTS = 20
"""Fewest triangulated person-instants (shoulders and ankles seen) to estimate from."""
LOW_ANKLES_PERCENTILE = 10.0
"""The ankles' height taken as standing: this percentile of all ankle heights (a foot in the air is higher)."""


def _mid(points: FloatArray, names: list[str], a: str, b: str) -> FloatArray:
    return np.asarray(0.5 * (points[:, names.index(a)] + points[:, names.index(b)]))


def up_and_floor(points: FloatArray, names: list[str] | tuple[str, ...], height_m: float) -> tuple[
        FloatArray, float, int]:  # fmt: skip
    """Up (unit vector) and the floor's offset along it, from people triangulated in any world.

    Parameters
    ----------
    points : array, shape (n, n_kp, 3)
        Person-instants, NaN where a keypoint was not triangulated.
    names : sequence of str, length n_kp
        The keypoints' names (shoulders and ankles named ``left_shoulder``, ``right_ankle``, ...).
    height_m : float
        The people's height (the ankle joint is :data:`ANKLE_HEIGHT_FRACTION` of it above the floor).

    Returns
    -------
    up : array, shape (3,)
    floor : float
        The floor is the plane ``X @ up == floor`` (metres).
    used : int
        Person-instants measured.

    Raises
    ------
    CalibrationError
        Fewer than :data:`MIN_PEOPLE_INSTANTS` people seen whole.
    """
    names = list(names)
    need = {"left_shoulder", "right_shoulder", "left_ankle", "right_ankle"}
    if not need <= set(names):
        raise CalibrationError(f"the up axis from the people needs their shoulders and ankles; the keypoints lack "
                               f"{sorted(need - set(names))}")  # fmt: skip
    pts = np.asarray(points, dtype=np.float64)
    body = _mid(pts, names, "left_shoulder", "right_shoulder") - _mid(pts, names, "left_ankle", "right_ankle")
    length = np.linalg.norm(body, axis=1)
    ok = np.isfinite(length) & (length > 0.5)  # a person seen whole, not a collapsed triangulation
    if int(ok.sum()) < MIN_PEOPLE_INSTANTS:
        raise CalibrationError(f"the up axis from the people: {int(ok.sum())} people seen whole by two cameras, "
                               f"{MIN_PEOPLE_INSTANTS} needed; give --up y|z|-y")  # fmt: skip
    up = np.median(body[ok] / length[ok, None], axis=0)
    up /= np.linalg.norm(up)
    ankles = np.concatenate([pts[ok, names.index("left_ankle")], pts[ok, names.index("right_ankle")]])
    heights = ankles @ up
    floor = (
        float(np.percentile(heights[np.isfinite(heights)], LOW_ANKLES_PERCENTILE)) - ANKLE_HEIGHT_FRACTION * height_m
    )
    return up, floor, int(ok.sum())


def level_rotation(up: FloatArray) -> FloatArray:
    """The smallest rotation ``R`` (3x3) with ``R @ up == (0, 1, 0)``."""
    u = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    y = np.array([0.0, 1.0, 0.0])
    v = np.cross(u, y)
    s, c = float(np.linalg.norm(v)), float(u @ y)
    if s < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])  # already up, or upside down: half a turn about x
    k = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.asarray(np.eye(3) + k + k @ k * ((1.0 - c) / s**2))
