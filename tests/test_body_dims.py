"""A skeleton from a tape measure: a height and any segment lengths (``[imu.body]``, ``import --thigh`` ...)."""

from __future__ import annotations

import numpy as np
import pytest

from mocapd.core.body_dims import SEGMENTS, BodySpec, default_lengths, segment_lengths, skeleton_from_segments
from mocapd.core.skeleton import BONE_INDEX, Skeleton
from mocapd.errors import InputError
from mocapd.service.config import parse_config
from mocapd.service.rig_plan import rig_skeleton


def test_the_default_proportions_are_the_height_s_and_each_segment_given_is_that_long() -> None:
    for h in (1.5, 1.75, 2.0):
        np.testing.assert_allclose(skeleton_from_segments(h, {}).offsets, Skeleton.from_height(h).offsets)
        np.testing.assert_allclose(
            skeleton_from_segments(h, default_lengths(h)).offsets, Skeleton.from_height(h).offsets
        )
        assert skeleton_from_segments(h, {}).root_height == pytest.approx(Skeleton.from_height(h).root_height)
    given = {"hip_width": 0.21, "thigh": 0.47, "shank": 0.41, "foot": 0.15, "ankle_height": 0.08, "torso": 0.5,
             "shoulder_width": 0.4, "upper_arm": 0.31, "forearm": 0.27}  # fmt: skip
    assert set(given) == set(SEGMENTS)
    sk = skeleton_from_segments(1.8, given)
    assert segment_lengths(sk) == pytest.approx(given)
    # The hips stand on the legs: hip joint drop + thigh + shank + ankle height.
    assert sk.root_height == pytest.approx(0.05 * 1.8 / 1.75 + 0.47 + 0.41 + 0.08)
    assert sk.bone_length("RightLowerLeg") == pytest.approx(0.47)  # both sides
    assert sk.offsets[BONE_INDEX["RightUpperArm"], 0] == pytest.approx(-0.2)
    with pytest.raises(InputError, match="unknown body segment 'calf'"):
        skeleton_from_segments(1.75, {"calf": 0.4})
    with pytest.raises(InputError, match=r"thigh = 2\.0 m"):
        skeleton_from_segments(1.75, {"thigh": 2.0})


def test_imu_body_sizes_the_rig_and_says_how() -> None:
    cfg = parse_config({"imu": {"body": {"height_m": 1.62, "thigh_m": 0.41}}})
    sk = rig_skeleton(cfg)
    assert sk.height == 1.62 and sk.bone_length("LeftLowerLeg") == pytest.approx(0.41)
    assert sk.bone_length("LeftFoot") == pytest.approx(0.43 * 1.62 / 1.75)
    d = BodySpec(1.62, {"thigh": 0.41}).describe()
    assert d["source"] == "segments" and d["segments_m"] == {"thigh": 0.41}
    assert rig_skeleton(parse_config({})).offsets == pytest.approx(Skeleton.from_height(1.75).offsets)
    assert BodySpec().describe()["source"] == "height"


def _landmarks(skeleton: Skeleton) -> dict[str, float]:
    """Every segment as a tape measures it between the landmarks its help names, on the skeleton standing in the
    T-pose (joint positions from forward kinematics; the floor at y = 0)."""
    from mocapd.core.kinematics import Kinematics

    p = Kinematics(skeleton).forward(skeleton.rest_pose()).positions

    def d(a: str, b: str) -> float:
        return float(np.linalg.norm(p[BONE_INDEX[a]] - p[BONE_INDEX[b]]))

    hip_centre = (p[BONE_INDEX["LeftUpperLeg"]] + p[BONE_INDEX["RightUpperLeg"]]) / 2
    return {
        "hip_width": d("LeftUpperLeg", "RightUpperLeg"),
        "thigh": d("LeftUpperLeg", "LeftLowerLeg"),
        "shank": d("LeftLowerLeg", "LeftFoot"),
        "foot": d("LeftFoot", "LeftToes"),
        "ankle_height": float(p[BONE_INDEX["LeftFoot"], 1]),
        "torso": float(np.linalg.norm(p[BONE_INDEX["Neck"]] - hip_centre)),
        "shoulder_width": d("LeftUpperArm", "RightUpperArm"),
        "upper_arm": d("LeftUpperArm", "LeftLowerArm"),
        "forearm": d("LeftLowerArm", "LeftHand"),
    }


def test_a_skeleton_built_from_tape_measurements_round_trips_through_its_landmarks() -> None:
    """Issue 42, friction 6: ``--torso``'s help says "hip joint centre to the base of the neck" and the code measured
    from the Hips joint, ~5 cm higher: a tape measurement entered as the help says made the trunk 5 cm too long. Each
    segment's help names its landmarks, and the skeleton built from lengths measured between them has them."""
    given = {"hip_width": 0.21, "thigh": 0.47, "shank": 0.41, "foot": 0.15, "ankle_height": 0.08, "torso": 0.55,
             "shoulder_width": 0.4, "upper_arm": 0.31, "forearm": 0.27}  # fmt: skip
    for height in (1.55, 1.8):
        for one, length in given.items():  # each alone, then all together
            assert _landmarks(skeleton_from_segments(height, {one: length}))[one] == pytest.approx(length)
        assert _landmarks(skeleton_from_segments(height, given)) == pytest.approx(given)
        assert _landmarks(Skeleton.from_height(height)) == pytest.approx(default_lengths(height))
    assert "hip joint centres to the base of the neck" in SEGMENTS["torso"]
