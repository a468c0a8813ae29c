"""Pure post-processing of pose detectors: letterbox geometry, YOLO-pose decoding, NMS."""

from __future__ import annotations

import numpy as np
import pytest

from mocapd.core.pose2d import (
    PoseDetections,
    box_iou,
    decode_yolo_pose,
    detections_to_source,
    encode_yolo_pose,
    fitted_input_size,
    letterbox_geometry,
    nms,
)
from mocapd.errors import InputError


def _random_people(rng: np.random.Generator, n: int, k: int, w: float, h: float) -> PoseDetections:
    x0 = rng.uniform(0, w * 0.6, n)
    y0 = rng.uniform(0, h * 0.4, n)
    bw = rng.uniform(40, w * 0.3, n)
    bh = rng.uniform(100, h * 0.5, n)
    boxes = np.stack([x0, y0, x0 + bw, y0 + bh], axis=1)
    kp = np.empty((n, k, 3))
    kp[..., 0] = x0[:, None] + rng.uniform(0, 1, (n, k)) * bw[:, None]
    kp[..., 1] = y0[:, None] + rng.uniform(0, 1, (n, k)) * bh[:, None]
    kp[..., 2] = rng.uniform(0, 1, (n, k))
    return PoseDetections(boxes, rng.uniform(0.5, 0.99, n), kp)


@pytest.mark.parametrize(("sw", "sh"), [(1088, 1920), (1920, 1080), (640, 640), (100, 37), (4000, 30)])
def test_letterbox_fits_and_round_trips(sw: int, sh: int) -> None:
    lb = letterbox_geometry(sw, sh, 640, 640)
    assert lb.new_w <= 640 and lb.new_h <= 640
    assert max(lb.new_w, lb.new_h) == 640  # the long side fills the model input
    assert lb.pad_x + lb.new_w <= 640 and lb.pad_y + lb.new_h <= 640
    corners = np.array([[0.0, 0.0], [sw, sh]])
    m = lb.to_model(corners)
    np.testing.assert_allclose(m[0], [lb.pad_x, lb.pad_y])
    np.testing.assert_allclose(m[1], [lb.pad_x + lb.new_w, lb.pad_y + lb.new_h])
    pts = np.random.default_rng(0).uniform(0, 1, (50, 2)) * [sw, sh]
    np.testing.assert_allclose(lb.to_source(lb.to_model(pts)), pts, atol=1e-9)


def test_letterbox_portrait_demo_size_is_centred() -> None:
    lb = letterbox_geometry(1088, 1920, 640, 640)
    assert (lb.new_w, lb.new_h) == (363, 640)
    assert (lb.pad_x, lb.pad_y) == (138.0, 0.0)
    assert lb.sx == pytest.approx(363 / 1088) and lb.sy == pytest.approx(1 / 3)


def test_letterbox_rejects_empty_sizes() -> None:
    with pytest.raises(InputError):
        letterbox_geometry(0, 10, 640, 640)


def test_decode_recovers_people_through_letterbox_and_back() -> None:
    rng = np.random.default_rng(1)
    src = _random_people(rng, 4, 17, 1088, 1920)
    # Keep them apart so NMS keeps all four.
    src = PoseDetections(src.boxes * 0.2 + np.arange(4)[:, None] * [250, 0, 250, 0], src.scores, src.keypoints)
    src.keypoints[..., 0] = src.keypoints[..., 0] * 0.2 + np.arange(4)[:, None] * 250
    src.keypoints[..., 1] *= 0.2
    lb = letterbox_geometry(1088, 1920, 640, 640)
    in_model = src.transformed(lb.sx, lb.sy, lb.pad_x, lb.pad_y)
    raw = encode_yolo_pose(in_model, 8400, rng).astype(np.float32)
    det = detections_to_source(decode_yolo_pose(raw, 17, score_threshold=0.25), lb)
    assert len(det) == 4
    order = np.argsort(-src.scores)
    np.testing.assert_allclose(det.boxes, src.boxes[order], atol=1e-3)
    np.testing.assert_allclose(det.keypoints[..., :2], src.keypoints[order, :, :2], atol=1e-3)
    np.testing.assert_allclose(det.keypoints[..., 2], src.keypoints[order, :, 2], atol=1e-6)
    np.testing.assert_allclose(det.scores, src.scores[order], atol=1e-6)


def test_decode_drops_low_scores_and_duplicates() -> None:
    rng = np.random.default_rng(2)
    kp = np.zeros((3, 17, 3))
    boxes = np.array([[10, 10, 110, 310], [12, 8, 112, 305], [300, 10, 400, 300]], dtype=float)
    det = PoseDetections(boxes, np.array([0.9, 0.8, 0.2]), kp)
    raw = encode_yolo_pose(det, 100, rng)
    out = decode_yolo_pose(raw, 17, score_threshold=0.25, iou_threshold=0.65)
    assert len(out) == 1  # the duplicate is suppressed, the 0.2 one is below threshold
    np.testing.assert_allclose(out.boxes[0], boxes[0])
    assert len(decode_yolo_pose(raw, 17, score_threshold=0.95)) == 0


def test_decode_rejects_wrong_shape() -> None:
    with pytest.raises(InputError, match="56"):
        decode_yolo_pose(np.zeros((1, 55, 10)), 17)
    with pytest.raises(InputError, match="batch"):
        decode_yolo_pose(np.zeros((2, 56, 10)), 17)


def test_nms_keeps_best_of_overlapping_and_all_disjoint() -> None:
    boxes = np.array([[0, 0, 10, 10], [1, 1, 11, 11], [20, 20, 30, 30], [0, 0, 10, 10.5]], dtype=float)
    scores = np.array([0.5, 0.9, 0.7, 0.4])
    keep = nms(boxes, scores, 0.5)
    assert keep.tolist() == [1, 2]
    assert nms(boxes, scores, 0.99).tolist() == [1, 2, 0, 3]
    assert nms(boxes, scores, 0.5, max_keep=1).tolist() == [1]
    assert nms(np.zeros((0, 4)), np.zeros(0), 0.5).tolist() == []


def test_nms_rejects_mismatched_inputs() -> None:
    with pytest.raises(InputError):
        nms(np.zeros((3, 4)), np.zeros(2), 0.5)


def test_box_iou_values() -> None:
    a = np.array([[0, 0, 10, 10]], dtype=float)
    b = np.array([[0, 0, 10, 10], [5, 0, 15, 10], [20, 20, 30, 30], [0, 0, 0, 0]], dtype=float)
    np.testing.assert_allclose(box_iou(a, b)[0], [1.0, 50 / 150, 0.0, 0.0])


@pytest.mark.parametrize(
    ("src", "fitted"),
    [
        ((544, 960), (384, 640)),  # 9:16 portrait (the demo's cameras)
        ((1920, 1080), (640, 384)),  # 16:9 landscape
        ((1280, 1024), (640, 512)),  # 5:4 machine-vision sensor
        ((1280, 960), (640, 512)),  # 4:3
        ((800, 800), (640, 640)),  # square: nothing to trim
        ((640, 600), (640, 640)),  # 40 rows of padding: less than one step of 64
    ],
)
def test_fitted_input_trims_whole_double_strides_of_padding(src: tuple[int, int], fitted: tuple[int, int]) -> None:
    assert fitted_input_size(*src, 640, 640) == fitted
    full, fit = letterbox_geometry(*src, 640, 640), letterbox_geometry(*src, *fitted)
    # Same scale, the image inside the fitted input, and its offset moved by whole strides only.
    assert (fit.sx, fit.sy, fit.new_w, fit.new_h) == (full.sx, full.sy, full.new_w, full.new_h)
    assert fit.new_w <= fitted[0] and fit.new_h <= fitted[1]
    assert (full.pad_x - fit.pad_x) % 32 == 0 and (full.pad_y - fit.pad_y) % 32 == 0
