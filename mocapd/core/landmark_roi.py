"""Where a BlazePose landmark model looks: one aligned square crop per person and view, and back to source pixels.

MediaPipe's pose pipeline (``pose_landmark_by_roi``, ``pose_detection_to_roi``) places the landmark model's input on
a *rotated* square: centred on the mid-hip, turned so that the mid-hip → mid-shoulder direction points up in the
crop, as large as the circle about the mid-hip that holds the whole body, enlarged by 1.25
(``RectTransformationCalculator scale_x = scale_y = 1.25``, ``square_long``), resampled to 256 x 256. Its own person
detector predicts the mid-hip, the circle and the incline; here YOLO's COCO-17 keypoints give them
(:func:`roi_from_coco17`): the hips' and shoulders' midpoints and the farthest confident keypoint.

The model's 33 landmarks come out in crop pixels; :meth:`LandmarkRoi.to_source` maps them back exactly as
MediaPipe's ``LandmarkProjectionCalculator`` does (rotate about the crop centre, scale, translate). Coordinates
are continuous (a pixel's centre at ``i + 0.5``) on both sides; :meth:`LandmarkRoi.sampling_matrix` gives OpenCV's
``warpAffine`` the pixel-index form.

Pure geometry: no model, no image library.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mocapd.core.keypoints import COCO17_FORMAT

FloatArray = NDArray[np.float64]

INPUT_SIZE = 256
"""Side of the landmark models' square input (pixels)."""
ROI_SCALE = 1.25
"""MediaPipe's enlargement of the body circle's square (``pose_detection_to_roi``)."""
BODY_CIRCLE_MARGIN = 1.15
"""The farthest COCO-17 keypoint is an eye or an ankle: the top of the head and the toes lie beyond it. The
margin stands in for the part of MediaPipe's body circle that its detector sees and YOLO's keypoints do not."""
MIN_CONFIDENCE = 0.3
"""A YOLO keypoint takes part in placing the crop when its confidence is at least this."""

_HIPS = (COCO17_FORMAT.index("left_hip"), COCO17_FORMAT.index("right_hip"))
_SHOULDERS = (COCO17_FORMAT.index("left_shoulder"), COCO17_FORMAT.index("right_shoulder"))


@dataclass(frozen=True)
class LandmarkRoi:
    """A rotated square in source pixels.

    Attributes
    ----------
    cx, cy : float
        Centre (source pixels).
    size : float
        Side (source pixels).
    rotation : float
        Radians in [-pi, pi): the crop's axes are the image's turned by this (clockwise on screen, y down), so the
        crop's up is the body's up.
    """

    cx: float
    cy: float
    size: float
    rotation: float

    def crop_to_source(self, input_size: int = INPUT_SIZE) -> FloatArray:
        """The affine map of continuous crop coordinates to continuous source ones, shape (2, 3)."""
        c, s = math.cos(self.rotation), math.sin(self.rotation)
        k = self.size / input_size
        a = np.array([[c * k, -s * k], [s * k, c * k]])
        # crop (input_size / 2, input_size / 2) is the centre.
        b = np.array([self.cx, self.cy]) - a @ np.array([input_size / 2, input_size / 2])
        return np.hstack([a, b[:, None]])

    def sampling_matrix(self, input_size: int = INPUT_SIZE) -> FloatArray:
        """The crop-pixel-index → source-pixel-index map, shape (2, 3): what ``cv2.warpAffine`` takes with
        ``WARP_INVERSE_MAP`` (it samples pixel ``i`` of the crop at source index ``M @ (i, 1)``)."""
        m = self.crop_to_source(input_size)
        a, b = m[:, :2], m[:, 2]
        # index i has its centre at i + 0.5 on both sides.
        return np.hstack([a, (b + a @ np.array([0.5, 0.5]) - 0.5)[:, None]])

    def to_source(self, points: FloatArray, input_size: int = INPUT_SIZE) -> FloatArray:
        """Crop points (continuous crop pixels), shape (..., 2) → source pixels, shape (..., 2)."""
        m = self.crop_to_source(input_size)
        pts = np.asarray(points, dtype=np.float64)
        return np.asarray(pts @ m[:, :2].T + m[:, 2], dtype=np.float64)

    def to_crop(self, points: FloatArray, input_size: int = INPUT_SIZE) -> FloatArray:
        """Source pixels, shape (..., 2) → continuous crop pixels, shape (..., 2) (the inverse of
        :meth:`to_source`)."""
        m = self.crop_to_source(input_size)
        inv = np.linalg.inv(m[:, :2])
        pts = np.asarray(points, dtype=np.float64) - m[:, 2]
        return np.asarray(pts @ inv.T, dtype=np.float64)


def normalized_angle(angle: float) -> float:
    """``angle`` wrapped to [-pi, pi) (MediaPipe's ``NormalizeRadians``)."""
    return angle - 2.0 * math.pi * math.floor((angle + math.pi) / (2.0 * math.pi))


def roi_rotation(hip: FloatArray, shoulder: FloatArray) -> float:
    """MediaPipe's ``ComputeRotation`` with target angle 90°: the turn that puts ``shoulder`` straight above
    ``hip`` (source pixels, y down), radians in [-pi, pi)."""
    dx, dy = float(shoulder[0] - hip[0]), float(shoulder[1] - hip[1])
    return normalized_angle(math.pi / 2.0 - math.atan2(-dy, dx))


def _mid(kp: FloatArray, pair: tuple[int, int], min_confidence: float) -> FloatArray | None:
    ok = [i for i in pair if kp[i, 2] >= min_confidence]
    if not ok:
        return None
    return np.asarray(kp[ok, :2].mean(axis=0), dtype=np.float64)


def roi_from_coco17(
    keypoints: FloatArray,
    *,
    min_confidence: float = MIN_CONFIDENCE,
    scale: float = ROI_SCALE,
    margin: float = BODY_CIRCLE_MARGIN,
) -> LandmarkRoi | None:
    """The landmark crop of one person from their COCO-17 keypoints, or None when a hip or a shoulder is missing.

    Parameters
    ----------
    keypoints : array, shape (17, 3)
        x, y (source pixels) and confidence of each COCO-17 keypoint.

    Returns
    -------
    LandmarkRoi or None
        Centre at the mid-hip (the mean of the confident hips), rotated so that the mid-shoulder is straight up,
        side ``2 * scale * margin * r`` with ``r`` the distance from the mid-hip to the farthest confident keypoint.
    """
    kp = np.asarray(keypoints, dtype=np.float64)
    if kp.shape != (COCO17_FORMAT.n_keypoints, 3):
        raise ValueError(f"COCO-17 keypoints must have shape (17, 3), got {kp.shape}")
    hip = _mid(kp, _HIPS, min_confidence)
    shoulder = _mid(kp, _SHOULDERS, min_confidence)
    if hip is None or shoulder is None:
        return None
    seen = kp[kp[:, 2] >= min_confidence, :2]
    radius = float(np.max(np.linalg.norm(seen - hip, axis=1))) * margin
    if not radius > 0.0:
        return None
    return LandmarkRoi(float(hip[0]), float(hip[1]), 2.0 * scale * radius, roi_rotation(hip, shoulder))


N_LANDMARKS = 33
"""BlazePose's landmarks (:data:`mocapd.core.keypoints.BLAZEPOSE33_FORMAT`); the model outputs 39, the last 6
being its own ROI helpers."""
_MODEL_LANDMARKS = 39
_VALUES = 5  # x, y, z (crop pixels), visibility and presence (logits)


def _sigmoid(x: FloatArray) -> FloatArray:
    return np.asarray(0.5 * (1.0 + np.tanh(0.5 * x)), dtype=np.float64)  # tanh form: no overflow warning


def decode_landmarks(raw: NDArray[np.floating], rois: list[LandmarkRoi], input_size: int = INPUT_SIZE) -> FloatArray:
    """The landmark model's first output → keypoints in source pixels.

    Parameters
    ----------
    raw : array, shape (n, 195)
        39 x (x, y, z, visibility logit, presence logit) per crop, x and y in crop pixels (MediaPipe's
        ``TensorsToLandmarksCalculator`` input).
    rois : list of LandmarkRoi, length n
        The crop of each row.

    Returns
    -------
    array, shape (n, 33, 3)
        x, y (source pixels) and confidence: sigmoid(visibility) x sigmoid(presence), MediaPipe's likelihoods that
        the point is unoccluded and inside the image.
    """
    out = np.asarray(raw, dtype=np.float64).reshape(len(rois), _MODEL_LANDMARKS, _VALUES)[:, :N_LANDMARKS]
    result = np.empty((len(rois), N_LANDMARKS, 3))
    for i, roi in enumerate(rois):
        result[i, :, :2] = roi.to_source(out[i, :, :2], input_size)
    result[:, :, 2] = _sigmoid(out[:, :, 3]) * _sigmoid(out[:, :, 4])
    return result
