"""Keypoints as track targets ``(bone, offset t_pb)`` (seed 003 §3.1, §3.3.2).

A 2D detector outputs a named keypoint set; each keypoint is tied to a skeleton bone and an offset in that
bone's frame. Joint keypoints sit on a bone's joint (zero offset by default); surface keypoints (nose, eyes,
ears) have non-zero offsets. Calibrated offsets (seed 003 §3.3.2) replace the defaults.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mocapd.core.skeleton import BONE_INDEX, REFERENCE_HEIGHT, Skeleton
from mocapd.errors import InputError

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]


@dataclass(frozen=True)
class TrackTargets:
    """A set of positional track targets.

    Attributes
    ----------
    names : tuple of str, length n
    bones : int array, shape (n,)
        Bone index of each target.
    offsets : array, shape (n, 3)
        Offset of each target in its bone's frame (metres).
    """

    names: tuple[str, ...]
    bones: IntArray
    offsets: FloatArray

    def __post_init__(self) -> None:
        bones = np.asarray(self.bones, dtype=np.intp)
        offsets = np.asarray(self.offsets, dtype=np.float64)
        n = len(self.names)
        if bones.shape != (n,) or offsets.shape != (n, 3):
            raise InputError(
                f"track targets: {n} names need bones ({n},) and offsets ({n}, 3); "
                f"got {bones.shape} and {offsets.shape}"
            )
        if not np.all(np.isfinite(offsets)):
            raise InputError("track target offsets contain non-finite values")
        object.__setattr__(self, "bones", bones)
        object.__setattr__(self, "offsets", offsets)

    def __len__(self) -> int:
        return len(self.names)

    def with_offsets(self, offsets: FloatArray) -> TrackTargets:
        """The same targets with new (e.g. calibrated) offsets, shape (n, 3)."""
        return TrackTargets(self.names, self.bones, np.asarray(offsets, dtype=np.float64))


# COCO-17 keypoint order with the bone each keypoint lives on and its default offset (1.75 m person).
COCO17: tuple[tuple[str, str, tuple[float, float, float]], ...] = (
    ("nose", "Head", (0.0, 0.06, 0.10)),
    ("left_eye", "Head", (0.035, 0.09, 0.08)),
    ("right_eye", "Head", (-0.035, 0.09, 0.08)),
    ("left_ear", "Head", (0.075, 0.07, 0.0)),
    ("right_ear", "Head", (-0.075, 0.07, 0.0)),
    ("left_shoulder", "LeftUpperArm", (0.0, 0.0, 0.0)),
    ("right_shoulder", "RightUpperArm", (0.0, 0.0, 0.0)),
    ("left_elbow", "LeftLowerArm", (0.0, 0.0, 0.0)),
    ("right_elbow", "RightLowerArm", (0.0, 0.0, 0.0)),
    ("left_wrist", "LeftHand", (0.0, 0.0, 0.0)),
    ("right_wrist", "RightHand", (0.0, 0.0, 0.0)),
    ("left_hip", "LeftUpperLeg", (0.0, 0.0, 0.0)),
    ("right_hip", "RightUpperLeg", (0.0, 0.0, 0.0)),
    ("left_knee", "LeftLowerLeg", (0.0, 0.0, 0.0)),
    ("right_knee", "RightLowerLeg", (0.0, 0.0, 0.0)),
    ("left_ankle", "LeftFoot", (0.0, 0.0, 0.0)),
    ("right_ankle", "RightFoot", (0.0, 0.0, 0.0)),
)


def coco17_targets(skeleton: Skeleton | None = None) -> TrackTargets:
    """COCO-17 track targets with default offsets scaled to the skeleton's height."""
    s = (skeleton.height if skeleton is not None else REFERENCE_HEIGHT) / REFERENCE_HEIGHT
    return TrackTargets(
        names=tuple(n for n, _, _ in COCO17),
        bones=np.array([BONE_INDEX[b] for _, b, _ in COCO17], dtype=np.intp),
        offsets=np.array([o for _, _, o in COCO17]) * s,
    )


FLOOR_TARGET_BONES: tuple[str, ...] = ("LeftFoot", "LeftToes", "RightFoot", "RightToes")
"""Joints the floor-penetration term applies to (seed 003 §3.2.5: feet and toes)."""


def floor_targets() -> TrackTargets:
    """The floor term's targets: the joints of both feet and toes (zero offsets)."""
    return TrackTargets(
        names=FLOOR_TARGET_BONES,
        bones=np.array([BONE_INDEX[b] for b in FLOOR_TARGET_BONES], dtype=np.intp),
        offsets=np.zeros((len(FLOOR_TARGET_BONES), 3)),
    )
