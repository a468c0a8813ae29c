"""The fingers of a published pose as every outgoing stream and file needs them (pure; issue 44).

A subject's fingers are an optional :class:`~mocapd.core.hand_skeleton.HandPose`: per hand (left, right) the 15
finger bones' local rotations from rest (w, x, y, z) on a sized :class:`~mocapd.core.hand_skeleton.HandSkeleton`,
and whether the hand was solved this frame. A hand not present holds the rest pose (straight fingers, rigid with the
hand). This module extends the 21 body bones by the 30 finger bones where a format has one list of bones:

- **Extended bone list** (glTF, BVH, FBX, the WebSocket hello): the 21 body bones (DESIGN.md), then the 30 finger
  bones of :data:`~mocapd.core.hand_skeleton.HAND_BONE_NAMES` (left hand then right, thumb to little finger,
  proximal to distal); each proximal bone's parent is the body's ``LeftHand``/``RightHand``, the others the bone
  before. Indices 0..20 keep their meaning.
- **Forward kinematics** of the fingers on top of the body's (:func:`finger_kinematics`): a finger bone's global
  rotation ``G = G_parent · L`` and joint ``x = x_parent + G_parent · offset``, as the body's; each fingertip is its
  distal bone's joint plus ``G_distal · tip``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mocapd.core.hand_skeleton import (
    FINGER_PARENTS,
    HAND_BONE_NAMES,
    N_FINGER_BONES,
    SIDES,
    HandPose,
    HandSkeleton,
    hand_bone_index,
)
from mocapd.core.kinematics import Kinematics
from mocapd.core.rotations import matrix_from_quat
from mocapd.core.skeleton import BONE_NAMES, N_BONES, PARENTS, POSE_DIM, Skeleton

FloatArray = NDArray[np.float64]

N_HAND_BONES = 2 * N_FINGER_BONES  # 30
HAND_OF_SIDE: tuple[int, int] = (hand_bone_index(SIDES[0]), hand_bone_index(SIDES[1]))
"""Body bone index of the left and the right hand (9, 12)."""
EXTENDED_BONE_NAMES: tuple[str, ...] = (*BONE_NAMES, *HAND_BONE_NAMES)
"""The 51 bones of a skeleton with fingers (see the module doc)."""
EXTENDED_PARENTS: tuple[int, ...] = (
    *PARENTS,
    *(HAND_OF_SIDE[h] if p < 0 else N_BONES + N_FINGER_BONES * h + p for h in range(2) for p in FINGER_PARENTS),
)
"""Parent of each of the 51 bones (-1 for the root)."""
N_EXTENDED = len(EXTENDED_BONE_NAMES)
MIDDLE_PROXIMAL = 6
"""Index of ``MiddleProximal`` within a hand: the knuckle a hand bone is drawn towards when it has fingers."""
DISTAL_TIP: tuple[tuple[int, int], ...] = tuple((3 * f + 2, f) for f in range(5))
"""(finger bone, tip index) of each distal bone: the bones whose end is a fingertip."""


def extended_offsets(offsets: FloatArray, hands: HandSkeleton) -> FloatArray:
    """Rest offsets of the 51 bones, shape (51, 3): the body's (21, 3) then the hands' (2 × 15, 3)."""
    return np.concatenate([np.asarray(offsets, dtype=np.float64), hands.offsets.reshape(N_HAND_BONES, 3)])


def leaf_ends(offsets: FloatArray, hands: HandSkeleton, end_fraction: float) -> dict[int, FloatArray]:
    """Where each leaf of the extended skeleton ends, in its own frame: the fingertips for the distal bones and
    ``end_fraction`` of the bone's own offset for the body's leaves (Head, toes; the hands have children)."""
    ext = extended_offsets(offsets, hands)
    ends: dict[int, FloatArray] = {}
    for b in range(N_EXTENDED):
        if b in EXTENDED_PARENTS:
            continue
        ends[b] = end_fraction * ext[b]
    for h in range(2):
        for bone, tip in DISTAL_TIP:
            ends[N_BONES + N_FINGER_BONES * h + bone] = hands.tips[h, tip].copy()
    return ends


def tail_child(parents: Sequence[int], b: int) -> int | None:
    """The child a bone is drawn towards: the first one, except a hand with fingers: its middle finger's knuckle."""
    if b in HAND_OF_SIDE and len(parents) == N_EXTENDED:
        return N_BONES + N_FINGER_BONES * HAND_OF_SIDE.index(b) + MIDDLE_PROXIMAL
    return next((c for c in range(len(parents)) if parents[c] == b), None)


@dataclass(frozen=True)
class FingerState:
    """Finger forward kinematics of a batch of subjects.

    Attributes
    ----------
    rotations : array, shape (n, 2, 15, 3, 3)
        Global rotation of each finger bone (bone frame -> world).
    positions : array, shape (n, 2, 15, 3)
        Each finger bone's joint, world (metres).
    tips : array, shape (n, 2, 5, 3)
        Each fingertip, world (metres).
    """

    rotations: FloatArray
    positions: FloatArray
    tips: FloatArray


def finger_kinematics(
    hand_rotations: FloatArray, hand_positions: FloatArray, local: FloatArray, skeletons: Sequence[HandSkeleton]
) -> FingerState:
    """Forward kinematics of the fingers from their hands' global transforms.

    Parameters
    ----------
    hand_rotations : array, shape (n, 2, 3, 3)
        Global rotation of the body's left and right hand bones.
    hand_positions : array, shape (n, 2, 3)
        Their joints (the wrists), world.
    local : array, shape (n, 2, 15, 4)
        The finger bones' local rotations (w, x, y, z), :attr:`HandPose.rotations`.
    skeletons : sequence of HandSkeleton, length n
    """
    n = local.shape[0]
    offsets = np.stack([s.offsets for s in skeletons]) if n else np.zeros((0, 2, N_FINGER_BONES, 3))
    tip_offsets = np.stack([s.tips for s in skeletons]) if n else np.zeros((0, 2, 5, 3))
    L = matrix_from_quat(np.asarray(local, dtype=np.float64))
    G = np.empty((n, 2, N_FINGER_BONES, 3, 3))
    x = np.empty((n, 2, N_FINGER_BONES, 3))
    for b, p in enumerate(FINGER_PARENTS):
        Gp = hand_rotations if p < 0 else G[:, :, p]
        xp = hand_positions if p < 0 else x[:, :, p]
        x[:, :, b] = xp + np.einsum("nhij,nhj->nhi", Gp, offsets[:, :, b])
        G[:, :, b] = Gp @ L[:, :, b]
    distal = [bone for bone, _ in DISTAL_TIP]
    tips = x[:, :, distal] + np.einsum("nhfij,nhfj->nhfi", G[:, :, distal], tip_offsets)
    return FingerState(G, x, tips)


def hands_of(people: Sequence[object]) -> list[HandPose | None]:
    """Each subject's fingers (its ``hands`` attribute, None where it has none)."""
    out: list[HandPose | None] = []
    for p in people:
        h = getattr(p, "hands", None)
        out.append(h if isinstance(h, HandPose) else None)
    return out


def subject_fingers(thetas: FloatArray, skeletons: Sequence[Skeleton], hands: Sequence[HandPose]) -> FingerState:
    """Finger forward kinematics of subjects from their pose vectors (n, 66), body skeletons and hands."""
    thetas = np.asarray(thetas, dtype=np.float64).reshape(-1, POSE_DIM)
    rot = np.empty((len(hands), 2, 3, 3))
    pos = np.empty((len(hands), 2, 3))
    for k, (theta, sk) in enumerate(zip(thetas, skeletons, strict=True)):
        fk = Kinematics(sk).forward(theta)
        rot[k], pos[k] = fk.rotations[list(HAND_OF_SIDE)], fk.positions[list(HAND_OF_SIDE)]
    local = np.stack([h.rotations for h in hands]) if hands else np.zeros((0, 2, N_FINGER_BONES, 4))
    return finger_kinematics(rot, pos, local, [h.skeleton for h in hands])


__all__ = [
    "EXTENDED_BONE_NAMES",
    "EXTENDED_PARENTS",
    "HAND_OF_SIDE",
    "N_EXTENDED",
    "N_HAND_BONES",
    "FingerState",
    "extended_offsets",
    "finger_kinematics",
    "hands_of",
    "leaf_ends",
    "subject_fingers",
    "tail_child",
]
