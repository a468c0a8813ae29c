"""Synthetic finger motion for the output tests (issue 44): a fist closing, without the solver.

Flexion turns each finger towards the palm (-Y at rest): about -Z for the left hand (its fingers point +X), +Z for
the right (-X); the thumb about the axis that turns its rest direction towards the palm. ``closure`` 0 is the flat
T-pose hand, 1 a fist (proximal 80°, intermediate 100°, distal 70°; the thumb 30°, 40°, 50°).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from mocapd.core.hand_skeleton import N_FINGER_BONES, THUMB_DIRECTION, HandPose, HandSkeleton
from mocapd.core.kinematics import Kinematics
from mocapd.core.rotations import quat_from_rotvec
from mocapd.core.skeleton import Skeleton
from mocapd.pipeline.scheduler import PersonPose

FloatArray = NDArray[np.float64]

FIST_DEG = (80.0, 100.0, 70.0)
THUMB_DEG = (30.0, 40.0, 50.0)


def flexion_axes(side: int) -> FloatArray:
    """(15, 3) unit axes of flexion of hand ``side`` (0 left, 1 right) in the parent bones' rest frames."""
    mirror = np.array([-1.0, 1.0, 1.0]) if side else np.ones(3)
    palm = np.array([0.0, -1.0, 0.0])
    thumb = np.cross(THUMB_DIRECTION * mirror, palm)
    finger = np.cross(np.array([1.0, 0.0, 0.0]) * mirror, palm)
    axes = np.array([thumb if b < 3 else finger for b in range(N_FINGER_BONES)])
    out: FloatArray = axes / np.linalg.norm(axes, axis=1, keepdims=True)
    return out


def fist_rotations(closure: float) -> FloatArray:
    """Local finger rotations (2, 15, 4) of both hands at ``closure`` (0 flat .. 1 fist)."""
    angles = np.radians([*THUMB_DEG, *(FIST_DEG * 4)]) * closure
    rotvec = np.stack([flexion_axes(h) * angles[:, None] for h in range(2)])
    out: FloatArray = quat_from_rotvec(rotvec)
    return out


def fist(closure: float, skeleton: HandSkeleton | None = None, present: tuple[bool, bool] = (True, True)) -> HandPose:
    """Both hands at ``closure``; a hand not ``present`` holds the rest pose."""
    rot = fist_rotations(closure)
    for h in range(2):
        if not present[h]:
            rot[h] = (1.0, 0.0, 0.0, 0.0)
    return HandPose(rot, np.array(present), skeleton if skeleton is not None else HandSkeleton.reference())


def closing(n: int) -> FloatArray:
    """Closure of a fist closing over ``n`` frames (eased, 0 to 1)."""
    out: FloatArray = 0.5 - 0.5 * np.cos(np.linspace(0.0, math.pi, n))
    return out


def person_with_fingers(identity: str, theta: FloatArray, skeleton: Skeleton, hands: HandPose | None, *,
                        track: int = 0, own: bool = False) -> PersonPose:  # fmt: skip
    """A solved person on ``skeleton`` (``own``: as a body-sized person's own skeleton) with these fingers."""
    joints = Kinematics(skeleton).forward(theta).positions
    return PersonPose(identity, track, None, theta, joints, 0.9, 3, 0, 4, True, skeleton if own else None,
                      hands=hands)  # fmt: skip
