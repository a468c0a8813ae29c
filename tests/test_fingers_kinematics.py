"""The outputs' finger forward kinematics (:mod:`mocapd.protocols.fingers`) is the hand solver's (issue 44): from the
same hinge angles, hand rotation and wrist, every finger joint and fingertip agrees with
:func:`mocapd.core.hand_solver.hand_fk`, so what the streams and files carry is what the solve fitted; and the
extended bone list hangs each finger from its hand."""

from __future__ import annotations

import numpy as np

from mocapd.core.hand_skeleton import HAND_BONE_NAMES, LANDMARK_IS_TIP, HandSkeleton
from mocapd.core.hand_solver import N_HINGES, hand_fk
from mocapd.core.rotations import matrix_from_rotvec, quat_from_matrix, random_rotvec
from mocapd.core.skeleton import BONE_NAMES
from mocapd.protocols.fingers import EXTENDED_BONE_NAMES, EXTENDED_PARENTS, finger_kinematics


def test_finger_kinematics_equals_the_hand_solvers() -> None:
    rng = np.random.default_rng(2)
    hands = HandSkeleton.reference((0.9, 1.1))
    for _ in range(5):
        rot = matrix_from_rotvec(random_rotvec(rng, (2,), np.pi))
        wrist = rng.normal(size=(2, 3))
        fks = [hand_fk(hands, s, rng.uniform(-0.6, 1.2, N_HINGES), rot[s], wrist[s]) for s in range(2)]
        local = np.stack([quat_from_matrix(fk.local) for fk in fks])
        fs = finger_kinematics(rot[None], wrist[None], local[None], [hands])
        for s, fk in enumerate(fks):
            np.testing.assert_allclose(fs.positions[0, s], fk.joints, atol=1e-12)
            np.testing.assert_allclose(fs.rotations[0, s], fk.global_rotations, atol=1e-12)
            np.testing.assert_allclose(fs.tips[0, s], fk.landmarks[np.array(LANDMARK_IS_TIP)], atol=1e-12)


def test_the_extended_bone_list() -> None:
    assert (*BONE_NAMES, *HAND_BONE_NAMES) == EXTENDED_BONE_NAMES and len(EXTENDED_PARENTS) == 51
    named = {EXTENDED_BONE_NAMES[b]: EXTENDED_BONE_NAMES[p] for b, p in enumerate(EXTENDED_PARENTS) if p >= 0}
    assert named["LeftThumbProximal"] == "LeftHand" and named["RightLittleProximal"] == "RightHand"
    assert named["LeftIndexIntermediate"] == "LeftIndexProximal" and named["RightRingDistal"] == "RightRingIntermediate"
    assert all(p < b for b, p in enumerate(EXTENDED_PARENTS))  # parents first: one pass of forward kinematics
