"""Where the hand landmark model looks: one aligned square crop per visible hand, from the body's keypoints.

MediaPipe's holistic pipeline places a hand's crop from the pose landmarks of that arm
(``HandDetectionsFromPoseToRectsCalculator``): the middle finger's knuckle estimated as ``(2 index + pinky) / 3``
of BlazePose's index and pinky points, the crop centred there, turned so that the wrist → middle-finger direction
points up in the crop (``ComputeRotation``, target 90°), its side twice the wrist → middle-finger distance. Holistic
then enlarges it 2.7× for a re-crop model that finds the hand again; mocapd has no re-crop model, so the crop goes
to the landmark model directly, enlarged by :data:`BLAZEPOSE_SCALE` and moved :data:`BLAZEPOSE_SHIFT` of its side
towards the fingertips (MediaPipe's own hand tracking places the landmark model's crop as twice the palm's box moved
0.1 of its side towards the fingers: ``hand_landmark_landmarks_to_roi``). Both constants were chosen on the Pose2Sim
demos (docs/detection.md, "Hand landmarks per person").

With COCO-17 (YOLO's keypoints: no point on the hand) the forearm stands in (:func:`hand_roi_from_forearm`): the
hand continues the elbow → wrist direction, its crop centred :data:`FOREARM_CENTRE` forearm lengths beyond the wrist
and :data:`FOREARM_SIDE` forearm lengths across. A forearm that points at the camera looks short; the upper arm's
length (:data:`UPPER_ARM_FLOOR` of it) is a floor for the crop's size.

The crops are :class:`~mocapd.core.landmark_roi.LandmarkRoi` squares (source pixels) and the landmarks map back with
its ``to_source`` at the hand model's input size (:data:`HAND_INPUT_SIZE`). Pure geometry: no model, no image
library.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mocapd.core.keypoints import HAND21, HAND_SIDES
from mocapd.core.landmark_roi import LandmarkRoi, roi_rotation

FloatArray = NDArray[np.float64]

HAND_INPUT_SIZE = 224
"""Side of the hand landmark model's square input (pixels)."""
BLAZEPOSE_SCALE = 1.75
"""The crop's side over MediaPipe's pose-derived hand box (twice the wrist → middle-finger distance)."""
BLAZEPOSE_SHIFT = 0.0
"""How far the crop's centre moves from the middle-finger estimate towards the fingertips, in crop sides."""
FOREARM_CENTRE = 0.45
"""Distance of the crop's centre beyond the wrist along the forearm, in forearm lengths (the middle knuckle lies about
0.4 of a forearm beyond the wrist)."""
FOREARM_SIDE = 1.0
"""The crop's side in forearm lengths (a hand is about 0.75 of one; the rest is room for a bent wrist)."""
UPPER_ARM_FLOOR = 0.8
"""The forearm length used is at least this share of the upper arm's (a forearm foreshortened towards the camera)."""
MIN_CONFIDENCE = 0.3
"""A body keypoint takes part in placing a crop when its confidence is at least this."""
MIN_SIDE_PX = 8.0
"""A crop smaller than this (source pixels) is not made: no hand model sees anything in it."""


def _shifted(centre: FloatArray, up: FloatArray, side: float, shift: float) -> FloatArray:
    return np.asarray(centre + shift * side * up, dtype=np.float64)


def hand_roi_from_blazepose(
    wrist: FloatArray,
    index: FloatArray,
    pinky: FloatArray,
    *,
    scale: float = BLAZEPOSE_SCALE,
    shift: float = BLAZEPOSE_SHIFT,
) -> LandmarkRoi | None:
    """A hand's crop from BlazePose's wrist, index and pinky points of that arm (source pixels, shape (2,) each).

    Returns
    -------
    LandmarkRoi or None
        Centred at ``(2 index + pinky) / 3`` moved ``shift * side`` towards the fingers, turned so that wrist →
        middle finger points up, side ``2 * scale * |middle - wrist|``; None when that distance is under
        :data:`MIN_SIDE_PX` / 2.
    """
    w = np.asarray(wrist, dtype=np.float64)
    middle = (2.0 * np.asarray(index, dtype=np.float64) + np.asarray(pinky, dtype=np.float64)) / 3.0
    reach = float(np.linalg.norm(middle - w))
    side = 2.0 * reach * scale
    if not side >= MIN_SIDE_PX:
        return None
    c = _shifted(middle, (middle - w) / reach, side, shift)
    return LandmarkRoi(float(c[0]), float(c[1]), side, roi_rotation(w, middle))


def hand_roi_from_forearm(
    shoulder: FloatArray | None,
    elbow: FloatArray,
    wrist: FloatArray,
    *,
    centre: float = FOREARM_CENTRE,
    side: float = FOREARM_SIDE,
    floor: float = UPPER_ARM_FLOOR,
) -> LandmarkRoi | None:
    """A hand's crop from the arm alone (COCO-17): the hand continues the elbow → wrist direction.

    Parameters
    ----------
    shoulder : array, shape (2,), or None
        The arm's shoulder (source pixels), for the size floor; None when not seen.
    elbow, wrist : array, shape (2,)
        Source pixels.

    Returns
    -------
    LandmarkRoi or None
        Centred ``centre * L`` beyond the wrist along the forearm, side ``side * L``, turned so that the forearm
        points up; ``L = max(|wrist - elbow|, floor * |elbow - shoulder|)``. None when the forearm has no length or
        the side is under :data:`MIN_SIDE_PX`.
    """
    e, w = np.asarray(elbow, dtype=np.float64), np.asarray(wrist, dtype=np.float64)
    forearm = float(np.linalg.norm(w - e))
    if not forearm > 0.0:
        return None
    length = forearm
    if shoulder is not None:
        length = max(length, floor * float(np.linalg.norm(e - np.asarray(shoulder, dtype=np.float64))))
    if not side * length >= MIN_SIDE_PX:
        return None
    c = w + centre * length * (w - e) / forearm
    return LandmarkRoi(float(c[0]), float(c[1]), side * length, roi_rotation(e, w))


def _point(kp: FloatArray, names: tuple[str, ...], name: str, min_confidence: float) -> FloatArray | None:
    if name not in names:
        return None
    row = kp[names.index(name)]
    return row[:2] if row[2] >= min_confidence else None


def hand_rois(
    keypoints: FloatArray, names: tuple[str, ...], *, min_confidence: float = MIN_CONFIDENCE
) -> list[LandmarkRoi | None]:
    """Both hands' crops of one person, ``[left, right]`` (the body's sides), from whatever the body's keypoint set
    has: BlazePose's wrist, index and pinky points (:func:`hand_roi_from_blazepose`) where all three are confident,
    else the elbow and wrist (:func:`hand_roi_from_forearm`), else None.

    Parameters
    ----------
    keypoints : array, shape (K, 3)
        x, y (source pixels) and confidence of the body's keypoints.
    names : tuple of str, length K
        The body's keypoint names (``left_wrist``, ``left_index``, ...).
    """
    kp = np.asarray(keypoints, dtype=np.float64)
    if kp.shape != (len(names), 3):
        raise ValueError(f"keypoints must have shape ({len(names)}, 3), got {kp.shape}")
    out: list[LandmarkRoi | None] = []
    for s in HAND_SIDES:
        wrist, index, pinky = (_point(kp, names, f"{s}_{n}", min_confidence) for n in ("wrist", "index", "pinky"))
        elbow = _point(kp, names, f"{s}_elbow", min_confidence)
        roi = None
        if wrist is not None and index is not None and pinky is not None:
            roi = hand_roi_from_blazepose(wrist, index, pinky)
        elif wrist is not None and elbow is not None:
            roi = hand_roi_from_forearm(_point(kp, names, f"{s}_shoulder", min_confidence), elbow, wrist)
        out.append(roi)
    return out


N_HAND = len(HAND21)
"""Points per hand."""

_PALM = tuple(HAND21.index(n) for n in ("wrist", "thumb_cmc", "thumb_mcp", "thumb_ip", "index_finger_mcp",
                                        "index_finger_pip", "middle_finger_mcp", "middle_finger_pip",
                                        "ring_finger_mcp", "ring_finger_pip", "pinky_mcp", "pinky_pip"))  # fmt: skip
REFINE_SCALE = 2.0
"""MediaPipe's enlargement of the palm's box for the next crop (``hand_landmark_landmarks_to_roi``)."""
REFINE_SHIFT = 0.1
"""... and its move towards the fingers, in box heights (its ``shift_y = -0.1``, the crop's y pointing down)."""


def hand_roi_from_hand(
    hand: FloatArray, *, scale: float = REFINE_SCALE, shift: float = REFINE_SHIFT
) -> LandmarkRoi | None:
    """The next crop of a hand from its own 21 points (source pixels, shape (21, 2) or (21, 3)), as MediaPipe's hand
    tracking places it (``HandLandmarksToRectCalculator``): turned so that the wrist → middle of the knuckles
    (the index and ring knuckles' midpoint averaged with the middle knuckle) points up, the palm points' box in
    that frame, moved ``shift`` of its height towards the fingers, its longer side times ``scale``.

    Returns
    -------
    LandmarkRoi or None
        None when the palm has no extent (fewer than :data:`MIN_SIDE_PX` across after scaling).
    """
    pts = np.asarray(hand, dtype=np.float64)[:, :2]
    wrist = pts[HAND21.index("wrist")]
    knuckles = (
        (pts[HAND21.index("index_finger_mcp")] + pts[HAND21.index("ring_finger_mcp")]) / 2.0
        + pts[HAND21.index("middle_finger_mcp")]
    ) / 2.0
    rotation = roi_rotation(wrist, knuckles)
    c, s = np.cos(rotation), np.sin(rotation)
    # Into the crop's frame (x right, y down, the fingers up): the inverse of the crop → source rotation.
    palm = pts[list(_PALM)] @ np.array([[c, -s], [s, c]])
    lo, hi = palm.min(axis=0), palm.max(axis=0)
    width, height = hi - lo
    centre_crop = (lo + hi) / 2.0 + np.array([0.0, -shift * height])
    side = scale * float(max(width, height))
    if not side >= MIN_SIDE_PX:
        return None
    centre = np.array([[c, -s], [s, c]]) @ centre_crop
    return LandmarkRoi(float(centre[0]), float(centre[1]), side, rotation)


def decode_hands(
    landmarks: NDArray[np.floating],
    presence: NDArray[np.floating],
    rois: list[LandmarkRoi],
    input_size: int = HAND_INPUT_SIZE,
) -> FloatArray:
    """The hand model's outputs → one hand's keypoints per crop, in source pixels.

    Parameters
    ----------
    landmarks : array, shape (n, 63)
        21 x (x, y, z) per crop, x and y in crop pixels (MediaPipe's ``TensorsToLandmarksCalculator`` input).
    presence : array, shape (n,)
        The model's hand-presence score per crop, in [0, 1] (MediaPipe's ``hand_presence_score``).
    rois : list of LandmarkRoi, length n

    Returns
    -------
    array, shape (n, 21, 3)
        x, y (source pixels) and confidence: the presence score on all 21 points (the model has no per-point
        visibility).
    """
    pts = np.asarray(landmarks, dtype=np.float64).reshape(len(rois), N_HAND, 3)
    out = np.empty((len(rois), N_HAND, 3))
    for i, roi in enumerate(rois):
        out[i, :, :2] = roi.to_source(pts[i, :, :2], input_size)
    out[:, :, 2] = np.clip(np.asarray(presence, dtype=np.float64).reshape(-1, 1), 0.0, 1.0)
    return out


def hand_span(hand: FloatArray) -> float:
    """A hand's size across in pixels: the longer side of its 21 points' bounding box (shape (21, 2) or (21, 3))."""
    pts = np.asarray(hand, dtype=np.float64)[:, :2]
    return float(np.max(pts.max(axis=0) - pts.min(axis=0)))
