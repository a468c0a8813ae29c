"""The optional hand skeleton: three bones per finger per hand, their names, rest offsets and the solved pose.

Bones (per hand, index = position in every array of this module; ``Left``/``Right`` prefix for the Unity name)::

     0 ThumbProximal   1 ThumbIntermediate   2 ThumbDistal
     3 IndexProximal   4 IndexIntermediate   5 IndexDistal
     6 MiddleProximal  7 MiddleIntermediate  8 MiddleDistal
     9 RingProximal   10 RingIntermediate   11 RingDistal
    12 LittleProximal 13 LittleIntermediate 14 LittleDistal

These are Unity's ``HumanBodyBones`` names (``LeftThumbProximal`` ... ``RightLittleDistal``); :data:`VRM1_NAMES`
and :data:`VRM0_NAMES` give the VRM humanoid names of the same bones (VRM 1.0 calls the thumb's three bones
``Metacarpal``/``Proximal``/``Distal``, VRM 0.x as Unity). Each finger's proximal bone hangs from the body's
``LeftHand``/``RightHand`` bone; the next two from the one before.

Frames follow the body (:mod:`mocapd.core.skeleton`): at rest (T-pose facing +Z, palms down) every bone frame is
the world's axes, a bone's *offset* is its joint in its parent's frame, and a bone's local rotation is its rotation
from rest in its parent's frame (identity = the flat hand of the T-pose, fingers straight along the forearm, the
thumb forward and out at 45° in the palm's plane). The left hand's fingers point +X, the right hand's -X; the
back of both hands faces +Y, the thumbs +Z. Each bone's joint is where the 21 hand landmarks of MediaPipe
(:data:`HAND21`) put it: thumb CMC, MCP, IP; finger MCP, PIP, DIP; the ``tips`` are the fifth landmark of each
finger, an offset in the distal bone.

Sizes (1.75 m reference, metres): the hand's length (wrist to the middle fingertip) is 0.108 of stature and the
forearm's 0.146 (Drillis & Contini 1966, as tabled in Winter, *Biomechanics and Motor Control of Human Movement*,
4th ed. 2009, Fig. 4.1), so a sized person's hand is :data:`HAND_PER_FOREARM` times their forearm. The fingers'
lengths relative to the middle finger are the means of Chatzıoglou, Pınar & Govsa 2024 (Anat Cell Biol 57(2),
172-182; 51 adults: thumb 49.5, index 63.9, middle 70.7, ring 65.5, little 53.3 mm, crease to tip); the middle
finger's joint-centre length (MCP to tip) is 0.49 of the hand's length and each finger splits 0.48/0.29/0.23 over
its three segments (the thumb 0.55/0.45 over its two phalanges after a 4.6 cm metacarpal): rounded, hand-set
proportions of the kind hand models use, not a measured table. The per-person scale is refined from the hand
keypoints by :mod:`mocapd.core.hand_solver`.

Pure: no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mocapd.core.keypoints import HAND21
from mocapd.core.skeleton import BONE_INDEX, REFERENCE_HEIGHT, Skeleton
from mocapd.errors import InputError

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

SIDES: tuple[str, str] = ("Left", "Right")
"""Hand order in every per-hand array (axis 0)."""
FINGERS: tuple[str, ...] = ("Thumb", "Index", "Middle", "Ring", "Little")
SEGMENTS: tuple[str, str, str] = ("Proximal", "Intermediate", "Distal")

FINGER_BONES: tuple[str, ...] = tuple(f + s for f in FINGERS for s in SEGMENTS)
"""The 15 bones of one hand without the side prefix, in array order."""
N_FINGER_BONES = len(FINGER_BONES)
FINGER_PARENTS: tuple[int, ...] = tuple(-1 if i % 3 == 0 else i - 1 for i in range(N_FINGER_BONES))
"""Parent of each finger bone within the hand; -1: the body's hand bone (:data:`HAND_BONES`)."""
HAND_BONES: Mapping[str, str] = {"Left": "LeftHand", "Right": "RightHand"}
"""The body bone (:data:`mocapd.core.skeleton.BONE_NAMES`) each hand's proximal bones hang from."""

HAND_BONE_NAMES: tuple[str, ...] = tuple(side + b for side in SIDES for b in FINGER_BONES)
"""The 30 Unity HumanBodyBones names, left hand then right (``LeftThumbProximal`` ... ``RightLittleDistal``)."""


def _vrm(side: str, finger: str, segment: str, version: int) -> str:
    if version == 1 and finger == "Thumb":
        segment = {"Proximal": "Metacarpal", "Intermediate": "Proximal", "Distal": "Distal"}[segment]
    return f"{side.lower()}{finger}{segment}"


VRM1_NAMES: Mapping[str, str] = {side + f + s: _vrm(side, f, s, 1) for side in SIDES for f in FINGERS for s in SEGMENTS}
"""Unity name -> VRM 1.0 humanoid bone name (``LeftThumbProximal`` -> ``leftThumbMetacarpal``)."""
VRM0_NAMES: Mapping[str, str] = {side + f + s: _vrm(side, f, s, 0) for side in SIDES for f in FINGERS for s in SEGMENTS}
"""Unity name -> VRM 0.x humanoid bone name (``LeftThumbProximal`` -> ``leftThumbProximal``)."""

N_HAND_KEYPOINTS = len(HAND21)  # MediaPipe's landmarks, :data:`mocapd.core.keypoints.HAND21`
LANDMARK_BONE: tuple[int, ...] = (-1, *(3 * f + j if j < 3 else 3 * f + 2 for f in range(5) for j in range(4)))
"""Per landmark: the finger bone it sits on (-1: the wrist, the hand bone's origin)."""
LANDMARK_IS_TIP: tuple[bool, ...] = (False, *(j == 3 for _ in range(5) for j in range(4)))
"""Per landmark: a fingertip (an offset in its distal bone, :attr:`HandSkeleton.tips`) rather than a bone's joint."""

HAND_PER_HEIGHT = 0.108
"""Hand length (wrist crease to the middle fingertip) per stature (Drillis & Contini 1966; Winter 2009)."""
FOREARM_PER_HEIGHT = 0.146
"""Forearm length (elbow to wrist) per stature (same source)."""
HAND_PER_FOREARM = HAND_PER_HEIGHT / FOREARM_PER_HEIGHT
REFERENCE_HAND_LENGTH = HAND_PER_HEIGHT * REFERENCE_HEIGHT  # 0.189 m

_FINGER_PER_MIDDLE = {"Thumb": 49.5 / 70.7, "Index": 63.9 / 70.7, "Middle": 1.0, "Ring": 65.5 / 70.7,
                      "Little": 53.3 / 70.7}  # fmt: skip
_MIDDLE_PER_HAND = 0.49  # MCP joint centre to the tip, per hand length
_SPLIT = (0.48, 0.29, 0.23)  # proximal, intermediate, distal-to-tip
_THUMB_SPLIT = (0.55, 0.45)  # the thumb's MCP to IP, IP to tip
_THUMB_METACARPAL = 0.046  # CMC to MCP at the reference size (m): the thumb's first bone is its metacarpal
# Where each finger's first joint sits in the left hand's frame (m, reference size): MCPs across the knuckles
# (a palm 8.5 cm wide), slightly behind the middle one on either side; the thumb's CMC near the wrist.
_BASE = {
    "Thumb": (0.030, -0.012, 0.022),
    "Index": (0.090, 0.0, 0.026),
    "Middle": (0.093, 0.0, 0.006),
    "Ring": (0.088, 0.0, -0.013),
    "Little": (0.080, 0.0, -0.031),
}
THUMB_DIRECTION: FloatArray = np.array([1.0, 0.0, 1.0]) / math.sqrt(2.0)
"""The left thumb's direction at rest in the hand's frame (the right's is mirrored in x)."""


def _reference_left() -> tuple[FloatArray, FloatArray]:
    """Offsets (15, 3) and tips (5, 3) of the left hand at the reference size."""
    offsets = np.zeros((N_FINGER_BONES, 3))
    tips = np.zeros((5, 3))
    middle = _MIDDLE_PER_HAND * REFERENCE_HAND_LENGTH
    for f, finger in enumerate(FINGERS):
        length = _FINGER_PER_MIDDLE[finger] * middle  # the first joint after the base to the tip
        if finger == "Thumb":
            direction = THUMB_DIRECTION
            segments = (_THUMB_METACARPAL, *(length * s for s in _THUMB_SPLIT))
        else:
            direction = np.array([1.0, 0.0, 0.0])
            segments = tuple(length * s for s in _SPLIT)
        offsets[3 * f] = _BASE[finger]
        offsets[3 * f + 1] = direction * segments[0]
        offsets[3 * f + 2] = direction * segments[1]
        tips[f] = direction * segments[2]
    return offsets, tips


_REF_OFFSETS, _REF_TIPS = _reference_left()
_MIRROR = np.array([-1.0, 1.0, 1.0])


@dataclass(frozen=True)
class HandSkeleton:
    """Both hands of one person, sized.

    Attributes
    ----------
    offsets : array, shape (2, 15, 3)
        Per hand (:data:`SIDES`), each finger bone's joint in its parent's frame at rest (metres); a proximal
        bone's parent is the body's hand bone (its origin the wrist).
    tips : array, shape (2, 5, 3)
        Each finger's tip in its distal bone's frame (metres).
    scale : array, shape (2,)
        Each hand's size relative to the reference hand (0.189 m long), informative.
    """

    offsets: FloatArray
    tips: FloatArray
    scale: FloatArray

    def __post_init__(self) -> None:
        offsets = np.array(self.offsets, dtype=np.float64)
        tips = np.array(self.tips, dtype=np.float64)
        scale = np.array(self.scale, dtype=np.float64)
        if offsets.shape != (2, N_FINGER_BONES, 3) or tips.shape != (2, 5, 3) or scale.shape != (2,):
            raise InputError(f"hand skeleton: offsets (2, 15, 3), tips (2, 5, 3), scale (2,) expected; got "
                             f"{offsets.shape}, {tips.shape}, {scale.shape}")  # fmt: skip
        if not (np.all(np.isfinite(offsets)) and np.all(np.isfinite(tips)) and np.all(np.isfinite(scale))):
            raise InputError("hand skeleton holds non-finite values")
        for a in (offsets, tips, scale):
            a.setflags(write=False)
        object.__setattr__(self, "offsets", offsets)
        object.__setattr__(self, "tips", tips)
        object.__setattr__(self, "scale", scale)

    @classmethod
    def reference(cls, scale: tuple[float, float] = (1.0, 1.0)) -> HandSkeleton:
        """The reference hands (a 1.75 m person's) scaled by ``scale`` (left, right)."""
        for s in scale:
            if not (math.isfinite(s) and 0.4 <= s <= 1.6):
                raise InputError(f"hand scale must be within [0.4, 1.6], got {s!r}")
        left, right = scale
        return cls(
            offsets=np.stack([_REF_OFFSETS * left, _REF_OFFSETS * _MIRROR * right]),
            tips=np.stack([_REF_TIPS * left, _REF_TIPS * _MIRROR * right]),
            scale=np.array([left, right]),
        )

    @classmethod
    def from_body(cls, skeleton: Skeleton) -> HandSkeleton:
        """Hands sized from the body: :data:`HAND_PER_FOREARM` times each forearm (``LeftHand``'s offset)."""
        scale = [HAND_PER_FOREARM * skeleton.bone_length(HAND_BONES[side]) / REFERENCE_HAND_LENGTH for side in SIDES]
        return cls.reference((float(np.clip(scale[0], 0.4, 1.6)), float(np.clip(scale[1], 0.4, 1.6))))

    def rescaled(self, side: int, factor: float) -> HandSkeleton:
        """The same hands with hand ``side`` (0 left, 1 right) scaled by ``factor`` (a refined size)."""
        new = float(self.scale[side] * factor)
        scale = (new, float(self.scale[1])) if side == 0 else (float(self.scale[0]), new)
        return HandSkeleton.reference(scale)

    def length(self, side: int) -> float:
        """Hand length (m, wrist to the middle fingertip at rest) of hand ``side``."""
        return float(self.scale[side] * REFERENCE_HAND_LENGTH)


@dataclass(frozen=True)
class HandPose:
    """The fingers of one solved person (the optional ``hands`` of a published pose).

    Attributes
    ----------
    rotations : array, shape (2, 15, 4)
        Per hand (:data:`SIDES`) and finger bone (:data:`FINGER_BONES`): the local rotation from rest in the
        parent's frame, unit quaternion (w, x, y, z). A hand not present holds identity (the rest pose).
    present : bool array, shape (2,)
        Whether each hand was solved from keypoints this frame.
    skeleton : HandSkeleton
        The hands' rest offsets the rotations are on.
    """

    rotations: FloatArray
    present: BoolArray
    skeleton: HandSkeleton

    def __post_init__(self) -> None:
        rotations = np.asarray(self.rotations, dtype=np.float64)
        present = np.asarray(self.present, dtype=bool)
        if rotations.shape != (2, N_FINGER_BONES, 4) or present.shape != (2,):
            raise InputError(f"hand pose: rotations (2, 15, 4) and present (2,) expected; got {rotations.shape} "
                             f"and {present.shape}")  # fmt: skip
        if not np.all(np.isfinite(rotations)):
            raise InputError("hand pose rotations contain non-finite values")
        object.__setattr__(self, "rotations", rotations)
        object.__setattr__(self, "present", present)

    @classmethod
    def rest(cls, skeleton: HandSkeleton) -> HandPose:
        """Both hands flat (the T-pose's), not present."""
        rotations = np.zeros((2, N_FINGER_BONES, 4))
        rotations[..., 0] = 1.0
        return cls(rotations, np.zeros(2, dtype=bool), skeleton)

    def named(self) -> dict[str, FloatArray]:
        """Unity bone name -> local rotation (4,) of the hands present."""
        return {
            side + bone: self.rotations[h, b]
            for h, side in enumerate(SIDES)
            if self.present[h]
            for b, bone in enumerate(FINGER_BONES)
        }


def hand_bone_index(side: str) -> int:
    """The body bone index (:data:`mocapd.core.skeleton.BONE_INDEX`) hand ``side`` ("Left"/"Right") hangs from."""
    return BONE_INDEX[HAND_BONES[side]]
