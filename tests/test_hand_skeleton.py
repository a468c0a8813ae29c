"""The hand skeleton's definition: names (Unity, VRM 0.x and 1.0), parents, landmark map, sizes, the pose type."""

from __future__ import annotations

import numpy as np
import pytest

from mocapd.core.hand_skeleton import (
    FINGER_BONES,
    FINGER_PARENTS,
    HAND_BONE_NAMES,
    HAND_PER_FOREARM,
    LANDMARK_BONE,
    LANDMARK_IS_TIP,
    N_FINGER_BONES,
    REFERENCE_HAND_LENGTH,
    VRM0_NAMES,
    VRM1_NAMES,
    HandPose,
    HandSkeleton,
    hand_bone_index,
)
from mocapd.core.keypoints import HAND21
from mocapd.core.skeleton import BONE_INDEX, Skeleton
from mocapd.errors import InputError


def test_names_follow_unity_and_vrm() -> None:
    assert N_FINGER_BONES == 15 and len(HAND_BONE_NAMES) == 30
    assert HAND_BONE_NAMES[0] == "LeftThumbProximal" and HAND_BONE_NAMES[-1] == "RightLittleDistal"
    assert FINGER_BONES[3:6] == ("IndexProximal", "IndexIntermediate", "IndexDistal")
    # VRM 1.0 renamed the thumb's bones (its first is the metacarpal); VRM 0.x kept Unity's
    assert VRM1_NAMES["LeftThumbProximal"] == "leftThumbMetacarpal"
    assert VRM1_NAMES["RightThumbIntermediate"] == "rightThumbProximal"
    assert VRM1_NAMES["RightThumbDistal"] == "rightThumbDistal"
    assert VRM1_NAMES["LeftLittleIntermediate"] == "leftLittleIntermediate"
    assert VRM0_NAMES["LeftThumbIntermediate"] == "leftThumbIntermediate"
    assert set(VRM1_NAMES) == set(HAND_BONE_NAMES) == set(VRM0_NAMES)
    assert hand_bone_index("Left") == BONE_INDEX["LeftHand"] and hand_bone_index("Right") == BONE_INDEX["RightHand"]


def test_parents_and_landmarks_make_three_bone_chains() -> None:
    assert FINGER_PARENTS == (-1, 0, 1, -1, 3, 4, -1, 6, 7, -1, 9, 10, -1, 12, 13)
    assert len(HAND21) == 21 and HAND21[0] == "wrist" and HAND21[4] == "thumb_tip" and HAND21[8] == "index_finger_tip"
    # each finger: three joints then a tip on the distal bone
    assert LANDMARK_BONE[5:9] == (3, 4, 5, 5) and LANDMARK_IS_TIP[5:9] == (False, False, False, True)
    assert LANDMARK_BONE[0] == -1


def test_reference_hand_is_the_anthropometric_length_and_mirrored() -> None:
    hand = HandSkeleton.reference()
    middle = hand.offsets[0, 6:9].sum(axis=0) + hand.tips[0, 2]  # wrist to the middle fingertip at rest
    assert middle[0] == pytest.approx(REFERENCE_HAND_LENGTH, rel=0.03)
    np.testing.assert_allclose(hand.offsets[1], hand.offsets[0] * [-1, 1, 1])
    np.testing.assert_allclose(hand.tips[1], hand.tips[0] * [-1, 1, 1])
    assert hand.offsets[0, 0, 2] > 0 and hand.offsets[0, 1, 2] > 0  # the thumb points forward (+Z)
    lengths = [np.linalg.norm(hand.offsets[0, 3 * f + 1 : 3 * f + 3], axis=1).sum() for f in range(5)]
    assert lengths[2] == max(lengths[1:])  # the middle finger is the longest


def test_from_body_follows_the_forearm() -> None:
    tall = Skeleton.from_bone_lengths({"LeftHand": 0.30, "RightHand": 0.28}, height=1.9)
    hand = HandSkeleton.from_body(tall)
    assert hand.length(0) == pytest.approx(HAND_PER_FOREARM * 0.30)
    assert hand.length(1) == pytest.approx(HAND_PER_FOREARM * 0.28)
    assert hand.rescaled(0, 1.1).length(0) == pytest.approx(1.1 * hand.length(0))
    assert hand.rescaled(0, 1.1).length(1) == pytest.approx(hand.length(1))


def test_bad_values_are_refused() -> None:
    with pytest.raises(InputError, match="hand scale"):
        HandSkeleton.reference((np.nan, 1.0))
    with pytest.raises(InputError, match="hand skeleton"):
        HandSkeleton(np.zeros((2, 14, 3)), np.zeros((2, 5, 3)), np.ones(2))
    hand = HandSkeleton.reference()
    with pytest.raises(InputError, match="non-finite"):
        HandPose(np.full((2, 15, 4), np.nan), np.ones(2, dtype=bool), hand)


def test_rest_pose_and_names() -> None:
    pose = HandPose.rest(HandSkeleton.reference())
    assert not pose.present.any() and pose.named() == {}
    present = HandPose(pose.rotations, np.array([True, False]), pose.skeleton)
    named = present.named()
    assert len(named) == 15 and set(named) == set(HAND_BONE_NAMES[:15])
    np.testing.assert_array_equal(named["LeftIndexDistal"], [1.0, 0.0, 0.0, 0.0])
