"""A person's pose carried forward from their last two solves (the governor's last step, issue 39).

When the governor's last step solves people on every other tick only, the ticks between still publish every
person: their last solved pose carried forward at the velocity of their last two solves. The root translation moves
on linearly; each bone's local rotation turns on by its last relative rotation (in the bone's own frame: for
``R_prev`` then ``R_last``, the step ``Δ = R_prev⁻¹ · R_last``), scaled to the time carried over the time between the
solves (``R = R_last · Δ^s``, ``s = (t - t_last) / (t_last - t_prev)``). A motion at constant velocity (root and
every bone's angular velocity constant in its own frame) is carried exactly; a person solved once is carried
unchanged.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mocapd.core.rotations import quat_conjugate, quat_from_rotvec, quat_multiply, rotvec_from_quat

FloatArray = NDArray[np.float64]


def carry_pose(
    theta_last: FloatArray, t_last_ns: int, t_ns: int, theta_prev: FloatArray | None = None, t_prev_ns: int = 0
) -> FloatArray:
    """The pose at ``t_ns`` carried from the solve at ``t_last_ns`` by the motion since the solve before it.

    Parameters
    ----------
    theta_last : array, shape (3 + 3k,)
        The last solved θ: root translation, then ``k`` local rotation vectors (the solver's layout, (66,)).
    t_last_ns, t_ns : int
        The instant ``theta_last`` was solved for, and the instant to carry it to.
    theta_prev : array, shape (3 + 3k,), optional
        The solve before it, for ``t_prev_ns`` (None: one solve only, carried unchanged).

    Returns
    -------
    array, shape (3 + 3k,)
        A new θ (rotation vectors of angle at most π).
    """
    if theta_prev is None or t_last_ns <= t_prev_ns:
        return np.array(theta_last, dtype=np.float64)
    s = (t_ns - t_last_ns) / (t_last_ns - t_prev_ns)
    out = np.empty_like(theta_last, dtype=np.float64)
    out[:3] = theta_last[:3] + s * (theta_last[:3] - theta_prev[:3])
    q_last = quat_from_rotvec(theta_last[3:].reshape(-1, 3))
    q_prev = quat_from_rotvec(theta_prev[3:].reshape(-1, 3))
    step = rotvec_from_quat(quat_multiply(quat_conjugate(q_prev), q_last))  # Δ, in the bone's own frame
    q = quat_multiply(q_last, quat_from_rotvec(s * step))
    out[3:] = rotvec_from_quat(q).reshape(-1)
    return out
