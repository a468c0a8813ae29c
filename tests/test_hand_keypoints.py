"""The hand keypoint set (issue 44): 21 named points per hand, both hands after the body's keypoints."""

from __future__ import annotations

import pytest

from mocapd.core.keypoints import (
    BLAZEPOSE33_FORMAT,
    BLAZEPOSE33_HANDS_FORMAT,
    COCO17_FORMAT,
    COCO17_HANDS_FORMAT,
    FINGERS,
    HAND21,
    HAND21_EDGES,
    HANDS42,
    hand_keypoint_names,
    keypoint_format,
)
from mocapd.core.lr_flips import lr_pairs
from mocapd.errors import ConfigError


def test_hand21_is_mediapipes_order() -> None:
    assert len(HAND21) == 21 and len(set(HAND21)) == 21
    assert HAND21[0] == "wrist" and HAND21[4] == "thumb_tip" and HAND21[8] == "index_finger_tip"
    assert HAND21[9] == "middle_finger_mcp" and HAND21[17] == "pinky_mcp" and HAND21[20] == "pinky_tip"
    assert [len(v) for v in FINGERS.values()] == [4, 4, 4, 4, 4]
    assert FINGERS["ring"] == ("ring_finger_mcp", "ring_finger_pip", "ring_finger_dip", "ring_finger_tip")
    # every point is on the drawn hand, and the edges form a tree (21 points, 20 edges) plus the palm's closing edge
    assert {i for e in HAND21_EDGES for i in e} == set(range(21)) and len(HAND21_EDGES) == 21


def test_per_person_names_carry_the_bodys_side() -> None:
    assert hand_keypoint_names("left")[0] == "left_hand_wrist"
    assert hand_keypoint_names("right")[20] == "right_hand_pinky_tip"
    assert (*hand_keypoint_names("left"), *hand_keypoint_names("right")) == HANDS42
    with pytest.raises(ConfigError, match="hand side"):
        hand_keypoint_names("middle")


@pytest.mark.parametrize(("body", "hands"), [(COCO17_FORMAT, COCO17_HANDS_FORMAT),
                                             (BLAZEPOSE33_FORMAT, BLAZEPOSE33_HANDS_FORMAT)])  # fmt: skip
def test_hand_formats_keep_the_body_columns(body: object, hands: object) -> None:
    from mocapd.core.keypoints import KeypointFormat

    assert isinstance(body, KeypointFormat) and isinstance(hands, KeypointFormat)
    assert keypoint_format(f"{body.name}_hands") is hands
    assert hands.keypoints[: body.n_keypoints] == body.keypoints
    assert hands.keypoints[body.n_keypoints :] == HANDS42
    assert hands.n_keypoints == body.n_keypoints + 42
    # The solver's view of the body is unchanged: the same targets in the same order (the hand points have none
    # until the finger bones exist).
    a, b = body.track_targets(), hands.track_targets()
    assert a.names == b.names and (a.bones == b.bones).all() and (a.offsets == b.offsets).all()
    assert set(hands.edges) >= set(body.edges)
    # left/right pairs find the hands' twins by name
    pairs = dict(lr_pairs(hands.keypoints))
    left_wrist = hands.keypoints.index("left_hand_wrist")
    assert hands.keypoints[pairs[left_wrist]] == "right_hand_wrist"


def test_unknown_format_names_the_hand_formats() -> None:
    with pytest.raises(ConfigError, match="blazepose33_hands"):
        keypoint_format("hands21")
