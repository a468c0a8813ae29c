"""Per-person body size from triangulated COCO-17 joints (the first seconds of a track).

Limb lengths are the medians of keypoint distances over the frames (robust to mis-detections): upper arm
(shoulder–elbow), forearm (elbow–wrist), thigh (hip–knee), shank (knee–ankle), averaged over left and right;
shoulder and hip widths scale the lateral offsets. The height, used for everything not measured (spine, neck,
head, feet), is the default proportion of the leg length (the most reliable measurement).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mocapd.core.keypoints import COCO17
from mocapd.core.skeleton import BONE_INDEX, REFERENCE_HEIGHT, Skeleton
from mocapd.errors import InputError

FloatArray = NDArray[np.float64]

_KP = {name: i for i, (name, _, _) in enumerate(COCO17)}
# bone whose offset is the measured segment (see Skeleton.from_bone_lengths), keypoint pairs left and right
_SEGMENTS = {
    "LowerArm": ("shoulder", "elbow"),  # upper-arm length = offset of the lower arm
    "Hand": ("elbow", "wrist"),
    "LowerLeg": ("hip", "knee"),  # thigh length = offset of the lower leg
    "Foot": ("knee", "ankle"),
}


def _median_distance(kp: FloatArray, a: str, b: str) -> float:
    d = np.linalg.norm(kp[:, _KP[a]] - kp[:, _KP[b]], axis=-1)
    d = d[np.isfinite(d)]
    return float(np.median(d)) if d.size else np.nan


def estimate_skeleton(keypoints: FloatArray, min_frames: int = 10) -> Skeleton:
    """A skeleton sized from triangulated COCO-17 keypoints.

    Parameters
    ----------
    keypoints : array, shape (n_frames, 17, 3)
        World positions (metres), NaN where not triangulated.
    min_frames : int
        Fewer frames with both legs measured raise :class:`InputError` (use a configured height instead).
    """
    kp = np.asarray(keypoints, dtype=np.float64)
    if kp.ndim != 3 or kp.shape[1:] != (len(COCO17), 3):
        raise InputError(f"keypoints must have shape (n_frames, {len(COCO17)}, 3), got {kp.shape}")
    legs = [
        np.isfinite(kp[:, _KP[f"{s}_{j}"]]).all(axis=-1) for s in ("left", "right") for j in ("hip", "knee", "ankle")
    ]
    if int(np.logical_and.reduce(legs).sum()) < min_frames:
        raise InputError(f"body size needs at least {min_frames} frames with both legs triangulated")
    ref = Skeleton.from_height(REFERENCE_HEIGHT)
    lengths: dict[str, float] = {}
    for bone, (a, b) in _SEGMENTS.items():
        m = np.nanmean([_median_distance(kp, f"{side}_{a}", f"{side}_{b}") for side in ("left", "right")])
        if np.isfinite(m):
            lengths[f"Left{bone}"] = lengths[f"Right{bone}"] = float(m)
    leg = lengths["LeftLowerLeg"] + lengths["LeftFoot"]
    ref_leg = ref.bone_length("LeftLowerLeg") + ref.bone_length("LeftFoot")
    height = float(np.clip(REFERENCE_HEIGHT * leg / ref_leg, 0.5, 2.6))
    s = height / REFERENCE_HEIGHT
    for side in ("Left", "Right"):
        for bone, pair in ((f"{side}UpperArm", ("left_shoulder", "right_shoulder")),
                           (f"{side}UpperLeg", ("left_hip", "right_hip"))):  # fmt: skip
            half = 0.5 * _median_distance(kp, *pair)
            lateral = abs(ref.offsets[BONE_INDEX[bone], 0]) * s
            if np.isfinite(half) and lateral > 0:
                lengths[bone] = float(np.linalg.norm(ref.offsets[BONE_INDEX[bone]]) * s * half / lateral)
    return _fit_torso(Skeleton.from_bone_lengths(lengths, height=height), kp)


_SPINE = [BONE_INDEX[b] for b in ("Spine", "Spine1", "Spine2", "Spine3")]
_UPPER_ARMS = [BONE_INDEX["LeftUpperArm"], BONE_INDEX["RightUpperArm"]]
_UPPER_LEGS = [BONE_INDEX["LeftUpperLeg"], BONE_INDEX["RightUpperLeg"]]


def _fit_torso(skeleton: Skeleton, kp: FloatArray) -> Skeleton:
    """Scale the spine chain so the rest-pose distance from the hip midpoint up to the shoulder midpoint is the
    measured one (the median over frames). Torso proportions vary between people far more than the height-scaled
    default assumes (a CMU subject's is ~30 % shorter than the default for his leg length)."""
    mid_hip = 0.5 * (kp[:, _KP["left_hip"]] + kp[:, _KP["right_hip"]])
    mid_shoulder = 0.5 * (kp[:, _KP["left_shoulder"]] + kp[:, _KP["right_shoulder"]])
    torso = float(np.nanmedian(np.linalg.norm(mid_shoulder - mid_hip, axis=-1)))
    off = skeleton.offsets.copy()
    # Rest pose, vertical: shoulders at Σ spine + upper-arm offset above the root, hips at the upper-leg offset.
    spine = off[_SPINE, 1].sum() + off[_UPPER_ARMS, 1].mean()
    below = off[_UPPER_LEGS, 1].mean()  # negative: the hip joints sit below the root
    if not np.isfinite(torso) or spine <= 0:
        return skeleton
    k = float(np.clip((torso + below) / spine, 0.5, 1.5))
    off[_SPINE] *= k
    off[_UPPER_ARMS, 1] *= k
    return Skeleton(offsets=off, root_height=skeleton.root_height, height=skeleton.height)
