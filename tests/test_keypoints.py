"""Keypoint formats (COCO-17, Body25, Halpe-26, BlazePose-33), their default track targets and the solver's COCO-17
table."""

from __future__ import annotations

import numpy as np
import pytest

from mocapd.core.keypoints import BLAZEPOSE33_FORMAT as BLAZEPOSE33
from mocapd.core.keypoints import BODY25_FORMAT as BODY25
from mocapd.core.keypoints import COCO17 as COCO17_TABLE
from mocapd.core.keypoints import COCO17_FORMAT as COCO17
from mocapd.core.keypoints import FORMATS, KeypointFormat, TrackTarget, coco17_targets, keypoint_format
from mocapd.core.keypoints import HALPE26_FORMAT as HALPE26
from mocapd.core.lr_flips import lr_pairs
from mocapd.core.skeleton import BONE_NAMES, Skeleton
from mocapd.errors import ConfigError


def test_the_coco17_format_is_the_solvers_coco17_table() -> None:
    # One set of COCO-17 defaults: the format and the solver's targets agree name by name.
    assert COCO17.keypoints == tuple(n for n, _, _ in COCO17_TABLE)
    for name, bone, offset in COCO17_TABLE:
        assert COCO17.targets[name] == TrackTarget(bone, offset)
    for sk in (None, Skeleton.from_height(1.6)):
        a, b = COCO17.track_targets(sk), coco17_targets(sk)
        assert a.names == b.names
        np.testing.assert_array_equal(a.bones, b.bones)
        np.testing.assert_allclose(a.offsets, b.offsets)


@pytest.mark.parametrize(("fmt", "n"), [(COCO17, 17), (BODY25, 25), (HALPE26, 26), (BLAZEPOSE33, 33)])
def test_sizes_and_unique_names(fmt: KeypointFormat, n: int) -> None:
    assert fmt.n_keypoints == n
    assert len(set(fmt.keypoints)) == n
    for a, b in fmt.edges:
        assert 0 <= a < n and 0 <= b < n


@pytest.mark.parametrize("fmt", list(FORMATS.values()))
def test_every_keypoint_has_a_target_on_a_real_bone(fmt: KeypointFormat) -> None:
    assert set(fmt.targets) == set(fmt.keypoints)
    for tt in fmt.targets.values():
        assert tt.bone in BONE_NAMES
        assert all(abs(v) < 0.25 for v in tt.offset)


@pytest.mark.parametrize("fmt", list(FORMATS.values()))
def test_left_and_right_are_mirror_images(fmt: KeypointFormat) -> None:
    for name, tt in fmt.targets.items():
        if not name.startswith("left_"):
            continue
        twin = fmt.targets[name.replace("left_", "right_")]
        assert twin.bone == tt.bone.replace("Left", "Right")
        assert twin.offset == (-tt.offset[0], tt.offset[1], tt.offset[2])
        # +X is the subject's left (facing +Z, +Y up, right-handed): left-side face points have x > 0.
        if tt.bone == "Head":
            assert tt.offset[0] > 0


def test_joint_keypoints_sit_on_the_child_bone_origin() -> None:
    expected = {
        "left_shoulder": "LeftUpperArm",
        "left_elbow": "LeftLowerArm",
        "left_wrist": "LeftHand",
        "right_hip": "RightUpperLeg",
        "right_knee": "RightLowerLeg",
        "right_ankle": "RightFoot",
    }
    for name, bone in expected.items():
        assert COCO17.targets[name] == TrackTarget(bone, (0.0, 0.0, 0.0))
    assert COCO17.targets["nose"].bone == "Head" and COCO17.targets["nose"].offset[2] > 0
    assert BODY25.targets["mid_hip"].bone == "Hips" and HALPE26.targets["hip"].bone == "Hips"
    assert BODY25.targets["left_big_toe"].bone == "LeftToes"
    assert HALPE26.targets["right_heel"].bone == "RightFoot"


def test_formats_agree_on_shared_keypoints() -> None:
    for name in COCO17.keypoints:
        assert BODY25.targets[name] == COCO17.targets[name] == HALPE26.targets[name] == BLAZEPOSE33.targets[name]
    assert HALPE26.keypoints[:17] == COCO17.keypoints


def test_lookup_and_errors() -> None:
    assert keypoint_format("body25") is BODY25
    assert COCO17.index("left_wrist") == 9 and BODY25.index("left_wrist") == 7
    with pytest.raises(ConfigError, match="unknown keypoint format"):
        keypoint_format("mpi15")
    with pytest.raises(ConfigError, match="no keypoint"):
        COCO17.index("neck")
    with pytest.raises(ConfigError, match="unknown bone"):
        KeypointFormat("x", ("a",), {"a": TrackTarget("Tail")}, ())
    custom = COCO17.with_offsets({"nose": TrackTarget("Head", (0.0, 0.1, 0.12))})
    assert custom.targets["nose"].offset == (0.0, 0.1, 0.12)
    assert COCO17.targets["nose"].offset != (0.0, 0.1, 0.12)


def test_blazepose33_is_mediapipes_landmark_order_with_feet_and_hands_on_their_bones() -> None:
    # MediaPipe's indices: 0 nose, 11/12 shoulders, 15/16 wrists, 17-22 pinky/index/thumb, 23/24 hips,
    # 27/28 ankles, 29/30 heels, 31/32 foot index.
    assert keypoint_format("blazepose33") is BLAZEPOSE33
    for name, i in (("nose", 0), ("left_shoulder", 11), ("right_wrist", 16), ("left_pinky", 17), ("right_thumb", 22),
                    ("left_hip", 23), ("right_ankle", 28), ("left_heel", 29), ("right_foot_index", 32)):  # fmt: skip
        assert BLAZEPOSE33.index(name) == i
    for side, bone in (("left", "Left"), ("right", "Right")):
        assert BLAZEPOSE33.targets[f"{side}_heel"].bone == f"{bone}Foot"
        assert BLAZEPOSE33.targets[f"{side}_foot_index"].bone == f"{bone}Toes"
        for finger in ("pinky", "index", "thumb"):
            tt = BLAZEPOSE33.targets[f"{side}_{finger}"]
            assert tt.bone == f"{bone}Hand"
            # Beyond the wrist, toward the hand's own side (+x is the subject's left in the rest pose).
            assert tt.offset[0] * (1 if side == "left" else -1) > 0
    # The heel is behind the ankle, the toe tip in front: the foot's pitch and yaw are observed.
    assert BLAZEPOSE33.targets["left_heel"].offset[2] < 0 < BLAZEPOSE33.targets["left_foot_index"].offset[2]
    # Thumb and pinky on opposite sides of the hand's axis: its roll is observed too.
    assert BLAZEPOSE33.targets["left_thumb"].offset[2] > 0 > BLAZEPOSE33.targets["left_pinky"].offset[2]


def test_blazepose33_pairs_every_left_point_with_its_right_twin() -> None:
    pairs = lr_pairs(BLAZEPOSE33.keypoints)
    assert len(pairs) == 16  # 33 = the nose + 16 pairs
    for li, ri in pairs:
        assert BLAZEPOSE33.keypoints[ri] == BLAZEPOSE33.keypoints[li].replace("left_", "right_")


def test_blazepose33_offsets_are_calibratable() -> None:
    moved = BLAZEPOSE33.with_offsets({"left_heel": TrackTarget("LeftFoot", (0.0, -0.06, -0.07))})
    tt = moved.track_targets()
    i = tt.names.index("left_heel")
    np.testing.assert_allclose(tt.offsets[i], (0.0, -0.06, -0.07))
    assert len(tt) == 33
