"""Rokoko Studio Live, "JSON v3" over UDP: the stream Rokoko's open-source Studio Live plugins read (pure).

Consumers: the Rokoko Studio Live plugins for Unity, Unreal Engine (Live Link), Blender, Cinema 4D and others, each
listening on UDP port 14043 by default. Sources followed (public, read, nothing copied; their parsing code is not
used by mocapd or its tests):

- Unity plugin ``Rokoko/rokoko-studio-live-unity`` at commit 0252b35 (plugin 2.0.2, June 2024):
  ``Scripts/Core/JsonLiveSerializerV3.cs`` (the ``LiveFrame_v4`` / ``SceneFrame`` / ``ActorFrame`` / ``BodyFrame``
  field names and types), ``StudioReceiver.cs`` (every datagram is LZ4-decompressed, then parsed with Unity's
  ``JsonUtility``), ``Mono/Inputs/Actor.cs`` (each body joint carries the bone's *world* rotation in Unity's frame
  and the Smartsuit T-pose table ``SmartsuitTPose``; hips also their world position, lowered by
  ``dimensions.hipHeight`` minus the model's), ``StudioManager.cs`` (``scene.actors`` and ``scene.props`` are both
  iterated: both must be arrays).
- Unreal plugin ``Rokoko/rokoko-studio-live-unreal-engine`` at commit 1a35a72 (plugin 1.13.1, February 2025):
  ``VirtualProductionSource.cpp`` (``LZ4F_decompress`` of each datagram must consume it whole and end the LZ4 frame;
  a 32 768-byte receive buffer; ``version``, ``scene.actors[].name``, ``meta`` with its five flags, ``body`` with
  ``position {x, y, z}`` / ``rotation {x, y, z, w}`` per joint).
- Blender add-on ``Rokoko/rokoko-studio-live-blender`` at commit 1e87e6a (add-on 1.4.2, June 2025):
  ``core/live_data_manager.py`` (LZ4 frame if the ``lz4`` module decodes it, else plain UTF-8 JSON; ``version``
  >= 3 reads ``fps``, ``scene.timestamp``, ``scene.actors``, ``scene.props``), ``core/animations.py`` and
  ``core/animation_lists.py`` (the same T-pose table, with more digits; hips position relative to
  ``dimensions.hipHeight``).

The Unity and Unreal plugins accept only LZ4-compressed datagrams (the LZ4 *frame* format); the Blender add-on
takes both. mocapd sends LZ4 frames by default (``compression = "lz4"``; ``"none"``: plain JSON, for the Blender
add-on without its ``lz4`` module or for reading with ``nc``).

One datagram per output frame (the whole scene: every streamed subject is one actor), at most
``max_datagram_bytes`` (default 32 768, the Unreal plugin's receive buffer); actors that would not fit are left out
of that frame and counted. The JSON document (UTF-8, keys in this order, numbers with 6 decimals)::

    {"version": 3,                      Rokoko's JSON version (the plugins' LiveFrame_v4 reads it as a number)
     "fps": 60.0,                       frames per second of this stream (output rate / rate_divisor)
     "frame": 1234,                     mocapd's output frame counter (not in Rokoko's format; plugins ignore it)
     "scene": {"timestamp": 12.345678,  seconds since the stream's first frame, of the frame's solve time
               "actors": [ACTOR, ...],  one per streamed subject, in order of appearance
               "props": []}}            mocapd has no props (the Unity plugin needs the empty array)

    ACTOR = {"name": "suit:suit0",     the subject's identity, or its [udp.rokoko] actor_names entry
             "color": [255, 59, 48],   RGB 0..255 (the live viewer's colour of the subject's slot)
             "meta": {"hasGloves": false, "hasLeftGlove": false, "hasRightGlove": false,
                      "hasBody": true, "hasFace": false},      hasBody false: a subject lost for now, at its
                                                                last pose (the Unity plugin then leaves it be)
             "dimensions": {"totalHeight": 1.75, "hipHeight": 0.98},   metres: the subject's skeleton's height
                                                                        and rest Hips joint height
             "body": {JOINT: {"position": {"x": .., "y": .., "z": ..},
                              "rotation": {"x": .., "y": .., "z": .., "w": ..}}, ...}}   63 joints, below

Frame and units (Rokoko Studio is a Unity application): Unity's left-handed frame, +Y up, metres, floor at y = 0;
:data:`mocapd.protocols.conventions.UNITY` (x = −X of mocapd, the subject's right when facing +Z). A joint's
``position`` is a world position; its ``rotation`` is a world rotation (x, y, z, w) in Studio's convention:
``q_joint = C(G_bone) ⊗ T_joint``, where ``G_bone`` is the mocapd bone's global rotation relative to the T-pose
(forward kinematics of θ), ``C`` the conversion to Unity's frame and ``T_joint`` the joint's rotation in Studio's
T-pose (the plugins' table, :data:`TPOSE`). So a subject in mocapd's T-pose facing +Z sends exactly the T-pose
table, and the plugins' retargeting (``world rotation × T⁻¹ × the model's T-pose``) gives each bone of the
receiving character mocapd's rotation.

Joints (Rokoko name ← mocapd bone giving the rotation; position)::

    hip ← Hips; chest ← Spine3 (the Unity plugin drives UpperChest with it); neck ← Neck; head ← Head
                                                                          each at its bone's joint
    spine ← Spine, swung: Rokoko's skeleton has one lower-spine bone where mocapd has Spine, Spine1 and Spine2, so
        Spine's rotation is turned by the smallest rotation that points the lower spine (Spine's joint to Spine3's)
        where mocapd's is; a receiver's chest then sits where mocapd's does (with Spine's own rotation it was off by
        9 to 19 cm on the synthetic rig's motion, in Rokoko's Blender add-on), at Spine's joint
    leftShoulder, rightShoulder ← Spine3 (mocapd has no clavicles: rigid with the chest), at the mid-line point at
        the height and depth of that side's upper-arm joint (the MVN shoulder rule, mocapd.protocols.mvn)
    left/rightUpperArm, LowerArm, Hand ← same names; left/rightUpLeg ← UpperLeg, Leg ← LowerLeg, Foot ← Foot,
        Toe ← Toes                                                        each at its bone's joint
    left/rightToeEnd ← Toes, at the toes' end site (half the toe offset beyond the toe joint, as the BVH export)
    40 finger joints left/right Thumb/Index/Middle/Ring/Little × Proximal/Medial/Distal/Tip: for a hand solved
        this frame (the subject's fingers, :class:`mocapd.core.hand_skeleton.HandPose`; issue 44) Proximal, Medial
        and Distal ← that hand's finger bones Proximal, Intermediate and Distal (for the thumb its three bones, the
        first its metacarpal), each at its joint, and Tip ← Distal at the fingertip, and that side's
        ``meta.hasLeftGlove``/``hasRightGlove`` (and ``hasGloves``) are true while the subject is tracked; a hand
        without fingers is sent straight (the T-pose finger rotations, rigid with the hand) at the hand's end site,
        as before fingers: the Unity plugin sets every humanoid bone it finds, so an absent finger would be a zero
        quaternion.

A 2-actor scene is about 18 kB of JSON, 3.5 kB as an LZ4 frame (the repeated finger joints compress well).
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass

import lz4.frame
import numpy as np
from numpy.typing import NDArray

from mocapd.core.hand_skeleton import FINGER_BONES, HandPose
from mocapd.core.kinematics import Kinematics
from mocapd.core.per_skeleton import PerSkeleton
from mocapd.core.rotations import quat_from_matrix, quat_multiply, quat_normalize
from mocapd.core.skeleton import BONE_INDEX, POSE_DIM, Skeleton
from mocapd.errors import InputError
from mocapd.protocols.conventions import UNITY
from mocapd.protocols.fingers import HAND_OF_SIDE, finger_kinematics

FloatArray = NDArray[np.float64]

DEFAULT_PORT = 14043
VERSION = 3
DEFAULT_MAX_DATAGRAM = 32768  # the Unreal plugin's receive buffer (Unity: 65 507, Blender: 81 920)
COMPRESSIONS = ("lz4", "none")
END_FRACTION = 0.5  # end sites: this fraction of the leaf bone's offset beyond its joint (as the BVH writer)

_H = math.sqrt(0.5)
_ARM_L = (-0.5, -0.5, -0.5, 0.5)
_ARM_R = (0.5, 0.5, -0.5, 0.5)
_UP = (0.0, 0.0, 0.0, 1.0)  # 180° about z: the spine chain's bones point up in Studio's skeleton
_FINGERS = ("Index", "Middle", "Ring", "Little")
_PHALANGES = ("Proximal", "Medial", "Distal", "Tip")

# Rokoko joint -> (mocapd bone giving the rotation, position rule, T-pose rotation (w, x, y, z) in Unity's frame).
# Position rules: "joint" (the bone's joint), "clavicle" (the shoulder rule), "end" (the bone's end site).
# The T-pose rotations are the Studio T-pose of the plugins (Unity's Actor.SmartsuitTPose as (x, y, z, w);
# Blender's animation_lists.actor_bones as (w, x, y, z), to five decimals); thumbs as printed there.
_BODY: tuple[tuple[str, str, str, tuple[float, float, float, float]], ...] = (
    ("hip", "Hips", "joint", (1.0, 0.0, 0.0, 0.0)),
    ("spine", "Spine", "joint", _UP),
    ("chest", "Spine3", "joint", _UP),
    ("neck", "Neck", "joint", _UP),
    ("head", "Head", "joint", _UP),
    ("leftShoulder", "Spine3", "clavicle", (-_H, 0.0, 0.0, _H)),
    ("leftUpperArm", "LeftUpperArm", "joint", _ARM_L),
    ("leftLowerArm", "LeftLowerArm", "joint", _ARM_L),
    ("leftHand", "LeftHand", "joint", _ARM_L),
    ("rightShoulder", "Spine3", "clavicle", (_H, 0.0, 0.0, _H)),
    ("rightUpperArm", "RightUpperArm", "joint", _ARM_R),
    ("rightLowerArm", "RightLowerArm", "joint", _ARM_R),
    ("rightHand", "RightHand", "joint", _ARM_R),
    ("leftUpLeg", "LeftUpperLeg", "joint", (_H, 0.0, _H, 0.0)),
    ("leftLeg", "LeftLowerLeg", "joint", (_H, 0.0, _H, 0.0)),
    ("leftFoot", "LeftFoot", "joint", (0.0, 0.0, _H, -_H)),
    ("leftToe", "LeftToes", "joint", (0.0, 0.0, _H, -_H)),
    ("leftToeEnd", "LeftToes", "end", (0.0, 0.0, _H, -_H)),
    ("rightUpLeg", "RightUpperLeg", "joint", (_H, 0.0, -_H, 0.0)),
    ("rightLeg", "RightLowerLeg", "joint", (_H, 0.0, -_H, 0.0)),
    ("rightFoot", "RightFoot", "joint", (0.0, 0.0, -_H, _H)),
    ("rightToe", "RightToes", "joint", (0.0, 0.0, -_H, _H)),
    ("rightToeEnd", "RightToes", "end", (0.0, 0.0, -_H, _H)),
)


def _finger_joints() -> list[tuple[str, str, str, tuple[float, float, float, float]]]:
    out = []
    for side, hand, flat, thumb0, thumb in (
        ("left", "LeftHand", _ARM_L, (-0.0923, -0.56098, -0.70106, 0.43046), (-0.2706, -0.65328, -0.65328, 0.2706)),
        ("right", "RightHand", _ARM_R, (0.0923, 0.56099, -0.70106, 0.43046), (0.2706, 0.65328, -0.65328, 0.2706)),
    ):
        for k, ph in enumerate(_PHALANGES):
            out.append((f"{side}Thumb{ph}", hand, "end", thumb0 if k == 0 else thumb))
        for finger in _FINGERS:
            out += [(f"{side}{finger}{ph}", hand, "end", flat) for ph in _PHALANGES]
    return out


JOINTS = (*_BODY, *_finger_joints())
JOINT_NAMES: tuple[str, ...] = tuple(j[0] for j in JOINTS)
"""The 63 body joints in the order sent (the Unity plugin's ``BodyFrame`` order)."""
N_JOINTS = len(JOINTS)
TPOSE: FloatArray = quat_normalize(np.array([j[3] for j in JOINTS], dtype=np.float64))
"""Studio's T-pose rotation of each joint, (63, 4) as (w, x, y, z) in Unity's frame."""
TPOSE.setflags(write=False)
_ROT_SRC = np.array([BONE_INDEX[j[1]] for j in JOINTS], dtype=np.intp)
_SPINE = JOINT_NAMES.index("spine")
_CLAVICLE_ARM = {"leftShoulder": "LeftUpperArm", "rightShoulder": "RightUpperArm"}

# Each joint's JSON, with %-placeholders for its 7 numbers (x y z, then the rotation's x y z w).
_JOINT_JSON = '"{}":{{"position":{{"x":%.6f,"y":%.6f,"z":%.6f}},"rotation":{{"x":%.6f,"y":%.6f,"z":%.6f,"w":%.6f}}}}'
_BODY_TEMPLATE = "{" + ",".join(_JOINT_JSON.format(n) for n in JOINT_NAMES) + "}"
_META = '{{"hasGloves":{},"hasLeftGlove":{},"hasRightGlove":{},"hasBody":{},"hasFace":false}}'
# Per hand, the Rokoko joint index of each finger bone (FINGER_BONES order), and of each fingertip (thumb to little).
_FINGER_JOINTS = np.array([[JOINT_NAMES.index(side + b.replace("Intermediate", "Medial")) for b in FINGER_BONES]
                           for side in ("left", "right")], dtype=np.intp)  # fmt: skip
_TIP_JOINTS = np.array([[JOINT_NAMES.index(f"{side}{f}Tip") for f in ("Thumb", *_FINGERS)]
                        for side in ("left", "right")], dtype=np.intp)  # fmt: skip


class RokokoJoints:
    """World positions and Studio-convention rotations of the 63 joints from pose vectors of one skeleton."""

    def __init__(self, skeleton: Skeleton) -> None:
        self.skeleton = skeleton
        self.kinematics = Kinematics(skeleton)
        off = skeleton.offsets
        base = np.empty(N_JOINTS, dtype=np.intp)  # the bone whose joint the position starts from
        local = np.zeros((N_JOINTS, 3))  # then this vector in that bone's frame
        for i, (name, bone, rule, _) in enumerate(JOINTS):
            base[i] = BONE_INDEX[bone]
            if rule == "clavicle":
                o = off[BONE_INDEX[_CLAVICLE_ARM[name]]]
                local[i] = (0.0, o[1], o[2])
            elif rule == "end":
                local[i] = END_FRACTION * off[BONE_INDEX[bone]]
        self._base = base
        self._local = local
        sp = BONE_INDEX["Spine"]
        self._spine = sp
        self._lower_spine = off[BONE_INDEX["Spine1"]] + off[BONE_INDEX["Spine2"]] + off[BONE_INDEX["Spine3"]]

    def compute(
        self, thetas: FloatArray, hands: Sequence[HandPose | None] | None = None
    ) -> tuple[FloatArray, FloatArray]:
        """Joint positions and rotations for a batch of subjects.

        Parameters
        ----------
        thetas : array, shape (n, 66)
        hands : sequence of HandPose or None, optional
            Each subject's fingers: the finger joints of its hands present follow them (module doc).

        Returns
        -------
        positions : array, shape (n, 63, 3)
            World positions, metres, Unity's frame.
        rotations : array, shape (n, 63, 4)
            World rotations in Studio's convention (``C(G) ⊗ T``), (w, x, y, z), Unity's frame.
        """
        thetas = np.asarray(thetas, dtype=np.float64)
        if thetas.ndim != 2 or thetas.shape[1] != POSE_DIM:
            raise InputError(f"thetas must have shape (n, {POSE_DIM}), got {thetas.shape}")
        fk = self.kinematics.forward(thetas)
        Q = fk.rotations[:, self._base]
        pos = fk.positions[:, self._base] + np.einsum("nkij,kj->nki", Q, self._local)
        R = fk.rotations[:, _ROT_SRC]
        sp = self._spine
        chest = fk.positions[:, BONE_INDEX["Spine3"]] - fk.positions[:, sp]
        R[:, _SPINE] = swing(fk.rotations[:, sp] @ self._lower_spine, chest) @ fk.rotations[:, sp]
        fingered = [(k, h) for k, h in enumerate(hands or ()) if h is not None and h.present.any()]
        if fingered:
            self._fingers(fk.rotations, fk.positions, fingered, R, pos)
        g = UNITY.quaternions(quat_from_matrix(R))
        return UNITY.positions(pos), quat_multiply(g, TPOSE)

    def _fingers(self, G: FloatArray, x: FloatArray, fingered: list[tuple[int, HandPose]], R: FloatArray,
                 pos: FloatArray) -> None:  # fmt: skip
        """Replace the finger joints of the hands present (subject rows of ``R``/``pos``) by the fingers' own."""
        side = list(HAND_OF_SIDE)
        rows, hands = [k for k, _ in fingered], [h for _, h in fingered]
        fs = finger_kinematics(G[rows][:, side], x[rows][:, side], np.stack([h.rotations for h in hands]),
                               [h.skeleton for h in hands])  # fmt: skip
        distal = [3 * f + 2 for f in range(5)]
        for i, (k, h) in enumerate(zip(rows, hands, strict=True)):
            for s in np.flatnonzero(h.present):
                R[k, _FINGER_JOINTS[s]] = fs.rotations[i, s]
                pos[k, _FINGER_JOINTS[s]] = fs.positions[i, s]
                R[k, _TIP_JOINTS[s]] = fs.rotations[i, s, distal]
                pos[k, _TIP_JOINTS[s]] = fs.tips[i, s]


def swing(a: FloatArray, b: FloatArray) -> FloatArray:
    """The smallest rotations taking directions ``a`` to ``b``: (n, 3), (n, 3) → (n, 3, 3).

    ``R = I + K + K² / (1 + a·b)`` with ``K = [a × b]×`` for unit ``a``, ``b`` (undefined only for opposite
    directions, which a spine does not reach).
    """
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    k = np.cross(a, b)
    K = np.zeros((*k.shape[:-1], 3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -k[..., 2], k[..., 1], -k[..., 0]
    K[..., 1, 0], K[..., 2, 0], K[..., 2, 1] = k[..., 2], -k[..., 1], k[..., 0]
    c = np.sum(a * b, axis=-1)[..., None, None]
    out: FloatArray = np.eye(3) + K + (K @ K) / np.maximum(1.0 + c, 1e-9)
    return out


@dataclass(frozen=True)
class RokokoActor:
    """One actor of a scene: a subject's pose with its actor name and colour."""

    name: str
    theta: FloatArray  # (66,)
    color: tuple[int, int, int] = (255, 255, 255)
    skeleton: Skeleton | None = None  # the subject's own sized skeleton (None: the encoder's)
    tracked: bool = True  # meta.hasBody: False for a subject lost for now, sent at its last pose
    hands: HandPose | None = None  # the subject's fingers (None: straight fingers, as without)


def _bool(v: bool) -> str:
    return "true" if v else "false"


def _gloves(a: RokokoActor) -> tuple[bool, bool, bool]:
    """meta.hasGloves, hasLeftGlove, hasRightGlove: the hands with fingers this frame, while the actor is tracked."""
    if a.hands is None or not a.tracked:
        return False, False, False
    left, right = (bool(v) for v in a.hands.present)
    return left or right, left, right


@dataclass(frozen=True)
class RokokoDatagram:
    """One encoded scene: the datagram and how many of the given actors it holds (the rest did not fit)."""

    data: bytes
    actors: int
    json_bytes: int


class RokokoEncoder:
    """Output frames → one Rokoko Studio Live JSON v3 datagram each (values in, bytes out).

    Parameters
    ----------
    skeleton : Skeleton
        The skeleton of the pose vectors (a subject's own sized skeleton can be given per actor).
    fps : float
        The stream's frame rate, sent as ``fps``.
    compression : str
        ``"lz4"`` (an LZ4 frame, what the Unity and Unreal plugins read) or ``"none"`` (plain JSON).
    max_datagram_bytes : int
        Largest datagram; actors beyond it are left out of the frame.
    """

    def __init__(
        self,
        skeleton: Skeleton,
        *,
        fps: float,
        compression: str = "lz4",
        max_datagram_bytes: int = DEFAULT_MAX_DATAGRAM,
    ) -> None:
        if compression not in COMPRESSIONS:
            raise InputError(f"Rokoko compression {compression!r}: allowed {', '.join(COMPRESSIONS)}")
        if not (math.isfinite(fps) and fps > 0):
            raise InputError(f"Rokoko fps must be a positive number, got {fps!r}")
        self.joints = RokokoJoints(skeleton)
        self._sized = PerSkeleton(self.joints, RokokoJoints)
        self.fps = float(fps)
        self.compression = compression
        self.max_datagram_bytes = max_datagram_bytes
        self._t0_ns: int | None = None

    def seconds(self, t_ns: int) -> float:
        """Seconds since the first frame encoded (the stream's start)."""
        if self._t0_ns is None:
            self._t0_ns = t_ns
        return (t_ns - self._t0_ns) / 1e9

    def actor_json(self, actors: Sequence[RokokoActor]) -> list[str]:
        """Each actor's JSON object (actors on the same skeleton share one forward-kinematics call)."""
        groups: dict[int, tuple[RokokoJoints, list[int]]] = {}
        for k, a in enumerate(actors):
            th = np.asarray(a.theta, dtype=np.float64)
            if th.shape != (POSE_DIM,) or not np.all(np.isfinite(th)):
                raise InputError(f"Rokoko actor {a.name!r}: theta must be finite with shape ({POSE_DIM},)")
            joints = self._sized.get(a.skeleton)
            groups.setdefault(id(joints), (joints, []))[1].append(k)
        out = [""] * len(actors)
        for joints, members in groups.values():
            pos, rot = joints.compute(
                np.stack([np.asarray(actors[k].theta, dtype=np.float64) for k in members]),
                [actors[k].hands for k in members],
            )
            values = np.concatenate([pos, rot[..., [1, 2, 3, 0]]], axis=2)  # x y z, then x y z w
            values[np.abs(values) < 5e-7] = 0.0  # no "-0.000000"
            sk = joints.skeleton
            dims = f'"dimensions":{{"totalHeight":{sk.height:.6f},"hipHeight":{sk.root_height:.6f}}}'
            for k, v in zip(members, values, strict=True):
                a = actors[k]
                r, g, b = (int(c) for c in a.color)
                body = _BODY_TEMPLATE % tuple(v.ravel().tolist())
                meta = _META.format(*(_bool(v) for v in _gloves(a)), _bool(a.tracked))
                out[k] = f'{{"name":{json.dumps(a.name)},"color":[{r},{g},{b}],"meta":{meta},{dims},"body":{body}}}'
        return out

    def document(self, frame: int, t_ns: int, actors_json: Sequence[str]) -> bytes:
        """The scene's JSON document (UTF-8) for the given actor objects."""
        head = f'{{"version":{VERSION},"fps":{self.fps:.6g},"frame":{int(frame)},'
        scene = f'"scene":{{"timestamp":{self.seconds(t_ns):.6f},"actors":[{",".join(actors_json)}],"props":[]}}}}'
        return (head + scene).encode("utf-8")

    def pack(self, document: bytes) -> bytes:
        """The datagram of a JSON document: an LZ4 frame (content size stored, as the plugins' decoders read it)
        or the JSON itself."""
        if self.compression == "none":
            return document
        return bytes(lz4.frame.compress(document, store_size=True))

    def encode(self, frame: int, t_ns: int, actors: Sequence[RokokoActor]) -> RokokoDatagram:
        """The datagram of one output frame: every actor that fits within ``max_datagram_bytes``, in order.

        Parameters
        ----------
        frame : int
            mocapd's output frame counter.
        t_ns : int
            The frame's solve time (host monotonic ns); ``scene.timestamp`` counts from the first call.
        actors : sequence of RokokoActor
        """
        parts = self.actor_json(actors)
        n = len(parts)
        while True:
            doc = self.document(frame, t_ns, parts[:n])
            data = self.pack(doc)
            if len(data) <= self.max_datagram_bytes:
                return RokokoDatagram(data, n, len(doc))
            if n == 0:
                raise InputError(f"max_datagram_bytes = {self.max_datagram_bytes} cannot hold an empty Rokoko scene")
            n -= 1
