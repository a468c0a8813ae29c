"""Per-person body size from triangulated keypoints (the first seconds of a track), of any keypoint set that names
shoulders, elbows, wrists, hips, knees and ankles (COCO-17, BODY_25, Halpe-26, COCO-WholeBody, BlazePose: the
points are looked up by their names, :data:`SIZING_KEYPOINTS`).

Limb lengths are the medians of keypoint distances over the frames (robust to mis-detections): upper arm
(shoulder–elbow), forearm (elbow–wrist), thigh (hip–knee), shank (knee–ankle), averaged over left and right;
shoulder and hip widths scale the lateral offsets; the spine chain is scaled to the measured hip-to-shoulder
distance. The height, used for everything not measured, is the default proportion of the leg length (the most
reliable measurement). A set that also names a neck, a mid-hip and a nose (:data:`TRUNK_KEYPOINTS`: BODY_25, and
Halpe-26, whose mid-hip is ``hip``) has the rest of the trunk measured too: where the Neck joint sits above the
shoulders, where the Hips joint sits above the hip joints, and the head's length; other sets (COCO-17, BlazePose)
keep those at the height-scaled default proportions.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mocapd.core.keypoints import COCO17
from mocapd.core.skeleton import BONE_INDEX, REFERENCE_HEIGHT, Skeleton
from mocapd.errors import InputError

FloatArray = NDArray[np.float64]

COCO17_NAMES: tuple[str, ...] = tuple(name for name, _, _ in COCO17)
SIZING_KEYPOINTS: tuple[str, ...] = tuple(
    f"{side}_{j}" for side in ("left", "right") for j in ("shoulder", "elbow", "wrist", "hip", "knee", "ankle")
)
"""The keypoints body sizing measures: a set without one of them cannot be sized (:func:`can_size`)."""
# bone whose offset is the measured segment (see Skeleton.from_bone_lengths), keypoint pairs left and right
_SEGMENTS = {
    "LowerArm": ("shoulder", "elbow"),  # upper-arm length = offset of the lower arm
    "Hand": ("elbow", "wrist"),
    "LowerLeg": ("hip", "knee"),  # thigh length = offset of the lower leg
    "Foot": ("knee", "ankle"),
}


def can_size(names: tuple[str, ...] | list[str]) -> bool:
    """Whether a keypoint set with these names can be sized (it has every one of :data:`SIZING_KEYPOINTS`)."""
    return set(SIZING_KEYPOINTS) <= set(names)


def _median_distance(kp: FloatArray, a: int, b: int) -> float:
    d = np.linalg.norm(kp[:, a] - kp[:, b], axis=-1)
    d = d[np.isfinite(d)]
    return float(np.median(d)) if d.size else np.nan


def estimate_skeleton(
    keypoints: FloatArray, min_frames: int = 10, names: tuple[str, ...] | list[str] = COCO17_NAMES
) -> Skeleton:
    """A skeleton sized from triangulated keypoints.

    Parameters
    ----------
    keypoints : array, shape (n_frames, n_kp, 3)
        World positions (metres), NaN where not triangulated.
    min_frames : int
        Fewer frames with both legs measured raise :class:`InputError` (use a configured height instead).
    names : sequence of str, length n_kp
        The keypoints' names (COCO-17's by default); the set must have every one of :data:`SIZING_KEYPOINTS`.
    """
    kp = np.asarray(keypoints, dtype=np.float64)
    if kp.ndim != 3 or kp.shape[1:] != (len(names), 3):
        raise InputError(f"keypoints must have shape (n_frames, {len(names)}, 3), got {kp.shape}")
    if not can_size(names):
        missing = sorted(set(SIZING_KEYPOINTS) - set(names))
        raise InputError(f"body size needs the keypoints {missing}, which this keypoint set does not have")
    at = {n: i for i, n in enumerate(names)}
    legs = [
        np.isfinite(kp[:, at[f"{s}_{j}"]]).all(axis=-1) for s in ("left", "right") for j in ("hip", "knee", "ankle")
    ]
    if int(np.logical_and.reduce(legs).sum()) < min_frames:
        raise InputError(f"body size needs at least {min_frames} frames with both legs triangulated")
    ref = Skeleton.from_height(REFERENCE_HEIGHT)
    lengths: dict[str, float] = {}
    for bone, (a, b) in _SEGMENTS.items():
        m = np.nanmean([_median_distance(kp, at[f"{side}_{a}"], at[f"{side}_{b}"]) for side in ("left", "right")])
        if np.isfinite(m):
            lengths[f"Left{bone}"] = lengths[f"Right{bone}"] = float(m)
    leg = lengths["LeftLowerLeg"] + lengths["LeftFoot"]
    ref_leg = ref.bone_length("LeftLowerLeg") + ref.bone_length("LeftFoot")
    height = float(np.clip(REFERENCE_HEIGHT * leg / ref_leg, 0.5, 2.6))
    s = height / REFERENCE_HEIGHT
    for side in ("Left", "Right"):
        for bone, pair in ((f"{side}UpperArm", ("left_shoulder", "right_shoulder")),
                           (f"{side}UpperLeg", ("left_hip", "right_hip"))):  # fmt: skip
            half = 0.5 * _median_distance(kp, at[pair[0]], at[pair[1]])
            lateral = abs(ref.offsets[BONE_INDEX[bone], 0]) * s
            if np.isfinite(half) and lateral > 0:
                lengths[bone] = float(np.linalg.norm(ref.offsets[BONE_INDEX[bone]]) * s * half / lateral)
    return _fit_trunk(Skeleton.from_bone_lengths(lengths, height=height), kp, at)


_SPINE = [BONE_INDEX[b] for b in ("Spine", "Spine1", "Spine2", "Spine3")]
_UPPER_ARMS = [BONE_INDEX["LeftUpperArm"], BONE_INDEX["RightUpperArm"]]
_UPPER_LEGS = [BONE_INDEX["LeftUpperLeg"], BONE_INDEX["RightUpperLeg"]]
_NECK, _HEAD = BONE_INDEX["Neck"], BONE_INDEX["Head"]
TRUNK_KEYPOINTS: tuple[str, ...] = ("neck", "mid_hip", "nose")
"""With all of these (BODY_25; Halpe-26 through :data:`TRUNK_ALIASES`), sizing also places the Neck, Hips and Head
joints (:func:`_fit_trunk`)."""
TRUNK_ALIASES: dict[str, str] = {"hip": "mid_hip"}
"""Other sets' names of a trunk keypoint: Halpe-26's ``hip`` is its mid-hip (the Hips joint's target, as BODY_25's
``mid_hip``: :data:`mocapd.core.keypoints.HALPE26_FORMAT`)."""
_NOSE_ON_HEAD = (0.06, 0.10 + 0.01)
"""The nose target's height above the Head joint and its distance in front of the Neck joint, at the reference
height (COCO-17's nose offset on Head plus the Head joint's own forward offset)."""


def _fit_torso(skeleton: Skeleton, kp: FloatArray, at: dict[str, int]) -> Skeleton:
    """Scale the spine chain so the rest-pose distance from the hip midpoint up to the shoulder midpoint is the
    measured one (the median over frames). Torso proportions vary between people far more than the height-scaled
    default assumes (a CMU subject's is ~30 % shorter than the default for his leg length)."""
    mid_hip = 0.5 * (kp[:, at["left_hip"]] + kp[:, at["right_hip"]])
    mid_shoulder = 0.5 * (kp[:, at["left_shoulder"]] + kp[:, at["right_shoulder"]])
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


def _fit_trunk(skeleton: Skeleton, kp: FloatArray, at: dict[str, int]) -> Skeleton:
    """:func:`_fit_torso`, and, for a keypoint set with :data:`TRUNK_KEYPOINTS`, the trunk's other proportions
    measured (medians over frames) where the default ones would put the detector's points centimetres off, a constant
    error no filter removes (~7 mm of MPJPE on ``mocapd eval keypoints``, docs/accuracy.md):

    - the Hips joint (the mid-hip keypoint's bone) at the measured height of the mid-hip above the hip joints'
      midpoint, along the trunk's axis (hip midpoint to shoulder midpoint); the standing root height follows;
    - the Neck joint (the neck keypoint's) at the measured height of the neck above the shoulders' midpoint;
    - the Head joint at the length that puts the nose target at the measured neck–nose distance.

    Any other set is sized exactly as :func:`_fit_torso` sizes it.
    """
    at = {**{name: at[alias] for alias, name in TRUNK_ALIASES.items() if alias in at}, **at}
    if not set(TRUNK_KEYPOINTS) <= set(at):
        return _fit_torso(skeleton, kp, at)
    mid_sh = 0.5 * (kp[:, at["left_shoulder"]] + kp[:, at["right_shoulder"]])
    mid_hj = 0.5 * (kp[:, at["left_hip"]] + kp[:, at["right_hip"]])
    with np.errstate(invalid="ignore"):  # frames with a point missing give NaN, which the medians skip
        up = (mid_sh - mid_hj) / np.linalg.norm(mid_sh - mid_hj, axis=1, keepdims=True)
        pelvis_up = _nanmedian(np.sum((kp[:, at["mid_hip"]] - mid_hj) * up, axis=1))
        neck_up = _nanmedian(np.sum((kp[:, at["neck"]] - mid_sh) * up, axis=1))
    nose = _nanmedian(np.linalg.norm(kp[:, at["nose"]] - kp[:, at["neck"]], axis=1))
    off, root_height = skeleton.offsets.copy(), skeleton.root_height
    if np.isfinite(pelvis_up):  # before the torso fit, which measures the spine from the hip joints up
        root_height += pelvis_up + float(off[_UPPER_LEGS, 1].mean())
        off[_UPPER_LEGS, 1] = -pelvis_up
    sk = _fit_torso(Skeleton(offsets=off, root_height=root_height, height=skeleton.height), kp, at)
    off, s = sk.offsets.copy(), sk.height / REFERENCE_HEIGHT
    if np.isfinite(neck_up):  # the Neck joint's height above the shoulder joints (both children of Spine3)
        off[_NECK, 1] = off[_UPPER_ARMS, 1].mean() + neck_up
    up_nose, forward_nose = (v * s for v in _NOSE_ON_HEAD)
    if np.isfinite(nose) and nose > forward_nose:
        off[_HEAD, 1] = np.sqrt(nose**2 - forward_nose**2) - up_nose
    return Skeleton(offsets=off, root_height=sk.root_height, height=sk.height)


def _nanmedian(x: FloatArray) -> float:
    """The median of the finite values, NaN when there are none (without numpy's all-NaN warning)."""
    x = x[np.isfinite(x)]
    return float(np.median(x)) if x.size else np.nan
