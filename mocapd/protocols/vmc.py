"""VMC protocol (Virtual Motion Capture Protocol, OSC over UDP) output, as a "Performer" driving one avatar.

Receivers ("Marionettes") include EVMC4U (Unity), VMC4UE and VRM4U (Unreal), VSeeFace, VMagicMirror, Warudo and
VMC4B (Blender). Source followed: the VMC protocol specification (protocol.vmc.info, messages of versions 2.0 to
2.7) and its reference receiver EVMC4U's protocol notes; OSC encoding from :mod:`mocapd.protocols.osc`. The
default Marionette port is 39539. One avatar per receiver: the protocol has no character id.

Every output frame of one subject becomes one or more OSC bundles (time tag 1, "immediately"; each within
``max_datagram_bytes``, so one UDP datagram each) holding, in this order::

    /VMC/Ext/Root/Pos  s "root"  f p.x p.y p.z  f q.x q.y q.z q.w      the avatar root: the world origin, identity
    /VMC/Ext/Bone/Pos  s <HumanBodyBones name>  f p.x p.y p.z  f q.x q.y q.z q.w     × 22 bones (list below)
    /VMC/Ext/OK        i loaded=1  i calibration state=3 (calibrated)  i calibration mode=0 (normal)
                       i tracking status (1 = tracked this frame, 0 = not)         (the V2.7 form)
    /VMC/Ext/T         f seconds since the stream started (the first frame sent) of the instant this avatar's
                       pose is for (later than the frame's solve time for a predicted pose)

OK and T come last, in the last bundle, so receivers that apply a frame when they see them (VRM4U) apply it
after all its bones. A bone message is 76 bytes for "LeftUpperArm": address "/VMC/Ext/Bone/Pos" + 3 NUL (20),
type tags ",sfffffff" + 3 NUL (12), name + NULs (16), seven float32 (28), all big-endian; a frame is ~1.9 kB, so
at the default 1472-byte limit it is two bundles.

Frames and values: Unity's left-handed, +Y up, +Z forward frame in metres (:data:`mocapd.protocols.conventions.UNITY`:
x = −X of mocapd). ``p`` is the bone's ``localPosition`` (its joint relative to the parent bone's joint, in the
parent's frame) and ``q`` its ``localRotation`` (x, y, z, w), both relative to the parent bone as listed below, for
a rig whose bones all have identity rotation in the T-pose (a VRM-normalised humanoid; our rest pose is that
T-pose). Hips carries the world position and rotation (its parent is the root at the origin).

Bones (HumanBodyBones name ← mocapd bones; parent)::

    Hips ← Hips (root)             Spine ← Spine (Hips)           Chest ← Spine1 (Spine)
    UpperChest ← Spine2·Spine3 (Chest): the transform at Spine2's joint with Spine3's global rotation
    Neck ← Neck (UpperChest)       Head ← Head (Neck)
    LeftShoulder, RightShoulder (UpperChest): no mocapd bone; rigid with the chest (identity local rotation), at the
        mid-line point at the height and depth of the upper-arm joint (the MVN shoulder rule, mocapd.protocols.mvn)
    Left/RightUpperArm ← same (Shoulder)   Left/RightLowerArm ← same   Left/RightHand ← same
    Left/RightUpperLeg ← same (Hips)       Left/RightLowerLeg ← same   Left/RightFoot ← same   Left/RightToes ← same

A rig without UpperChest or shoulders simply ignores those messages (receivers skip bones the avatar lacks).

Fingers (issue 44): a subject with fingers (:class:`mocapd.core.hand_skeleton.HandPose`) also sends, after the 22
bones and for each hand solved this frame, its 15 finger bones under their HumanBodyBones names (parent)::

    Left/Right + Thumb/Index/Middle/Ring/Little + Proximal (Left/RightHand), Intermediate (Proximal),
    Distal (Intermediate)

each with ``localPosition`` its rest offset and ``localRotation`` its local rotation, in Unity's frame as above (a
Unity humanoid's fingers have identity rotation with the hand flat, fingers along the arm, as mocapd's rest). A hand
not solved this frame sends no finger bones (the avatar keeps its own). A subject without fingers sends exactly the
messages above.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from mocapd.core.hand_skeleton import FINGER_BONES, N_FINGER_BONES, SIDES, HandPose
from mocapd.core.per_skeleton import PerSkeleton
from mocapd.core.rotations import quat_conjugate, quat_from_rotvec, quat_multiply, quat_rotate
from mocapd.core.skeleton import BONE_INDEX, N_BONES, POSE_DIM, Skeleton
from mocapd.errors import InputError
from mocapd.protocols.conventions import UNITY
from mocapd.protocols.osc import encode_message, message_prefix, osc_string, pack_bundles

FloatArray = NDArray[np.float64]

DEFAULT_PORT = 39539
DEFAULT_MAX_DATAGRAM = 1472
BONE_ADDRESS = "/VMC/Ext/Bone/Pos"
ROOT_ADDRESS = "/VMC/Ext/Root/Pos"
OK_ADDRESS = "/VMC/Ext/OK"
TIME_ADDRESS = "/VMC/Ext/T"
CALIBRATED = 3
NORMAL_MODE = 0

# (HumanBodyBones name, parent name or None, mocapd bone giving the global rotation, mocapd bone giving the origin;
# None: the shoulder rule).
BONES: tuple[tuple[str, str | None, str, str | None], ...] = (
    ("Hips", None, "Hips", "Hips"),
    ("Spine", "Hips", "Spine", "Spine"),
    ("Chest", "Spine", "Spine1", "Spine1"),
    ("UpperChest", "Chest", "Spine3", "Spine2"),
    ("Neck", "UpperChest", "Neck", "Neck"),
    ("Head", "Neck", "Head", "Head"),
    ("LeftShoulder", "UpperChest", "Spine3", None),
    ("LeftUpperArm", "LeftShoulder", "LeftUpperArm", "LeftUpperArm"),
    ("LeftLowerArm", "LeftUpperArm", "LeftLowerArm", "LeftLowerArm"),
    ("LeftHand", "LeftLowerArm", "LeftHand", "LeftHand"),
    ("RightShoulder", "UpperChest", "Spine3", None),
    ("RightUpperArm", "RightShoulder", "RightUpperArm", "RightUpperArm"),
    ("RightLowerArm", "RightUpperArm", "RightLowerArm", "RightLowerArm"),
    ("RightHand", "RightLowerArm", "RightHand", "RightHand"),
    ("LeftUpperLeg", "Hips", "LeftUpperLeg", "LeftUpperLeg"),
    ("LeftLowerLeg", "LeftUpperLeg", "LeftLowerLeg", "LeftLowerLeg"),
    ("LeftFoot", "LeftLowerLeg", "LeftFoot", "LeftFoot"),
    ("LeftToes", "LeftFoot", "LeftToes", "LeftToes"),
    ("RightUpperLeg", "Hips", "RightUpperLeg", "RightUpperLeg"),
    ("RightLowerLeg", "RightUpperLeg", "RightLowerLeg", "RightLowerLeg"),
    ("RightFoot", "RightLowerLeg", "RightFoot", "RightFoot"),
    ("RightToes", "RightFoot", "RightToes", "RightToes"),
)
BONE_NAMES: tuple[str, ...] = tuple(b[0] for b in BONES)
N_VMC_BONES = len(BONES)
_NAME_INDEX = {b[0]: i for i, b in enumerate(BONES)}
_ROT_SRC = np.array([BONE_INDEX[r] for _, _, r, _ in BONES], dtype=np.intp)  # the local rotation's bone
_CLAVICLE_ARM = {_NAME_INDEX["LeftShoulder"]: "LeftUpperArm", _NAME_INDEX["RightShoulder"]: "RightUpperArm"}
_SHOULDER_IDX = np.array(sorted(_CLAVICLE_ARM), dtype=np.intp)
_UPPER_CHEST = _NAME_INDEX["UpperChest"]
_FLOATS = np.dtype(">f4")


class VmcBones:
    """Local bone transforms (Unity frame) of the VMC bone list from pose vectors of one sized skeleton.

    VMC is local, like θ, so no forward kinematics is needed: a bone's local rotation is its θ rotation (UpperChest:
    Spine2's then Spine3's; the shoulders: identity) and its local position is its rest offset, except where the
    merged UpperChest moves a child's joint: with the UpperChest transform at Spine2's joint and rotated by
    ``R_Spine3`` relative to Spine2, a child attached to Spine3 at offset ``o`` sits at ``R_Spine3ᵀ o_Spine3 + o``.
    """

    def __init__(self, skeleton: Skeleton) -> None:
        off = skeleton.offsets
        const = np.zeros((N_VMC_BONES, 3))
        self._after_spine3: list[tuple[int, FloatArray]] = []  # children of UpperChest: (VMC index, offset o)
        for i, (_, parent, _, origin) in enumerate(BONES):
            if origin is None:  # a shoulder: the mid-line point at the upper arm's height and depth
                o = off[BONE_INDEX[_CLAVICLE_ARM[i]]]
                self._after_spine3.append((i, np.array([0.0, o[1], o[2]])))
            elif parent == "UpperChest":
                self._after_spine3.append((i, off[BONE_INDEX[origin]].copy()))
            elif parent is not None and BONES[_NAME_INDEX[parent]][3] is None:  # an upper arm, from its shoulder
                o = off[BONE_INDEX[origin]]
                const[i] = [o[0], 0.0, 0.0]
            elif parent is not None:
                const[i] = off[BONE_INDEX[origin]]
        self._const = const
        self._o_spine3 = off[BONE_INDEX["Spine3"]].copy()

    def compute(self, thetas: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Local positions and rotations of the 22 VMC bones.

        Parameters
        ----------
        thetas : array, shape (n, 66)

        Returns
        -------
        positions : array, shape (n, 22, 3)
            ``localPosition`` in Unity's frame (metres); Hips: the world position.
        quaternions : array, shape (n, 22, 4)
            ``localRotation`` as (w, x, y, z) in Unity's frame (the wire order is x, y, z, w).
        """
        thetas = np.asarray(thetas, dtype=np.float64)
        if thetas.ndim != 2 or thetas.shape[1] != POSE_DIM:
            raise InputError(f"thetas must have shape (n, {POSE_DIM}), got {thetas.shape}")
        n = thetas.shape[0]
        q = quat_from_rotvec(thetas[:, 3:].reshape(n, N_BONES, 3))
        quats = q[:, _ROT_SRC]
        quats[:, _UPPER_CHEST] = quat_multiply(q[:, BONE_INDEX["Spine2"]], q[:, BONE_INDEX["Spine3"]])
        quats[:, _SHOULDER_IDX] = (1.0, 0.0, 0.0, 0.0)
        pos = np.broadcast_to(self._const, (n, N_VMC_BONES, 3)).copy()
        pos[:, 0] = thetas[:, :3]
        # R_Spine3ᵀ o_Spine3: Spine3's joint seen from the UpperChest transform.
        lifted = quat_rotate(quat_conjugate(q[:, BONE_INDEX["Spine3"]]), self._o_spine3)
        for i, o in self._after_spine3:
            pos[:, i] = lifted + o
        return UNITY.positions(pos), UNITY.quaternions(quats)


class VmcEncoder:
    """Encodes one subject's output frames into VMC bundles (pure: values in, bytes out).

    Parameters
    ----------
    skeleton : Skeleton
    max_datagram_bytes : int
        Largest bundle to produce; a frame is split over as many bundles as needed.
    """

    def __init__(self, skeleton: Skeleton, *, max_datagram_bytes: int = DEFAULT_MAX_DATAGRAM) -> None:
        self.bones = VmcBones(skeleton)
        self._sized = PerSkeleton(self.bones, VmcBones)  # per-person skeletons (body sizing)
        self.max_datagram_bytes = max_datagram_bytes
        self._prefixes = [message_prefix(BONE_ADDRESS, "sfffffff") + osc_string(name) for name in BONE_NAMES]
        self._finger_prefixes = [[message_prefix(BONE_ADDRESS, "sfffffff") + osc_string(side + bone)
                                  for bone in FINGER_BONES] for side in SIDES]  # fmt: skip
        self._root = encode_message(ROOT_ADDRESS, ["root", 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])
        self._t0_ns: int | None = None
        # Fail now, not per frame, when the limit cannot hold the largest message.
        pack_bundles([*(p + bytes(28) for p in self._prefixes), self._root], max_datagram_bytes)

    def seconds(self, t_ns: int) -> float:
        """Seconds since the first frame encoded (the stream's start)."""
        if self._t0_ns is None:
            self._t0_ns = t_ns
        return (t_ns - self._t0_ns) / 1e9

    def encode_many(
        self,
        t_ns: int,
        thetas: FloatArray,
        tracked: list[bool],
        skeletons: Sequence[Skeleton | None] | None = None,
        times_ns: Sequence[int] | None = None,
        hands: Sequence[HandPose | None] | None = None,
    ) -> list[list[bytes]]:
        """Bundles for several subjects of one frame (one list of bundles per subject, each for its own avatar).

        Parameters
        ----------
        t_ns : int
            Solve time of the frame (host monotonic ns).
        thetas : array, shape (n, 66)
        tracked : list of bool, length n
            The tracking status sent in /VMC/Ext/OK.
        skeletons : sequence of Skeleton or None, optional
            Each subject's own sized skeleton (None, or no sequence: the encoder's).
        times_ns : sequence of int, optional
            The instant each subject's pose is for (host ns; default ``t_ns``), sent as its ``/VMC/Ext/T``.
        hands : sequence of HandPose or None, optional
            Each subject's fingers (None: none; its bundles are as without fingers).
        """
        t = self.seconds(t_ns)
        thetas = np.asarray(thetas, dtype=np.float64).reshape(-1, POSE_DIM)
        if len(tracked) != thetas.shape[0]:
            raise InputError(f"tracked has {len(tracked)} entries for {thetas.shape[0]} subjects")
        if thetas.shape[0] == 0:
            return []
        if skeletons is None or all(sk is None for sk in skeletons):
            pos, quat = self.bones.compute(thetas)
        else:
            parts = [self._sized.get(sk).compute(th[None]) for sk, th in zip(skeletons, thetas, strict=True)]
            pos, quat = np.concatenate([a for a, _ in parts]), np.concatenate([b for _, b in parts])
        values = np.empty((thetas.shape[0], N_VMC_BONES, 7), dtype=_FLOATS)
        values[..., 0:3] = pos
        values[..., 3:6] = quat[..., 1:4]
        values[..., 6] = quat[..., 0]
        if times_ns is not None and len(times_ns) != thetas.shape[0]:
            raise InputError(f"VMC: {len(times_ns)} time stamps for {thetas.shape[0]} subjects")
        out = []
        for k in range(thetas.shape[0]):
            time_msg = encode_message(TIME_ADDRESS, [t if times_ns is None else self.seconds(times_ns[k])])
            raw = values[k].tobytes()
            msgs = [self._root]
            msgs += [p + raw[28 * i : 28 * i + 28] for i, p in enumerate(self._prefixes)]
            if hands is not None and hands[k] is not None:
                msgs += self._finger_messages(hands[k])
            msgs.append(encode_message(OK_ADDRESS, [1, CALIBRATED, NORMAL_MODE, int(tracked[k])]))
            msgs.append(time_msg)
            out.append(pack_bundles(msgs, self.max_datagram_bytes))
        return out

    def _finger_messages(self, hands: HandPose | None) -> list[bytes]:
        """The finger bone messages of the hands present (local position and rotation, Unity's frame)."""
        if hands is None:
            return []
        values = np.empty((2, N_FINGER_BONES, 7), dtype=_FLOATS)
        values[..., 0:3] = UNITY.positions(hands.skeleton.offsets)
        q = UNITY.quaternions(hands.rotations)
        values[..., 3:6] = q[..., 1:4]
        values[..., 6] = q[..., 0]
        out = []
        for h in range(2):
            if hands.present[h]:
                raw = values[h].tobytes()
                out += [p + raw[28 * i : 28 * i + 28] for i, p in enumerate(self._finger_prefixes[h])]
        return out

    def encode(self, t_ns: int, theta: FloatArray, tracked: bool = True) -> list[bytes]:
        """Bundles for one subject's frame (see :meth:`encode_many`)."""
        return self.encode_many(t_ns, np.asarray(theta, dtype=np.float64)[None, :], [tracked])[0]
