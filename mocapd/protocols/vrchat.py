"""VRChat OSC trackers output: one subject's solved body as VRChat's eight full-body trackers and its head (pure).

Source followed: VRChat's documentation page "OSC Trackers" (docs.vrchat.com/docs/osc-trackers) and its linked
Unity sender example (the ``OscTrackerSenderExample`` gist): VRChat listens on UDP port 9000 for::

    /tracking/trackers/1/position    f x  f y  f z     world position, metres, Unity frame
    /tracking/trackers/1/rotation    f x  f y  f z     world rotation, Euler angles in degrees (Unity's order)
    ...  up to /tracking/trackers/8/...
    /tracking/trackers/head/position, /tracking/trackers/head/rotation   optional: lets VRChat align the sender's
                                                                          tracking space with the headset's

Up to eight trackers: hip, chest, both feet, both knees, both elbows (upper arms). VRChat assigns body parts to
trackers at its own calibration, by where they are, so the numbers are only names; mocapd gives each role a fixed
number (below). The documentation advises that fewer trackers (e.g. hip and feet) can work better: which ones are
sent is configurable.

Frame and values (:data:`mocapd.protocols.conventions.UNITY`: left-handed, +Y up, x = −X of mocapd, metres):
a position ``p`` maps to ``s · C p`` and a rotation ``R`` to ``C R Cᵀ``, with ``s = user height / skeleton
height`` ("scaled such that 1.0 = 1 m in real-world space": the solved skeleton's metres become the user's).
Euler angles are Unity's ``Transform.eulerAngles`` convention: ``R = Ry(y) · Rx(x) · Rz(z)`` (rotation about Z
first, then X, then Y), each angle in degrees in (−180, 180].

Trackers (role: number, position, rotation from the solved skeleton)::

    hip          1   Hips joint                  Hips bone
    chest        2   Spine3 joint (upper chest)  Spine3 bone
    left_foot    3   LeftFoot joint (ankle)      LeftFoot bone        right_foot   4   likewise
    left_knee    5   LeftLowerLeg joint (knee)   LeftLowerLeg bone    right_knee   6   likewise
    left_elbow   7   LeftLowerArm joint (elbow)  LeftUpperArm bone    right_elbow  8   likewise
    head             between the eye keypoints   Head bone            (where a headset sits)

One output frame is one OSC bundle (time tag "immediately"), position before rotation for each tracker; with
all nine it is about 850 bytes.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from mocapd.core.keypoints import coco17_targets
from mocapd.core.kinematics import Kinematics
from mocapd.core.per_skeleton import PerSkeleton
from mocapd.core.skeleton import BONE_INDEX, POSE_DIM, Skeleton
from mocapd.errors import InputError
from mocapd.protocols.conventions import UNITY
from mocapd.protocols.osc import encode_bundle, encode_message

FloatArray = NDArray[np.float64]

DEFAULT_PORT = 9000
#: role -> (tracker number, bone whose joint is the position, bone whose global rotation is the rotation)
TRACKERS: dict[str, tuple[int, str, str]] = {
    "hip": (1, "Hips", "Hips"),
    "chest": (2, "Spine3", "Spine3"),
    "left_foot": (3, "LeftFoot", "LeftFoot"),
    "right_foot": (4, "RightFoot", "RightFoot"),
    "left_knee": (5, "LeftLowerLeg", "LeftLowerLeg"),
    "right_knee": (6, "RightLowerLeg", "RightLowerLeg"),
    "left_elbow": (7, "LeftLowerArm", "LeftUpperArm"),
    "right_elbow": (8, "RightLowerArm", "RightUpperArm"),
}
HEAD = "head"
ROLES = (*TRACKERS, HEAD)


def unity_euler_deg(R: FloatArray) -> FloatArray:
    """Unity Euler angles (x, y, z) in degrees of rotation matrices ``R = Ry(y) Rx(x) Rz(z)``; (..., 3, 3) → (..., 3).

    At the gimbal lock (x = ±90°) z is set to 0 and y carries the whole turn about the vertical.
    """
    R = np.asarray(R, dtype=np.float64)
    sx = np.clip(-R[..., 1, 2], -1.0, 1.0)
    x = np.arcsin(sx)
    locked = np.abs(sx) > 1.0 - 1e-9
    y = np.where(locked, np.arctan2(-R[..., 2, 0], R[..., 0, 0]), np.arctan2(R[..., 0, 2], R[..., 2, 2]))
    z = np.where(locked, 0.0, np.arctan2(R[..., 1, 0], R[..., 1, 1]))
    out: FloatArray = np.degrees(np.stack([x, y, z], axis=-1))
    return out


class _Parts:
    """Forward kinematics and the eye sites of one skeleton."""

    def __init__(self, skeleton: Skeleton) -> None:
        self.kin = Kinematics(skeleton)
        targets = coco17_targets(skeleton)
        eyes = [targets.names.index("left_eye"), targets.names.index("right_eye")]
        self.eye_bones = targets.bones[eyes]
        self.eye_offsets = targets.offsets[eyes]
        self.height = skeleton.height


class VrChatEncoder:
    """One subject's frames → one OSC bundle of VRChat tracker messages (values in, bytes out).

    Parameters
    ----------
    skeleton : Skeleton
        The skeleton of the solved pose vectors (a person's own sized skeleton can be given per frame).
    roles : sequence of str
        Which trackers to send, from :data:`ROLES` (``"head"`` included).
    user_height_m : float or None
        The user's real height; positions are scaled by it over the skeleton's height. None: the skeleton's own
        height (scale 1, right when body sizing has fitted the skeleton to the person).
    """

    def __init__(self, skeleton: Skeleton, *, roles: Sequence[str] = ROLES, user_height_m: float | None = None) -> None:
        unknown = sorted(set(roles) - set(ROLES))
        if unknown or not roles or len(set(roles)) != len(roles):
            raise InputError(f"VRChat trackers {list(roles)!r}: unknown {unknown} or repeated; choose from {ROLES}")
        if user_height_m is not None and not (math.isfinite(user_height_m) and 0.5 <= user_height_m <= 2.5):
            raise InputError(f"user height {user_height_m!r} m: allowed 0.5..2.5 m")
        self.roles = tuple(r for r in ROLES if r in roles)  # the documented order
        self.user_height_m = user_height_m
        self._parts = PerSkeleton(_Parts(skeleton), _Parts)
        body = [r for r in self.roles if r != HEAD]
        self._pos_bones = np.array([BONE_INDEX[TRACKERS[r][1]] for r in body], dtype=np.intp)
        self._rot_bones = np.array([BONE_INDEX[TRACKERS[r][2]] for r in body], dtype=np.intp)
        self._head = HEAD in self.roles
        names = [str(TRACKERS[r][0]) if r != HEAD else HEAD for r in self.roles]
        self._addresses = [(f"/tracking/trackers/{n}/position", f"/tracking/trackers/{n}/rotation") for n in names]

    def trackers(self, theta: FloatArray, skeleton: Skeleton | None = None) -> tuple[FloatArray, FloatArray]:
        """Positions (n, 3) in metres and Euler angles (n, 3) in degrees, Unity frame, in :attr:`roles` order."""
        theta = np.asarray(theta, dtype=np.float64)
        if theta.shape != (POSE_DIM,) or not np.all(np.isfinite(theta)):
            raise InputError(f"theta must be finite with shape ({POSE_DIM},), got {theta.shape}")
        parts = self._parts.get(skeleton)
        fk = parts.kin.forward(theta)
        pos = fk.positions[self._pos_bones]
        rot = fk.rotations[self._rot_bones]
        if self._head:
            eyes = parts.kin.targets(fk, parts.eye_bones, parts.eye_offsets)
            pos = np.concatenate([pos, eyes.mean(axis=0)[None]])
            rot = np.concatenate([rot, fk.rotations[BONE_INDEX["Head"]][None]])
        scale = 1.0 if self.user_height_m is None else self.user_height_m / parts.height
        return UNITY.positions(pos) * scale, unity_euler_deg(UNITY.matrices(rot))

    def encode(self, theta: FloatArray, skeleton: Skeleton | None = None) -> bytes:
        """One bundle: position then rotation of every tracker sent."""
        pos, euler = self.trackers(theta, skeleton)
        msgs = []
        for (a_pos, a_rot), p, e in zip(self._addresses, pos, euler, strict=True):
            msgs.append(encode_message(a_pos, [float(v) for v in p]))
            msgs.append(encode_message(a_rot, [float(v) for v in e]))
        return encode_bundle(msgs)
