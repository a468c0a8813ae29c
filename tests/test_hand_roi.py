"""The hand crop's geometry (mocapd.core.hand_roi): MediaPipe's hand ROI from BlazePose's wrist, index and pinky,
the forearm fallback for COCO-17, both sides of a person, and the decoding of the hand model's rows."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mocapd.core.hand_roi import (
    BLAZEPOSE_SCALE,
    BLAZEPOSE_SHIFT,
    FOREARM_CENTRE,
    FOREARM_SIDE,
    HAND_INPUT_SIZE,
    REFINE_SCALE,
    REFINE_SHIFT,
    UPPER_ARM_FLOOR,
    decode_hands,
    hand_roi_from_blazepose,
    hand_roi_from_forearm,
    hand_roi_from_hand,
    hand_rois,
    hand_span,
)
from mocapd.core.keypoints import BLAZEPOSE33_FORMAT as BLAZEPOSE33
from mocapd.core.keypoints import COCO17_FORMAT as COCO17
from mocapd.core.landmark_roi import LandmarkRoi, normalized_angle


def test_mediapipes_hand_box_from_wrist_index_and_pinky() -> None:
    # A hand hanging straight down (fingers towards +y on screen): wrist at (100, 100), index knuckle (95, 160),
    # pinky knuckle (125, 157). The middle finger is (2 index + pinky) / 3 = (105, 159).
    roi = hand_roi_from_blazepose(np.array([100.0, 100.0]), np.array([95.0, 160.0]), np.array([125.0, 157.0]))
    assert roi is not None
    reach = math.hypot(5.0, 59.0)
    assert roi.size == pytest.approx(2.0 * reach * BLAZEPOSE_SCALE)
    # Centre: the middle finger moved shift x side further from the wrist.
    along = np.array([5.0, 59.0]) / reach
    assert (roi.cx, roi.cy) == pytest.approx(tuple(np.array([105.0, 159.0]) + BLAZEPOSE_SHIFT * roi.size * along))
    # Fingers down on screen → the crop is turned half a turn (its up is the image's down), tilted by the 5 px.
    assert abs(normalized_angle(roi.rotation - math.pi - math.atan2(-5.0, 59.0))) < 1e-9


@pytest.mark.parametrize("degrees", [0.0, 45.0, 90.0, -135.0, 180.0])
def test_the_hand_crop_puts_the_fingers_up(degrees: float) -> None:
    a = math.radians(degrees)
    up = np.array([math.sin(a), -math.cos(a)])  # the hand pointing `degrees` clockwise from the image's up
    across = np.array([-up[1], up[0]])
    wrist = np.array([300.0, 400.0])
    index, pinky = wrist + 60 * up - 12 * across, wrist + 55 * up + 18 * across
    roi = hand_roi_from_blazepose(wrist, index, pinky)
    assert roi is not None
    crop = roi.to_crop(np.stack([wrist, (2 * index + pinky) / 3]), HAND_INPUT_SIZE)
    # In the crop the middle finger is straight above the wrist, both on the vertical centre line, and inside.
    assert crop[0, 0] == pytest.approx(HAND_INPUT_SIZE / 2) and crop[1, 0] == pytest.approx(HAND_INPUT_SIZE / 2)
    assert crop[1, 1] < crop[0, 1]
    assert crop[1, 1] > 0 and crop[0, 1] < HAND_INPUT_SIZE


def test_a_collapsed_hand_gets_no_crop() -> None:
    p = np.array([10.0, 10.0])
    assert hand_roi_from_blazepose(p, p + 0.5, p - 0.5) is None
    assert hand_roi_from_forearm(None, p, p) is None


def test_the_forearm_places_the_hand_beyond_the_wrist() -> None:
    elbow, wrist = np.array([200.0, 300.0]), np.array([200.0, 400.0])  # forearm pointing down, 100 px
    roi = hand_roi_from_forearm(np.array([200.0, 200.0]), elbow, wrist)
    assert roi is not None
    assert (roi.cx, roi.cy) == pytest.approx((200.0, 400.0 + FOREARM_CENTRE * 100.0))
    assert roi.size == pytest.approx(FOREARM_SIDE * 100.0)
    assert abs(normalized_angle(roi.rotation - math.pi)) < 1e-9
    # A forearm foreshortened towards the camera (20 px) keeps a crop sized from the upper arm (100 px).
    short = hand_roi_from_forearm(np.array([200.0, 200.0]), elbow, np.array([200.0, 320.0]))
    assert short is not None
    assert short.size == pytest.approx(FOREARM_SIDE * UPPER_ARM_FLOOR * 100.0)
    assert short.cy == pytest.approx(320.0 + FOREARM_CENTRE * UPPER_ARM_FLOOR * 100.0)
    # Without the shoulder the forearm alone sizes it.
    alone = hand_roi_from_forearm(None, elbow, np.array([200.0, 320.0]))
    assert alone is not None and alone.size == pytest.approx(FOREARM_SIDE * 20.0)


def _blazepose_arms() -> np.ndarray:
    kp = np.zeros((33, 3))
    for name, xy in (("left_shoulder", (400, 200)), ("left_elbow", (420, 320)), ("left_wrist", (430, 430)),
                     ("left_index", (440, 490)), ("left_pinky", (455, 480)), ("right_shoulder", (250, 200)),
                     ("right_elbow", (230, 320)), ("right_wrist", (220, 430)), ("right_index", (210, 490)),
                     ("right_pinky", (195, 480))):  # fmt: skip
        kp[BLAZEPOSE33.index(name)] = (*xy, 0.9)
    return kp


def test_both_hands_of_a_blazepose_person_left_then_right() -> None:
    kp = _blazepose_arms()
    left, right = hand_rois(kp, BLAZEPOSE33.keypoints)
    assert left is not None and right is not None
    assert left.cx > 400 and right.cx < 250  # each crop at its own arm's hand (the image's right is the body's left)
    expect = hand_roi_from_blazepose(kp[15, :2], kp[19, :2], kp[17, :2])
    assert left == expect
    # An unseen pinky: that hand falls back to the forearm.
    kp[BLAZEPOSE33.index("right_pinky"), 2] = 0.1
    _, fallback = hand_rois(kp, BLAZEPOSE33.keypoints)
    assert fallback == hand_roi_from_forearm(kp[12, :2], kp[14, :2], kp[16, :2])
    # No wrist: no crop.
    kp[BLAZEPOSE33.index("left_wrist"), 2] = 0.0
    assert hand_rois(kp, BLAZEPOSE33.keypoints)[0] is None


def test_coco17_hands_come_from_the_forearms() -> None:
    kp = np.zeros((17, 3))
    for name, xy in (("left_shoulder", (400, 200)), ("left_elbow", (420, 320)), ("left_wrist", (430, 430)),
                     ("right_elbow", (230, 320)), ("right_wrist", (220, 430))):  # fmt: skip
        kp[COCO17.index(name)] = (*xy, 0.8)
    left, right = hand_rois(kp, COCO17.keypoints)
    assert left == hand_roi_from_forearm(kp[5, :2], kp[7, :2], kp[9, :2])
    assert right == hand_roi_from_forearm(None, kp[8, :2], kp[10, :2])  # the right shoulder was not seen
    with pytest.raises(ValueError, match="shape"):
        hand_rois(kp[:16], COCO17.keypoints)


def test_decoding_maps_crop_pixels_back_to_the_source() -> None:
    rois = [LandmarkRoi(500.0, 300.0, 112.0, 0.0), LandmarkRoi(100.0, 100.0, 224.0, math.pi / 2)]
    marks = np.zeros((2, 63))
    marks[:, 0:3] = (112.0, 112.0, 5.0)  # the wrist at the crop centre
    marks[:, 3:6] = (224.0, 0.0, 0.0)  # the thumb's first point at the crop's top-right corner
    out = decode_hands(marks, np.array([0.9, 1.7]), rois)
    assert out.shape == (2, 21, 3)
    assert out[0, 0, :2] == pytest.approx((500.0, 300.0)) and out[1, 0, :2] == pytest.approx((100.0, 100.0))
    assert out[0, 1, :2] == pytest.approx((556.0, 244.0))  # half the scale: 112 crop px are 56 source px
    # A quarter turn clockwise on screen: the crop's top-right corner (+x, -y) lands at source (+x, +y).
    assert out[1, 1, :2] == pytest.approx((212.0, 212.0))
    assert (out[0, :, 2] == 0.9).all() and (out[1, :, 2] == 1.0).all()  # clipped to [0, 1]


def test_hand_span_is_the_longer_side_of_the_box() -> None:
    hand = np.zeros((21, 3))
    hand[:, 0] = np.linspace(10, 40, 21)
    hand[:, 1] = np.linspace(0, 70, 21)
    assert hand_span(hand) == pytest.approx(70.0)


def _upright_hand(wrist: tuple[float, float], length: float) -> np.ndarray:
    """21 points of an open hand, fingers straight up on screen (-y), palm ``length`` px from wrist to knuckles."""
    w = np.array(wrist)
    pts = np.zeros((21, 3))
    pts[0, :2] = w
    for f, dx in enumerate((-0.5, -0.25, 0.0, 0.2, 0.4)):  # thumb, index, middle, ring, pinky
        for j in range(4):
            reach = (0.35 + 0.2 * j) if f == 0 else (1.0 + 0.3 * j)
            pts[1 + 4 * f + j, :2] = w + length * np.array([dx * (1.3 if f == 0 else 1.0), -reach])
    pts[:, 2] = 0.9
    return pts


def test_the_tracking_crop_from_a_hands_own_points() -> None:
    hand = _upright_hand((400.0, 500.0), 50.0)
    roi = hand_roi_from_hand(hand)
    assert roi is not None
    # Fingers up: no turn. The palm's box (wrist .. the PIP joints, 65 px tall; thumb to pinky, 52.5 px wide), moved
    # 0.1 of its height towards the fingers, twice its longer side.
    assert abs(normalized_angle(roi.rotation)) < 0.1
    assert roi.size == pytest.approx(REFINE_SCALE * 65.0, rel=0.05)
    assert roi.cy < 500.0 - 65.0 / 2 and roi.cy == pytest.approx(500.0 - 65.0 / 2 - REFINE_SHIFT * 65.0, abs=3.0)
    # The whole hand, fingertips included, lies inside the crop.
    crop = roi.to_crop(hand[:, :2], HAND_INPUT_SIZE)
    assert (crop > 0).all() and (crop < HAND_INPUT_SIZE).all()
    # Turned a quarter clockwise on screen, the crop turns with it.
    c, s = 0.0, 1.0
    turned = hand.copy()
    turned[:, :2] = (hand[:, :2] - (400.0, 500.0)) @ np.array([[c, s], [-s, c]]) + (400.0, 500.0)
    roi90 = hand_roi_from_hand(turned)
    assert roi90 is not None and abs(normalized_angle(roi90.rotation - math.pi / 2)) < 0.1
    assert roi90.size == pytest.approx(roi.size)
    assert hand_roi_from_hand(np.zeros((21, 3))) is None
