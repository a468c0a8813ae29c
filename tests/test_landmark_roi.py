"""The landmark crop's geometry (mocapd.core.landmark_roi): MediaPipe's ROI from COCO-17 keypoints, the crop ↔ source
maps, the sampling matrix OpenCV uses, and the decoding of the model's rows."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from mocapd.core.keypoints import COCO17_FORMAT as COCO17
from mocapd.core.landmark_roi import (
    INPUT_SIZE,
    ROI_SCALE,
    LandmarkRoi,
    decode_landmarks,
    normalized_angle,
    roi_from_coco17,
    roi_rotation,
)


def _person(hip: tuple[float, float], up: tuple[float, float], height: float) -> np.ndarray:
    """COCO-17 keypoints of a straight person: mid-hip at ``hip``, body along the unit vector ``up`` (image y down),
    shoulders 0.3 and the eyes 0.45 of ``height`` above the hips, ankles 0.45 below."""
    h, u = np.array(hip), np.array(up) / np.linalg.norm(up)
    side = np.array([-u[1], u[0]])
    kp = np.zeros((17, 3))
    for name, along, across in (("nose", 0.43, 0.0), ("left_eye", 0.45, 0.02), ("right_eye", 0.45, -0.02),
                                ("left_shoulder", 0.3, 0.1), ("right_shoulder", 0.3, -0.1), ("left_hip", 0.0, 0.06),
                                ("right_hip", 0.0, -0.06), ("left_knee", -0.25, 0.06), ("right_knee", -0.25, -0.06),
                                ("left_ankle", -0.45, 0.06), ("right_ankle", -0.45, -0.06)):  # fmt: skip
        kp[COCO17.index(name)] = (*(h + height * (along * u + across * side)), 0.9)
    return kp


def test_an_upright_person_gets_an_unrotated_crop_centred_on_the_hips() -> None:
    roi = roi_from_coco17(_person((500.0, 600.0), (0.0, -1.0), 800.0))
    assert roi is not None
    assert roi.rotation == pytest.approx(0.0, abs=1e-12)
    assert (roi.cx, roi.cy) == pytest.approx((500.0, 600.0))
    # The farthest keypoint (an ankle or an eye, 0.45 x 800 = 360 px and a bit) sets the circle; the side is its
    # diameter x the margin x MediaPipe's 1.25: the whole body fits with room.
    assert roi.size > 2 * 360 * ROI_SCALE
    corners = roi.to_source(np.array([[0.0, 0.0], [INPUT_SIZE, INPUT_SIZE]]))
    assert corners[0, 1] < 600 - 0.45 * 800 and corners[1, 1] > 600 + 0.45 * 800


@pytest.mark.parametrize("degrees", [0.0, 30.0, 90.0, -120.0, 180.0])
def test_the_crop_turns_the_body_upright(degrees: float) -> None:
    a = math.radians(degrees)
    up = (math.sin(a), -math.cos(a))  # the body leaning `degrees` clockwise on screen
    kp = _person((400.0, 400.0), up, 600.0)
    roi = roi_from_coco17(kp)
    assert roi is not None
    assert normalized_angle(roi.rotation - a) == pytest.approx(0.0, abs=1e-9)
    crop = roi.to_crop(kp[:, :2])
    # In the crop the shoulders are straight above the hips, the ankles straight below, left and right level.
    hips, shoulders, ankles = (
        (crop[COCO17.index(f"left_{j}")] + crop[COCO17.index(f"right_{j}")]) / 2 for j in ("hip", "shoulder", "ankle")
    )
    assert hips == pytest.approx((INPUT_SIZE / 2, INPUT_SIZE / 2))
    assert shoulders[0] == pytest.approx(hips[0]) and shoulders[1] < hips[1]
    assert ankles[0] == pytest.approx(hips[0]) and ankles[1] > hips[1]


def test_rotation_is_mediapipes_compute_rotation() -> None:
    # target angle 90 deg: shoulders straight up → 0; to the right (screen) → +90 deg; down → -180 deg.
    assert roi_rotation(np.array([0.0, 0.0]), np.array([0.0, -1.0])) == pytest.approx(0.0)
    assert roi_rotation(np.array([0.0, 0.0]), np.array([1.0, 0.0])) == pytest.approx(math.pi / 2)
    assert roi_rotation(np.array([0.0, 0.0]), np.array([0.0, 1.0])) == pytest.approx(-math.pi)
    assert normalized_angle(3 * math.pi) == pytest.approx(-math.pi)


def test_no_crop_without_a_hip_or_a_shoulder() -> None:
    kp = _person((300.0, 300.0), (0.0, -1.0), 500.0)
    kp[[COCO17.index("left_hip"), COCO17.index("right_hip")], 2] = 0.1
    assert roi_from_coco17(kp) is None
    kp = _person((300.0, 300.0), (0.0, -1.0), 500.0)
    kp[[COCO17.index("left_shoulder"), COCO17.index("right_shoulder")], 2] = 0.0
    assert roi_from_coco17(kp) is None
    # One hip and one shoulder suffice.
    kp[COCO17.index("left_shoulder"), 2] = 0.9
    kp[COCO17.index("right_hip"), 2] = 0.0
    assert roi_from_coco17(kp) is not None
    with pytest.raises(ValueError, match=r"\(17, 3\)"):
        roi_from_coco17(np.zeros((33, 3)))


def test_to_crop_inverts_to_source() -> None:
    roi = LandmarkRoi(321.5, 210.25, 480.0, 0.7)
    pts = np.random.default_rng(1).uniform(-50, 300, (20, 2))
    np.testing.assert_allclose(roi.to_source(roi.to_crop(pts)), pts, atol=1e-9)


@pytest.mark.parametrize("rotation", [0.0, 0.4, -2.5])
def test_opencv_samples_the_source_where_to_source_says(rotation: float) -> None:
    # A bright dot in the source image lands in the crop at to_crop(dot) (to a fraction of a crop pixel): the
    # sampling matrix (pixel indices, centres at i + 0.5) and the continuous map agree.
    spike = np.zeros((600, 800), np.float32)
    dot = np.array([430.5, 260.5])  # the centre of pixel (430, 260)
    spike[260, 430] = 1.0
    img = cv2.GaussianBlur(spike, (0, 0), 6.0)
    roi = LandmarkRoi(400.0, 300.0, 300.0, rotation)  # 300 source px on 256 crop px
    crop = cv2.warpAffine(img, roi.sampling_matrix(), (INPUT_SIZE, INPUT_SIZE),
                          flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)  # fmt: skip
    ys, xs = np.mgrid[0:INPUT_SIZE, 0:INPUT_SIZE]
    w = crop / crop.sum()
    found = np.array([(w * (xs + 0.5)).sum(), (w * (ys + 0.5)).sum()])
    np.testing.assert_allclose(found, roi.to_crop(dot), atol=0.05)


def test_decode_maps_rows_to_source_pixels_with_sigmoid_confidences() -> None:
    rois = [LandmarkRoi(100.0, 200.0, 512.0, 0.0), LandmarkRoi(50.0, 60.0, 256.0, math.pi / 2)]
    raw = np.zeros((2, 39, 5), np.float32)
    raw[:, :, :2] = INPUT_SIZE / 2  # every landmark at the crop centre ...
    raw[0, 0, :2] = (INPUT_SIZE, INPUT_SIZE / 2)  # ... but the first one at the right edge's middle
    raw[1, 0, :2] = (INPUT_SIZE, INPUT_SIZE / 2)
    raw[0, :, 3:] = 20.0  # visible and present
    raw[1, 5, 3] = -20.0  # occluded
    out = decode_landmarks(raw.reshape(2, 195), rois)
    assert out.shape == (2, 33, 3)
    np.testing.assert_allclose(out[0, 1, :2], (100.0, 200.0))
    np.testing.assert_allclose(out[0, 0, :2], (100.0 + 256.0, 200.0))  # half of 512 to the right
    # Turned 90 deg clockwise on screen: the crop's right is the source's down.
    np.testing.assert_allclose(out[1, 0, :2], (50.0, 60.0 + 128.0), atol=1e-9)
    assert out[0, :, 2] == pytest.approx(1.0)
    assert out[1, 0, 2] == pytest.approx(0.25) and out[1, 5, 2] == pytest.approx(0.0, abs=1e-8)
