"""Skeleton sizing, forward kinematics and the kinematic Jacobians."""

from __future__ import annotations

import numpy as np
import pytest

from mocapd.core.kinematics import Kinematics
from mocapd.core.rotations import so3_exp, so3_log
from mocapd.core.skeleton import BONE_INDEX, BONE_NAMES, N_BONES, PARENTS, POSE_DIM, Skeleton
from mocapd.errors import InputError


def test_bone_list_matches_design() -> None:
    assert BONE_NAMES[0] == "Hips" and N_BONES == 21 and POSE_DIM == 66
    assert BONE_NAMES[PARENTS[BONE_INDEX["LeftUpperArm"]]] == "Spine3"
    assert BONE_NAMES[PARENTS[BONE_INDEX["RightUpperLeg"]]] == "Hips"
    assert BONE_NAMES[PARENTS[BONE_INDEX["Head"]]] == "Neck"
    assert all(p < i for i, p in enumerate(PARENTS))  # topological order


def test_rest_pose_stands_on_floor_facing_plus_z() -> None:
    sk = Skeleton.from_height(1.75)
    fk = Kinematics(sk).forward(sk.rest_pose())
    x = fk.positions
    assert x[BONE_INDEX["LeftFoot"], 1] == pytest.approx(0.07, abs=1e-9)
    assert x[BONE_INDEX["LeftToes"], 1] == pytest.approx(0.05, abs=1e-9)
    assert x[BONE_INDEX["LeftToes"], 2] > x[BONE_INDEX["LeftFoot"], 2]  # toes point +Z
    assert x[BONE_INDEX["LeftHand"], 0] > 0.6 > -0.6 > x[BONE_INDEX["RightHand"], 0]  # T-pose, left is +X
    assert 1.5 < x[BONE_INDEX["Head"], 1] < 1.75


def test_height_scaling_and_explicit_lengths() -> None:
    a, b = Skeleton.from_height(1.75), Skeleton.from_height(1.40)
    np.testing.assert_allclose(b.offsets, a.offsets * 1.40 / 1.75)
    c = Skeleton.from_bone_lengths({"LeftLowerLeg": 0.50, "RightLowerLeg": 0.50})
    assert c.bone_length("LeftLowerLeg") == pytest.approx(0.50)
    assert c.root_height == pytest.approx(a.root_height + 0.07)
    with pytest.raises(InputError, match="height"):
        Skeleton.from_height(7.0)
    with pytest.raises(InputError, match="unknown"):
        Skeleton.from_bone_lengths({"Tail": 0.3})
    with pytest.raises(InputError, match="shape"):
        Skeleton(offsets=np.zeros((20, 3)))


def test_batch_fk_equals_single_frames() -> None:
    rng = np.random.default_rng(0)
    sk = Skeleton.from_height(1.8)
    kin = Kinematics(sk)
    thetas = rng.normal(scale=0.4, size=(7, POSE_DIM))
    batch = kin.forward(thetas)
    for i in range(7):
        one = kin.forward(thetas[i])
        np.testing.assert_allclose(batch.positions[i], one.positions, atol=1e-12)
        np.testing.assert_allclose(batch.rotations[i], one.rotations, atol=1e-12)
    with pytest.raises(InputError, match="66"):
        kin.forward(np.zeros(65))


def test_fk_bone_lengths_are_preserved() -> None:
    rng = np.random.default_rng(1)
    sk = Skeleton.from_height(1.75)
    fk = Kinematics(sk).forward(rng.normal(scale=1.0, size=(20, POSE_DIM)))
    for b in range(1, N_BONES):
        lengths = np.linalg.norm(fk.positions[:, b] - fk.positions[:, PARENTS[b]], axis=-1)
        np.testing.assert_allclose(lengths, np.linalg.norm(sk.offsets[b]), atol=1e-12)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_point_and_angular_jacobians_match_finite_differences(seed: int) -> None:
    rng = np.random.default_rng(seed)
    sk = Skeleton.from_height(1.75)
    kin = Kinematics(sk)
    theta = rng.normal(scale=0.6, size=POSE_DIM)
    bones = np.arange(N_BONES)
    offs = rng.normal(scale=0.1, size=(N_BONES, 3))
    pairs = kin.chain_pairs(bones)

    def points(th: np.ndarray) -> np.ndarray:
        return kin.targets(kin.forward(th), bones, offs)

    fk = kin.forward(theta)
    axes = kin.angular_axes(fk, theta)
    J = kin.point_jacobian(fk, axes, points(theta), pairs)
    Jw = kin.angular_jacobian(axes, pairs, N_BONES)
    eps = 1e-6
    Jn = np.zeros_like(J)
    Jwn = np.zeros_like(Jw)
    for k in range(POSE_DIM):
        d = np.zeros(POSE_DIM)
        d[k] = eps
        Jn[:, :, k] = (points(theta + d) - points(theta - d)) / (2 * eps)
        Rp, Rm = kin.forward(theta + d).rotations, kin.forward(theta - d).rotations
        # global angular perturbation: R(θ+d) = exp(ω) R(θ)
        Jwn[:, :, k] = (
            so3_log(Rp @ np.swapaxes(fk.rotations, -1, -2)) - so3_log(Rm @ np.swapaxes(fk.rotations, -1, -2))
        ) / (2 * eps)
    assert np.max(np.abs(J - Jn)) / np.max(np.abs(Jn)) < 1e-6
    assert np.max(np.abs(Jw - Jwn)) / np.max(np.abs(Jwn)) < 1e-6


def test_local_rotation_is_exp_of_theta() -> None:
    sk = Skeleton.from_height(1.75)
    theta = sk.rest_pose()
    theta[3 + 3 * BONE_INDEX["LeftLowerArm"] + 1] = 0.5
    fk = Kinematics(sk).forward(theta)
    np.testing.assert_allclose(fk.local[BONE_INDEX["LeftLowerArm"]], so3_exp(np.array([0.0, 0.5, 0.0])))
