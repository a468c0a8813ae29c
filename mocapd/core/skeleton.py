"""The 21-bone skeleton of DESIGN.md and its per-person sizing.

Bone order, names and parents are fixed (index = position in every array). The rest pose is a T-pose facing
+Z with +Y up (so the person's left is +X). Each bone's *offset* is the position of its joint in its parent's
frame at rest; the root's offset is zero because the root position is the first three elements of θ.

The default proportions are for a 1.75 m person and scale linearly with height. The ankle sits 7 cm and the
toe joint 5 cm above the floor at rest, matching the 5 cm collision radius of the floor term (seed 003 §3.2.5).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from mocapd.errors import InputError

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

BONE_NAMES: tuple[str, ...] = (
    "Hips",
    "Spine",
    "Spine1",
    "Spine2",
    "Spine3",
    "Neck",
    "Head",
    "LeftUpperArm",
    "LeftLowerArm",
    "LeftHand",
    "RightUpperArm",
    "RightLowerArm",
    "RightHand",
    "LeftUpperLeg",
    "LeftLowerLeg",
    "LeftFoot",
    "LeftToes",
    "RightUpperLeg",
    "RightLowerLeg",
    "RightFoot",
    "RightToes",
)
N_BONES = len(BONE_NAMES)
POSE_DIM = 3 + 3 * N_BONES  # root translation + one rotation vector per bone = 66
BONE_INDEX: Mapping[str, int] = {name: i for i, name in enumerate(BONE_NAMES)}

_PARENT_NAMES: dict[str, str | None] = {
    "Hips": None,
    "Spine": "Hips",
    "Spine1": "Spine",
    "Spine2": "Spine1",
    "Spine3": "Spine2",
    "Neck": "Spine3",
    "Head": "Neck",
    "LeftUpperArm": "Spine3",
    "LeftLowerArm": "LeftUpperArm",
    "LeftHand": "LeftLowerArm",
    "RightUpperArm": "Spine3",
    "RightLowerArm": "RightUpperArm",
    "RightHand": "RightLowerArm",
    "LeftUpperLeg": "Hips",
    "LeftLowerLeg": "LeftUpperLeg",
    "LeftFoot": "LeftLowerLeg",
    "LeftToes": "LeftFoot",
    "RightUpperLeg": "Hips",
    "RightLowerLeg": "RightUpperLeg",
    "RightFoot": "RightLowerLeg",
    "RightToes": "RightFoot",
}
PARENTS: tuple[int, ...] = tuple(
    -1 if _PARENT_NAMES[n] is None else BONE_INDEX[str(_PARENT_NAMES[n])] for n in BONE_NAMES
)

REFERENCE_HEIGHT = 1.75
"""Height (m) the default offsets are written for."""

# Joint offsets in the parent frame (metres) for a 1.75 m person in the T-pose facing +Z.
_DEFAULT_OFFSETS: dict[str, tuple[float, float, float]] = {
    "Hips": (0.0, 0.0, 0.0),
    "Spine": (0.0, 0.09, -0.01),
    "Spine1": (0.0, 0.11, 0.0),
    "Spine2": (0.0, 0.11, 0.0),
    "Spine3": (0.0, 0.11, 0.0),
    "Neck": (0.0, 0.10, 0.0),
    "Head": (0.0, 0.10, 0.01),
    "LeftUpperArm": (0.18, 0.06, 0.0),
    "LeftLowerArm": (0.29, 0.0, 0.0),
    "LeftHand": (0.25, 0.0, 0.0),
    "RightUpperArm": (-0.18, 0.06, 0.0),
    "RightLowerArm": (-0.29, 0.0, 0.0),
    "RightHand": (-0.25, 0.0, 0.0),
    "LeftUpperLeg": (0.09, -0.05, 0.0),
    "LeftLowerLeg": (0.0, -0.43, 0.0),
    "LeftFoot": (0.0, -0.43, 0.0),
    "LeftToes": (0.0, -0.02, 0.14),
    "RightUpperLeg": (-0.09, -0.05, 0.0),
    "RightLowerLeg": (0.0, -0.43, 0.0),
    "RightFoot": (0.0, -0.43, 0.0),
    "RightToes": (0.0, -0.02, 0.14),
}
DEFAULT_ROOT_HEIGHT = 0.98
"""Height (m) of the Hips joint above the floor at rest for a 1.75 m person (ankles then at 7 cm)."""


def _depths(parents: tuple[int, ...]) -> tuple[int, ...]:
    depth = [0] * len(parents)
    for i, p in enumerate(parents):
        depth[i] = 0 if p < 0 else depth[p] + 1
    return tuple(depth)


def _ancestor_matrix(parents: tuple[int, ...]) -> NDArray[np.bool_]:
    """``A[b, k]`` is True when bone k is b or one of its ancestors (so k's rotation moves b)."""
    n = len(parents)
    anc = np.zeros((n, n), dtype=bool)
    for b in range(n):
        k = b
        while k >= 0:
            anc[b, k] = True
            k = parents[k]
    return anc


@dataclass(frozen=True)
class Skeleton:
    """A sized instance of the 21-bone skeleton.

    Attributes
    ----------
    offsets : array, shape (21, 3)
        Joint position of each bone in its parent's frame at rest (metres); row 0 is zero.
    root_height : float
        Hips joint height above the floor in the rest pose (metres); used for the rest pose θ.
    height : float
        The person's height (metres) these offsets correspond to (informative).
    """

    offsets: FloatArray
    root_height: float = DEFAULT_ROOT_HEIGHT
    height: float = REFERENCE_HEIGHT
    parents: tuple[int, ...] = PARENTS
    depths: tuple[int, ...] = field(init=False)
    ancestors: NDArray[np.bool_] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        offsets = np.asarray(self.offsets, dtype=np.float64)
        if offsets.shape != (N_BONES, 3):
            raise InputError(f"skeleton offsets must have shape ({N_BONES}, 3), got {offsets.shape}")
        if not np.all(np.isfinite(offsets)):
            raise InputError("skeleton offsets contain non-finite values")
        if not (math.isfinite(self.root_height) and math.isfinite(self.height) and self.height > 0):
            # both scale things downstream (IMU mounts, body size): nan would spread silently into every pose
            raise InputError(f"skeleton root_height and height must be finite, height > 0; got "
                             f"{self.root_height!r} and {self.height!r}")  # fmt: skip
        offsets = offsets.copy()
        offsets[0] = 0.0
        offsets.setflags(write=False)
        object.__setattr__(self, "offsets", offsets)
        object.__setattr__(self, "depths", _depths(self.parents))
        anc = _ancestor_matrix(self.parents)
        anc.setflags(write=False)
        object.__setattr__(self, "ancestors", anc)

    @classmethod
    def from_height(cls, height: float = REFERENCE_HEIGHT) -> Skeleton:
        """The default proportions scaled to a person of ``height`` metres."""
        if not (0.5 <= height <= 2.6):
            raise InputError(f"person height must be within [0.5, 2.6] m, got {height!r}")
        s = height / REFERENCE_HEIGHT
        offsets = np.array([_DEFAULT_OFFSETS[n] for n in BONE_NAMES]) * s
        return cls(offsets=offsets, root_height=DEFAULT_ROOT_HEIGHT * s, height=height)

    @classmethod
    def from_bone_lengths(cls, lengths: Mapping[str, float], height: float = REFERENCE_HEIGHT) -> Skeleton:
        """Default directions with explicit lengths for some bones.

        Parameters
        ----------
        lengths : mapping bone name -> metres
            Length of the offset from the parent's joint to this bone's joint (e.g. ``"LeftLowerLeg"`` is the
            thigh length). Bones not named keep the default scaled to ``height``.
        """
        base = cls.from_height(height)
        offsets = base.offsets.copy()
        for name, length in lengths.items():
            if name not in BONE_INDEX or name == "Hips":
                raise InputError(f"unknown or root bone in bone lengths: {name!r}")
            if not (np.isfinite(length) and 0.0 < length < 1.5):
                raise InputError(f"bone length of {name} must be in (0, 1.5) m, got {length!r}")
            i = BONE_INDEX[name]
            offsets[i] *= length / float(np.linalg.norm(offsets[i]))
        # The root height follows the legs: hip offset + thigh + shank + ankle height of the default.
        leg = -(
            offsets[BONE_INDEX["LeftUpperLeg"], 1]
            + offsets[BONE_INDEX["LeftLowerLeg"], 1]
            + offsets[BONE_INDEX["LeftFoot"], 1]
        )
        ankle = 0.07 * height / REFERENCE_HEIGHT
        return cls(offsets=offsets, root_height=float(leg + ankle), height=height)

    def rest_pose(self) -> FloatArray:
        """θ of the T-pose standing on the floor at the origin facing +Z, shape (66,)."""
        theta = np.zeros(POSE_DIM)
        theta[1] = self.root_height
        return theta

    def bone_length(self, name: str) -> float:
        """Length (m) of the offset of bone ``name`` from its parent's joint."""
        return float(np.linalg.norm(self.offsets[BONE_INDEX[name]]))
