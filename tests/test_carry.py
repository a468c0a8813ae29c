"""The pose carried between two solves (mocapd.core.carry): exact for a constant velocity, unchanged for one
solve."""

from __future__ import annotations

import numpy as np

from mocapd.core.carry import carry_pose
from mocapd.core.rotations import matrix_from_rotvec, quat_from_rotvec, quat_multiply, random_rotvec, rotvec_from_quat
from mocapd.core.skeleton import N_BONES

PERIOD = 16_666_667


def _at(start: np.ndarray, omega: np.ndarray, velocity: np.ndarray, k: float) -> np.ndarray:
    """θ after ``k`` periods of constant motion: root at ``velocity`` a period, each bone turning by ``omega`` (a
    rotation vector a period) in its own frame."""
    theta = np.empty(3 + 3 * N_BONES)
    theta[:3] = start[:3] + k * velocity
    q = quat_multiply(quat_from_rotvec(start[3:].reshape(-1, 3)), quat_from_rotvec(k * omega))
    theta[3:] = rotvec_from_quat(q).reshape(-1)
    return theta


def test_a_constant_velocity_motion_is_carried_exactly() -> None:
    rng = np.random.default_rng(3)
    start = np.concatenate([rng.normal(size=3), random_rotvec(rng, (N_BONES,), max_angle=2.0).reshape(-1)])
    omega = random_rotvec(rng, (N_BONES,), max_angle=0.2)
    velocity = np.array([0.02, -0.01, 0.03])
    prev, last = _at(start, omega, velocity, 0.0), _at(start, omega, velocity, 2.0)  # solved 2 periods apart
    for k in (3.0, 4.0):  # a period after the last solve, and two
        carried = carry_pose(last, 2 * PERIOD, round(k * PERIOD), prev, 0)
        want = _at(start, omega, velocity, k)
        np.testing.assert_allclose(carried[:3], want[:3], atol=1e-9)
        np.testing.assert_allclose(matrix_from_rotvec(carried[3:].reshape(-1, 3)),
                                   matrix_from_rotvec(want[3:].reshape(-1, 3)), atol=1e-7)  # fmt: skip


def test_a_pose_solved_once_is_carried_unchanged() -> None:
    rng = np.random.default_rng(4)
    last = np.concatenate([rng.normal(size=3), random_rotvec(rng, (N_BONES,), max_angle=2.0).reshape(-1)])
    carried = carry_pose(last, PERIOD, 2 * PERIOD)
    assert np.array_equal(carried, last) and carried is not last
    assert np.array_equal(carry_pose(last, PERIOD, 2 * PERIOD, last + 1.0, PERIOD), last)  # no interval between
