"""A low-poly VRM 1.0 mannequin for the live viewer's avatar view (issue 44): generated, never committed.

No npm or PyPI package ships a humanoid avatar under a permissive licence with finger bones (VRoid's CC0
AvatarSample models live on VRoid Hub, not in a registry), so mocapd builds its own from its skeleton: the
default 1.75 m body (:class:`~mocapd.core.skeleton.Skeleton`) and its sized hands
(:class:`~mocapd.core.hand_skeleton.HandSkeleton`), as a glTF binary with the ``VRMC_vrm`` extension, which any
VRM 1.0 loader (three-vrm in the viewer, UniVRM, the VRM add-on for Blender) reads as a humanoid.

- **Bones.** One node per VRM humanoid bone, named as Unity's ``HumanBodyBones`` (``Hips``, ``Spine``, ``Chest``,
  ``UpperChest``, ``Neck``, ``Head``, the arms and legs, ``LeftToes``, the 30 finger bones): mocapd's 21 body
  bones except ``Spine1``, whose offset joins ``Spine2``'s (VRM has three spine bones where mocapd has four), and
  the 30 finger bones of :data:`~mocapd.core.hand_skeleton.HAND_BONE_NAMES`. :data:`HUMAN_BONES` maps each node to
  its VRM 1.0 name (the thumbs' bones are ``Metacarpal``/``Proximal``/``Distal`` there,
  :data:`~mocapd.core.hand_skeleton.VRM1_NAMES`) and to the mocapd bone whose rotation drives it. Every rest
  rotation is the identity: the rest pose is mocapd's T-pose facing +Z (VRM 1.0's own rest pose and axes: +Y up,
  +Z forward, the model's left +X), so a bone's normalized VRM rotation is mocapd's global rotation expressed in
  its parent's, with no change of axes.
- **Mesh.** A tube of eight sides per bone (elliptic, tapered, capped), every vertex rigidly bound to its bone
  (``JOINTS_0``/``WEIGHTS_0``), one grey material; no normals (loaders shade it flat: the low-poly look).
- **Meta.** Name, author ``mocapd``, licence CC0-1.0 (``otherLicenseUrl``): the model is this module's output.

Pure (arrays in, bytes out); :mod:`pygltflib` packs the container as for :mod:`mocapd.protocols.gltf_writer`.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import pygltflib as gl
from numpy.typing import NDArray

from mocapd.core.hand_skeleton import FINGERS, HAND_BONE_NAMES, VRM0_NAMES, VRM1_NAMES, HandSkeleton
from mocapd.core.skeleton import BONE_NAMES, REFERENCE_HEIGHT, Skeleton
from mocapd.errors import InputError
from mocapd.protocols.fingers import EXTENDED_BONE_NAMES, EXTENDED_PARENTS, extended_offsets

FloatArray = NDArray[np.float64]

_BODY_VRM: dict[str, tuple[str, str]] = {  # mocapd bone -> (node name, VRM 1.0 humanoid name)
    "Hips": ("Hips", "hips"),
    "Spine": ("Spine", "spine"),
    "Spine2": ("Chest", "chest"),
    "Spine3": ("UpperChest", "upperChest"),
    "Neck": ("Neck", "neck"),
    "Head": ("Head", "head"),
    **{f"{s}{b}": (f"{s}{b}", f"{s.lower()}{b}") for s in ("Left", "Right")
       for b in ("UpperArm", "LowerArm", "Hand", "UpperLeg", "LowerLeg", "Foot", "Toes")},
}  # fmt: skip
MERGED = "Spine1"
"""The mocapd bone without a VRM bone: its offset is added to ``Spine2``'s (the VRM ``chest``)."""

HUMAN_BONES: tuple[tuple[str, str, str], ...] = (
    *((_BODY_VRM[b][0], _BODY_VRM[b][1], b) for b in BONE_NAMES if b != MERGED),
    *((b, VRM1_NAMES[b], b) for b in HAND_BONE_NAMES),
)
"""Per avatar node, in node order: (node name, VRM 1.0 humanoid bone, the mocapd bone that drives it)."""

SIDES = 8
"""Sides of each bone's tube."""
COLOUR = (0.82, 0.84, 0.88, 1.0)
NAME = "mocapd mannequin"
"""The model's name in its meta (the viewer tints a model of this name with the subject's colour)."""
LICENCE_URL = "https://creativecommons.org/publicdomain/zero/1.0/"

# Half-widths (m at 1.75 m) of each bone's tube at its joint and at its end: (across, depth) with "across" the
# axis perpendicular to the bone and to the depth axis (+Z, or +Y for a bone along Z: the feet), see _frame.
_RADII: dict[str, tuple[float, float, float, float]] = {
    "Hips": (0.15, 0.10, 0.14, 0.09),
    "Spine": (0.14, 0.09, 0.14, 0.09),
    "Spine2": (0.15, 0.10, 0.16, 0.10),
    "Spine3": (0.17, 0.10, 0.08, 0.06),
    "Neck": (0.045, 0.045, 0.045, 0.045),
    "Head": (0.075, 0.09, 0.08, 0.095),
    "UpperArm": (0.05, 0.05, 0.04, 0.04),
    "LowerArm": (0.038, 0.038, 0.03, 0.032),
    "Hand": (0.016, 0.04, 0.014, 0.045),
    "UpperLeg": (0.075, 0.075, 0.055, 0.055),
    "LowerLeg": (0.05, 0.05, 0.038, 0.038),
    "Foot": (0.045, 0.045, 0.045, 0.025),
    "Toes": (0.045, 0.02, 0.04, 0.015),
    "Thumb": (0.011, 0.011, 0.009, 0.009),
    "Finger": (0.0085, 0.0085, 0.007, 0.007),
}
_HEAD_LENGTH = 0.22  # m at 1.75 m, the head's tube above its joint
_TOES_FRACTION = 0.6  # of the toes' own offset
_PELVIS_DROP = 0.08  # m at 1.75 m: the hips' tube starts this far below the Hips joint


def _radii(bone: str) -> tuple[float, float, float, float]:
    if bone in _RADII:
        return _RADII[bone]
    for key in ("UpperArm", "LowerArm", "UpperLeg", "LowerLeg", "Foot", "Toes", "Hand"):
        if bone.endswith(key):
            return _RADII[key]
    return _RADII["Thumb" if "Thumb" in bone else "Finger"]


def _skeleton(body: Skeleton, hands: HandSkeleton) -> tuple[list[int], FloatArray]:
    """Parents (node indices, -1 for Hips) and rest offsets (m, 3) of the avatar's nodes (:data:`HUMAN_BONES`)."""
    ext = extended_offsets(body.offsets, hands)
    node_of = {mocapd: i for i, (_, _, mocapd) in enumerate(HUMAN_BONES)}
    merged = EXTENDED_BONE_NAMES.index(MERGED)
    parents: list[int] = []
    offsets = np.zeros((len(HUMAN_BONES), 3))
    for i, (_, _, mocapd) in enumerate(HUMAN_BONES):
        b = EXTENDED_BONE_NAMES.index(mocapd)
        p = EXTENDED_PARENTS[b]
        offsets[i] = ext[b]
        if p == merged:  # Spine2 hangs from Spine through Spine1
            offsets[i] += ext[merged]
            p = EXTENDED_PARENTS[merged]
        parents.append(-1 if p < 0 else node_of[EXTENDED_BONE_NAMES[p]])
    return parents, offsets


def _frame(axis: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Two unit vectors across a bone along ``axis``: (across, depth), depth +Z (+Y for a bone along Z)."""
    u = axis / max(float(np.linalg.norm(axis)), 1e-9)
    depth = np.array([0.0, 0.0, 1.0]) if abs(u[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
    across = np.cross(depth, u)
    across /= np.linalg.norm(across)
    return across, np.cross(u, across)


def _tube(head: FloatArray, tail: FloatArray, radii: tuple[float, float, float, float], scale: float
          ) -> tuple[FloatArray, list[tuple[int, int, int]]]:  # fmt: skip
    """Vertices (2 * SIDES + 2, 3) and triangles (local indices) of a capped elliptic tube from head to tail."""
    across, depth = _frame(tail - head)
    angles = 2 * math.pi * np.arange(SIDES) / SIDES
    rings = []
    for centre, (ra, rd) in ((head, radii[:2]), (tail, radii[2:])):
        rings.append(centre + scale * (ra * np.cos(angles)[:, None] * across + rd * np.sin(angles)[:, None] * depth))
    verts = np.concatenate([rings[0], rings[1], head[None], tail[None]])
    tris: list[tuple[int, int, int]] = []
    cap0, cap1 = 2 * SIDES, 2 * SIDES + 1
    for k in range(SIDES):
        n = (k + 1) % SIDES
        tris += [(k, n, SIDES + n), (k, SIDES + n, SIDES + k), (cap0, n, k), (cap1, SIDES + k, SIDES + n)]
    return verts, tris


def _mesh(parents: list[int], offsets: FloatArray, rest: FloatArray, hands: HandSkeleton, scale: float
          ) -> tuple[FloatArray, NDArray[np.uint16], NDArray[np.uint16]]:  # fmt: skip
    """Positions (v, 3), bone per vertex (v,), triangles (t, 3) of the whole body at rest."""
    verts: list[FloatArray] = []
    bones: list[int] = []
    tris: list[tuple[int, int, int]] = []
    names = [m for _, _, m in HUMAN_BONES]
    for i, bone in enumerate(names):
        kids = [c for c, p in enumerate(parents) if p == i]
        head = rest[i].copy()
        if bone == "Hips":
            head[1] -= _PELVIS_DROP * scale
            tail = rest[names.index("Spine")]
        elif bone == "Head":
            tail = rest[i] + np.array([0.0, _HEAD_LENGTH * scale, 0.0])
        elif bone.endswith("Toes"):
            tail = rest[i] + _TOES_FRACTION * offsets[i]
        elif bone.endswith("Hand"):
            tail = rest[names.index(bone.replace("Hand", "MiddleProximal"))]
        elif bone.endswith("Distal"):
            side = 0 if bone.startswith("Left") else 1
            finger = next(f for f, name in enumerate(FINGERS) if name in bone)
            tail = rest[i] + hands.tips[side, finger]
        elif bone.startswith(("Left", "Right")) and kids:
            tail = rest[kids[0]]
        else:  # the spine's bones: towards the next spine bone or the neck (the first child)
            tail = rest[kids[0]]
        v, t = _tube(head, tail, _radii(bone), scale)
        k = sum(len(x) for x in verts)
        verts.append(v)
        bones += [i] * len(v)
        tris += [(a + k, b + k, c + k) for a, b, c in t]
    return np.concatenate(verts), np.array(bones, dtype=np.uint16), np.array(tris, dtype=np.uint16)


def _add(doc: gl.GLTF2, blob: bytearray, array: NDArray[np.generic], kind: str, *, target: int | None = None,
         minmax: bool = False) -> int:  # fmt: skip
    ctype = {np.dtype(np.float32): gl.FLOAT, np.dtype(np.uint16): gl.UNSIGNED_SHORT}[array.dtype]
    raw = np.ascontiguousarray(array).tobytes()
    doc.bufferViews.append(gl.BufferView(buffer=0, byteOffset=len(blob), byteLength=len(raw), target=target))
    blob += raw + b"\0" * (-len(raw) % 4)
    count = array.shape[0] if kind != "SCALAR" else array.size
    acc = gl.Accessor(bufferView=len(doc.bufferViews) - 1, componentType=ctype, count=int(count), type=kind)
    if minmax:
        flat = array.reshape(int(count), -1)
        acc.min = [float(v) for v in flat.min(axis=0)]
        acc.max = [float(v) for v in flat.max(axis=0)]
    doc.accessors.append(acc)
    return len(doc.accessors) - 1


def avatar_vrm(body: Skeleton | None = None, version: int = 1) -> bytes:
    """The mannequin (module doc) as VRM bytes, sized to ``body`` (default: a 1.75 m person).

    ``version`` 1: VRM 1.0 (the viewer's). 0: VRM 0.x, as older tools write it (the ``VRM`` extension, the thumbs'
    bones ``Proximal``/``Intermediate``/``Distal``, :data:`~mocapd.core.hand_skeleton.VRM0_NAMES`), and facing -Z as
    VRM 0.x models do (every position turned 180° about +Y): for the loaders' VRM 0.x path.
    """
    if version not in (0, 1):
        raise InputError(f"VRM version must be 0 or 1, got {version!r}")
    body = body if body is not None else Skeleton.from_height(REFERENCE_HEIGHT)
    hands = HandSkeleton.from_body(body)
    scale = body.height / REFERENCE_HEIGHT
    parents, offsets = _skeleton(body, hands)
    m = len(parents)
    rest = np.zeros((m, 3))
    for i in range(m):
        rest[i] = (0.0, body.root_height, 0.0) if parents[i] < 0 else rest[parents[i]] + offsets[i]
    verts, bone_of, tris = _mesh(parents, offsets, rest, hands, scale)
    if version == 0:  # facing -Z: x and z negated (a rotation: the triangles keep their winding)
        turn = np.array([-1.0, 1.0, -1.0])
        offsets, rest, verts = offsets * turn, rest * turn, verts * turn
    doc = gl.GLTF2(asset=gl.Asset(version="2.0", generator="mocapd vrm_avatar"))
    blob = bytearray()
    for i, (name, _, _) in enumerate(HUMAN_BONES):
        t = rest[i] if parents[i] < 0 else offsets[i]
        kids = [c for c in range(m) if parents[c] == i]
        doc.nodes.append(gl.Node(name=name, translation=[float(v) for v in t], children=kids))
    ibm = np.tile(np.eye(4, dtype=np.float32), (m, 1, 1))
    ibm[:, 3, :3] = -rest  # column-major: the translation is the 4th column, stored as the 4th row
    doc.skins.append(gl.Skin(name="mannequin", joints=list(range(m)), skeleton=0,
                             inverseBindMatrices=_add(doc, blob, ibm.reshape(m, 16), "MAT4")))  # fmt: skip
    joints4 = np.zeros((bone_of.size, 4), dtype=np.uint16)
    joints4[:, 0] = bone_of
    weights = np.zeros((bone_of.size, 4), dtype=np.float32)
    weights[:, 0] = 1.0
    attrs = gl.Attributes(
        POSITION=_add(doc, blob, verts.astype(np.float32), "VEC3", target=gl.ARRAY_BUFFER, minmax=True),
        JOINTS_0=_add(doc, blob, joints4, "VEC4", target=gl.ARRAY_BUFFER),
        WEIGHTS_0=_add(doc, blob, weights, "VEC4", target=gl.ARRAY_BUFFER),
    )
    indices = _add(doc, blob, tris.reshape(-1), "SCALAR", target=gl.ELEMENT_ARRAY_BUFFER)
    doc.materials.append(gl.Material(name="mannequin", pbrMetallicRoughness=gl.PbrMetallicRoughness(
        baseColorFactor=list(COLOUR), metallicFactor=0.0, roughnessFactor=0.85)))  # fmt: skip
    doc.meshes.append(gl.Mesh(name="mannequin", primitives=[gl.Primitive(attributes=attrs, indices=indices,
                                                                         material=0)]))  # fmt: skip
    doc.nodes.append(gl.Node(name="mannequin mesh", mesh=0, skin=0))
    doc.scenes = [gl.Scene(name="mannequin", nodes=[0, m])]
    doc.scene = 0
    doc.extensionsUsed = ["VRMC_vrm"] if version == 1 else ["VRM"]
    doc.extensions = {"VRMC_vrm": _vrm1()} if version == 1 else {"VRM": _vrm0()}
    doc.buffers = [gl.Buffer(byteLength=len(blob))]
    doc.set_binary_blob(bytes(blob))
    return b"".join(doc.save_to_bytes())


def _vrm1() -> dict[str, object]:
    """The ``VRMC_vrm`` extension (VRM 1.0): meta and humanoid."""
    return {
        "specVersion": "1.0",
        "meta": {"name": NAME, "version": "1", "authors": ["mocapd"],
                 "licenseUrl": "https://vrm.dev/licenses/1.0/", "otherLicenseUrl": LICENCE_URL,
                 "avatarPermission": "everyone", "commercialUsage": "corporation", "creditNotation": "unnecessary",
                 "allowRedistribution": True, "modification": "allowModificationRedistribution"},
        "humanoid": {"humanBones": {vrm: {"node": i} for i, (_, vrm, _) in enumerate(HUMAN_BONES)}},
    }  # fmt: skip


def _vrm0() -> dict[str, object]:
    """The ``VRM`` extension (VRM 0.x): meta, humanoid (VRM 0.x's bone names) and the empty parts loaders expect."""
    names = {vrm: VRM0_NAMES.get(mocapd, vrm) for _, vrm, mocapd in HUMAN_BONES}
    head = next(i for i, (_, vrm, _) in enumerate(HUMAN_BONES) if vrm == "head")
    return {
        "exporterVersion": "mocapd", "specVersion": "0.0",
        "meta": {"title": NAME, "version": "1", "author": "mocapd", "allowedUserName": "Everyone",
                 "violentUssageName": "Allow", "sexualUssageName": "Allow", "commercialUssageName": "Allow",
                 "licenseName": "CC0", "otherLicenseUrl": LICENCE_URL},
        "humanoid": {"humanBones": [{"bone": names[vrm], "node": i, "useDefaultValues": True}
                                    for i, (_, vrm, _) in enumerate(HUMAN_BONES)]},
        "firstPerson": {"firstPersonBone": head, "firstPersonBoneOffset": {"x": 0.0, "y": 0.06, "z": 0.0},
                        "meshAnnotations": [], "lookAtTypeName": "Bone"},
        "blendShapeMaster": {"blendShapeGroups": []},
        "secondaryAnimation": {"boneGroups": [], "colliderGroups": []},
        "materialProperties": [],
    }  # fmt: skip


@functools.cache
def default_avatar() -> bytes:
    """:func:`avatar_vrm` of the 1.75 m default body, built once per process (the viewer's ``/avatar.vrm``)."""
    return avatar_vrm()


__all__ = ["HUMAN_BONES", "MERGED", "avatar_vrm", "default_avatar"]
