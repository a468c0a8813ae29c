"""Keypoint sets of other 2D detectors, by name, and their conversion onto the sets mocapd solves with.

mocapd's solver knows four keypoint formats (:mod:`mocapd.core.keypoints`: ``coco17``, ``body25``, ``halpe26``,
``blazepose33``).
Detectors in the wild write more: OpenPose's COCO-18, COCO-WholeBody's 133 points (RTMW, MMPose's wholebody
models), MediaPipe BlazePose's 33 landmarks (also FreeMoCap's). Each set here is its keypoint names in output
order; :func:`convert` moves a detection onto one of mocapd's formats *by name* (a keypoint the target has that
the source lacks gets confidence 0, which every consumer reads as "not seen"), and :data:`SOLVE_FORMAT` says which
of mocapd's formats a set goes onto without losing any point the solver can use (feet and BlazePose's hand points
included).

Names are COCO's (``left_shoulder``); a set's own spelling is translated by :data:`ALIASES` (BlazePose's
``left_foot_index``, the tip of the second toe, stands for the big toe: 1-2 cm apart, within the solver's
per-keypoint noise).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from mocapd.core.keypoints import BODY25_FORMAT, COCO17_FORMAT, HALPE26_FORMAT
from mocapd.errors import InputError

FloatArray = NDArray[np.float64]

COCO18: tuple[str, ...] = (
    "nose", "neck", "right_shoulder", "right_elbow", "right_wrist", "left_shoulder", "left_elbow", "left_wrist",
    "right_hip", "right_knee", "right_ankle", "left_hip", "left_knee", "left_ankle", "right_eye", "left_eye",
    "right_ear", "left_ear",
)  # fmt: skip
"""OpenPose's COCO model (``--model_pose COCO``): COCO-17 reordered, with a neck."""

_FEET = ("left_big_toe", "left_small_toe", "left_heel", "right_big_toe", "right_small_toe", "right_heel")

WHOLEBODY133: tuple[str, ...] = (
    *COCO17_FORMAT.keypoints,
    *_FEET,
    *(f"face_{i}" for i in range(68)),
    *(f"left_hand_{i}" for i in range(21)),
    *(f"right_hand_{i}" for i in range(21)),
)
"""COCO-WholeBody (RTMW, MMPose's wholebody models): body, feet, 68 face points, 21 per hand."""

BLAZEPOSE33: tuple[str, ...] = (
    "nose", "left_eye_inner", "left_eye", "left_eye_outer", "right_eye_inner", "right_eye", "right_eye_outer",
    "left_ear", "right_ear", "mouth_left", "mouth_right", "left_shoulder", "right_shoulder", "left_elbow",
    "right_elbow", "left_wrist", "right_wrist", "left_pinky", "right_pinky", "left_index", "right_index",
    "left_thumb", "right_thumb", "left_hip", "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle",
    "left_heel", "right_heel", "left_foot_index", "right_foot_index",
)  # fmt: skip
"""MediaPipe BlazePose (Pose Landmarker, FreeMoCap's first 33 points)."""

SETS: Mapping[str, tuple[str, ...]] = {
    "coco17": COCO17_FORMAT.keypoints,
    "coco18": COCO18,
    "body25": BODY25_FORMAT.keypoints,
    "halpe26": HALPE26_FORMAT.keypoints,
    "wholebody133": WHOLEBODY133,
    "blazepose33": BLAZEPOSE33,
}
"""Every keypoint set a file may hold, by name."""

SOLVE_FORMAT: Mapping[str, str] = {
    "coco17": "coco17",
    "coco18": "coco17",  # the neck is the shoulders' midpoint: nothing COCO-17 lacks
    "body25": "body25",
    "halpe26": "halpe26",
    "wholebody133": "halpe26",  # body + feet; hands and face have no target yet
    # every landmark: the heels and foot_index on Foot and Toes, pinky, index and thumb on Hand (halpe26 had no hand
    # point: hand local rotation median 11-14 -> 8 deg on the synthetic rig, tests/test_import_keypoints.py)
    "blazepose33": "blazepose33",
}
"""The mocapd format (:data:`mocapd.core.keypoints.FORMATS`) each set is solved in."""

ALIASES: Mapping[str, Mapping[str, str]] = {
    "blazepose33": {
        "left_foot_index": "left_big_toe",
        "right_foot_index": "right_big_toe",
        "mouth_left": "left_mouth",
        "mouth_right": "right_mouth",
    },
}
"""A set's own name -> mocapd's name for the same point (a target that has the set's own name gets it by that)."""


def keypoint_set(name: str) -> tuple[str, ...]:
    """The names of set ``name`` in output order."""
    try:
        return SETS[name]
    except KeyError:
        raise InputError(f"unknown keypoint set {name!r}; known: {', '.join(SETS)}") from None


def set_for_count(n: int, choices: Sequence[str] = tuple(SETS)) -> str:
    """The set among ``choices`` that has ``n`` keypoints (a file that does not name its set)."""
    found = [s for s in choices if len(SETS[s]) == n]
    if len(found) != 1:
        sizes = ", ".join(f"{s} {len(SETS[s])}" for s in choices)
        raise InputError(f"{n} keypoints per person is no keypoint set known here ({sizes}); name it (--keypoints)")
    return found[0]


def conversion_index(source: str, target: Sequence[str]) -> tuple[list[int], list[int]]:
    """Where each of ``target``'s names is in set ``source``: (target positions, source positions), names only in
    one of them left out."""
    alias = ALIASES.get(source, {})
    names = keypoint_set(source)
    # By the set's own name first (mocapd's blazepose33 format keeps foot_index), else by its alias (big_toe).
    where = {**{alias[n]: i for i, n in enumerate(names) if n in alias}, **{n: i for i, n in enumerate(names)}}
    pairs = [(j, where[n]) for j, n in enumerate(target) if n in where]
    return [j for j, _ in pairs], [i for _, i in pairs]


def convert(source: str, keypoints: FloatArray, confidences: FloatArray, target: Sequence[str]) -> tuple[
    FloatArray, FloatArray]:  # fmt: skip
    """Detections in set ``source`` as detections in the names ``target``.

    Parameters
    ----------
    source : str
        A name of :data:`SETS`.
    keypoints : array, shape (n_people, n_source, 2)
        Pixels.
    confidences : array, shape (n_people, n_source)
    target : sequence of str, length n_target
        Keypoint names in the order wanted.

    Returns
    -------
    keypoints : array, shape (n_people, n_target, 2)
        A target keypoint the source does not have is at pixel (0, 0) ...
    confidences : array, shape (n_people, n_target)
        ... with confidence 0.
    """
    n_src = len(keypoint_set(source))
    kp = np.asarray(keypoints, dtype=np.float64)
    cf = np.asarray(confidences, dtype=np.float64)
    if kp.ndim != 3 or kp.shape[1:] != (n_src, 2) or cf.shape != kp.shape[:2]:
        raise InputError(f"{source}: keypoints ({kp.shape[0] if kp.ndim else '?'}, {n_src}, 2) and confidences "
                         f"(n, {n_src}) expected, got {kp.shape} and {cf.shape}")  # fmt: skip
    dst, src = conversion_index(source, target)
    out_kp = np.zeros((kp.shape[0], len(target), 2))
    out_cf = np.zeros((kp.shape[0], len(target)))
    out_kp[:, dst] = kp[:, src]
    out_cf[:, dst] = cf[:, src]
    bad = ~np.all(np.isfinite(out_kp), axis=-1) | ~np.isfinite(out_cf)
    out_kp[bad] = 0.0  # a point a detector marks NaN is one it did not see
    out_cf[bad] = 0.0
    return out_kp, np.clip(out_cf, 0.0, 1.0)
