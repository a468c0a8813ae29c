"""The BVH writer: Euler decomposition (gimbal lock included), the hierarchy and channel order, and a round trip
through mocapd's BVH reader with a non-default skeleton."""

from __future__ import annotations

import numpy as np
import pytest

from mocapd.core.kinematics import Kinematics
from mocapd.core.rotations import matrix_from_quat, matrix_from_rotvec, random_rotvec
from mocapd.core.skeleton import BONE_NAMES, Skeleton
from mocapd.core.synthetic import moving_sequence
from mocapd.errors import InputError
from mocapd.io.bvh import parse_bvh
from mocapd.io.mocap_units import quat_from_euler
from mocapd.protocols.bvh_writer import bvh_text, euler_zxy_from_matrix


def test_euler_zxy_reconstructs_the_rotation_also_at_gimbal_lock() -> None:
    rng = np.random.default_rng(0)
    R = matrix_from_rotvec(random_rotvec(rng, (500,)))
    lock = matrix_from_quat(quat_from_euler(np.array([[30.0, 90.0, 20.0], [-10.0, -90.0, 45.0]]), "zxy"))
    R = np.concatenate([R, lock])
    angles = euler_zxy_from_matrix(R)
    assert np.all(np.abs(angles[:, 1]) <= 90.0)
    back = matrix_from_quat(quat_from_euler(angles, "zxy"))
    assert np.abs(back - R).max() < 1e-7  # arcsin near ±1 costs precision; BVH text keeps 1e-6 degrees


def test_hierarchy_channels_and_round_trip() -> None:
    sk = Skeleton.from_bone_lengths({"LeftLowerLeg": 0.47, "RightLowerArm": 0.31}, height=1.82)
    th = moving_sequence(sk, 40, seed=5)
    text = bvh_text(sk.offsets, th, 60.0)
    lines = text.splitlines()
    assert lines[:5] == ["HIERARCHY", "ROOT Hips", "{", "\tOFFSET 0.000000 0.000000 0.000000",
                         "\tCHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation"]  # fmt: skip
    assert text.count("CHANNELS 3 Zrotation Xrotation Yrotation") == 20 and text.count("End Site") == 5
    assert "Frames: 40" in text and "Frame Time: 0.01666667" in text
    m = parse_bvh(text, unit="cm")
    assert m.joint_names == BONE_NAMES and m.fps == 60.0
    G, x = m.forward()
    fk = Kinematics(sk).forward(th)
    assert np.abs(x - fk.positions).max() < 1e-7 and np.abs(G - fk.rotations).max() < 1e-7
    assert np.allclose(m.translations[0, 1:], sk.offsets[1:], atol=1e-8)  # OFFSETs are the skeleton's


def test_bad_inputs_are_errors() -> None:
    sk = Skeleton.from_height()
    with pytest.raises(InputError):
        bvh_text(sk.offsets[:5], np.zeros((1, 66)), 60.0)
    with pytest.raises(InputError):
        bvh_text(sk.offsets, np.zeros((0, 66)), 60.0)
    with pytest.raises(InputError):
        bvh_text(sk.offsets, np.full((2, 66), np.nan), 60.0)
    with pytest.raises(InputError):
        bvh_text(sk.offsets, np.zeros((2, 66)), 0.0)
