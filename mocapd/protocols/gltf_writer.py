"""glTF 2.0 binary (``.glb``) of recorded subjects: a skinned 21-joint armature and one animation per subject.

Pure (arrays in, bytes out); :mod:`pygltflib` holds the document and packs the GLB container.

Layout, per subject ``s`` (in the order given):

- **Nodes.** An armature root node named after the subject, whose only child is the ``Hips`` joint node; the 21
  joint nodes carry the names and parents of DESIGN.md (``mocapd.core.skeleton.BONE_NAMES``). Each joint node's
  rest ``translation`` is the bone's offset in its parent's frame (the subject's own skeleton), ``Hips``' is
  ``(0, root_height, 0)``; every rest rotation is the identity, so the rest pose is the T-pose facing +Z.
- **Skin and mesh.** A skin over the 21 joints (``inverseBindMatrices``: the inverse rest transforms, pure
  translations) and a mesh node using it: one octahedral "bone" per joint from the joint towards its first child
  (a leaf: half its own offset further, as the BVH end sites), every vertex rigidly bound to its joint
  (``JOINTS_0``/``WEIGHTS_0``), so engines that only import skinned meshes (Unreal, Unity glTFast) see a
  skeleton. The mesh node sits at the scene root, as the specification asks of skinned meshes.
- **Animation.** One per subject, named after it: ``Hips`` translation and all 21 joint rotations, ``LINEAR``,
  sampled at the given times (seconds from the first frame of the export, shared by all subjects so they stay in
  sync). Rotations are the local rotations of θ as glTF quaternions (x, y, z, w), each the sign nearest the
  previous one so linear interpolation never takes the long way round.

Fingers (issue 44): a subject with ``hands`` gets 30 more joint nodes (:mod:`mocapd.protocols.fingers`: the 15
finger bones of each hand, ``LeftThumbProximal`` ..., children of its hand node, three per finger), in the skin and
the mesh (a hand's bone then points at its middle knuckle, a distal bone ends at its fingertip) and one rotation
channel each. A subject without fingers is exactly as above.

Units and axes are mocapd's, which are glTF's: metres, +Y up, right-handed, character facing +Z. Every number is
float32 (the format's type; 1e-7 relative, sub-micrometre at room scale).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pygltflib as gl
from numpy.typing import NDArray

from mocapd.core.hand_skeleton import N_FINGER_BONES, HandSkeleton
from mocapd.core.rotations import quat_from_rotvec
from mocapd.core.skeleton import BONE_NAMES, N_BONES, PARENTS, POSE_DIM
from mocapd.errors import InputError
from mocapd.protocols.fingers import EXTENDED_BONE_NAMES, EXTENDED_PARENTS, extended_offsets, leaf_ends, tail_child

FloatArray = NDArray[np.float64]

END_FRACTION = 0.5
"""A leaf bone's drawn length, as a fraction of its own offset (as the BVH writer's end sites)."""
BONE_WIDTH = 0.12
"""Octahedron half-width as a fraction of the bone's length (at least :data:`MIN_WIDTH_M`)."""
MIN_WIDTH_M = 0.01


@dataclass(frozen=True)
class GltfSubject:
    """One animated subject.

    Attributes
    ----------
    name : str
        Armature and animation name (the subject's identity).
    offsets : array, shape (21, 3)
        Rest bone offsets in metres (``Skeleton.offsets``).
    root_height : float
        Rest height of the Hips joint (metres).
    times : array, shape (n,)
        Sample times in seconds (increasing).
    thetas : array, shape (n, 66)
        Pose vectors at those times.
    hands : array, shape (n, 2, 15, 4), optional
        The fingers' local rotations (w, x, y, z) at those times, on ``hand_skeleton`` (None: no fingers).
    """

    name: str
    offsets: FloatArray
    root_height: float
    times: FloatArray
    thetas: FloatArray
    hands: FloatArray | None = None
    hand_skeleton: HandSkeleton | None = None

    def __post_init__(self) -> None:
        th, t = np.asarray(self.thetas, dtype=np.float64), np.asarray(self.times, dtype=np.float64)
        if np.asarray(self.offsets).shape != (N_BONES, 3):
            raise InputError(f"glTF subject {self.name!r}: offsets must have shape ({N_BONES}, 3)")
        if th.ndim != 2 or th.shape[1] != POSE_DIM or th.shape[0] < 1 or t.shape != (th.shape[0],):
            raise InputError(f"glTF subject {self.name!r}: thetas (n >= 1, {POSE_DIM}) and times (n,) expected")
        if not (np.all(np.isfinite(th)) and np.all(np.isfinite(t)) and np.all(np.diff(t) > 0)):
            raise InputError(f"glTF subject {self.name!r}: poses must be finite and times increasing")
        if self.hands is not None and (
            self.hand_skeleton is None
            or np.shape(self.hands) != (th.shape[0], 2, N_FINGER_BONES, 4)
            or not np.all(np.isfinite(self.hands))
        ):
            raise InputError(f"glTF subject {self.name!r}: fingers (n, 2, 15, 4), finite, with their hand skeleton")


def rest_positions(offsets: FloatArray, root_height: float, parents: tuple[int, ...] = PARENTS) -> FloatArray:
    """World joint positions of the rest pose (identity rotations), shape (m, 3) for ``m`` = len(parents)."""
    x = np.zeros((len(parents), 3))
    x[0] = (0.0, root_height, 0.0)
    for b in range(1, len(parents)):
        x[b] = x[parents[b]] + offsets[b]
    return x


def _continuous(q: FloatArray) -> FloatArray:
    """Quaternions (n, k, 4) with each sign flipped to the hemisphere of the previous sample."""
    q = q.copy()
    for i in range(1, q.shape[0]):
        flip = np.sum(q[i] * q[i - 1], axis=-1) < 0
        q[i, flip] *= -1.0
    return q


def _octahedra(
    rest: FloatArray, offsets: FloatArray, parents: tuple[int, ...] = PARENTS, ends: dict[int, FloatArray] | None = None
) -> tuple[FloatArray, NDArray[np.uint16], NDArray[np.uint16]]:
    """Bone shapes in the rest pose: positions (m*6, 3), joint index per vertex (m*6,), triangles (m*8, 3); ``ends``:
    where each leaf ends, in its frame (default :data:`END_FRACTION` of its own offset)."""
    m = len(parents)
    first_child = {b: tail_child(parents, b) for b in range(m)}
    verts: list[FloatArray] = []
    joints: list[int] = []
    tris: list[tuple[int, int, int]] = []
    for b in range(m):
        c = first_child[b]
        head = rest[b]
        tail = rest[c] if c is not None else head + (END_FRACTION * offsets[b] if ends is None else ends[b])
        axis = tail - head
        length = float(np.linalg.norm(axis))
        u = axis / length if length > 1e-9 else np.array([0.0, 1.0, 0.0])
        side = np.cross(u, [0.0, 0.0, 1.0] if abs(u[2]) < 0.9 else [1.0, 0.0, 0.0])
        side /= np.linalg.norm(side)
        up = np.cross(u, side)
        w = max(BONE_WIDTH * length, MIN_WIDTH_M)
        ring = head + 0.2 * axis
        k = len(verts)
        verts += [head, tail, ring + w * side, ring + w * up, ring - w * side, ring - w * up]
        joints += [b] * 6
        for i in range(4):
            a, n = k + 2 + i, k + 2 + (i + 1) % 4
            tris += [(k, n, a), (k + 1, a, n)]
    return np.array(verts), np.array(joints, dtype=np.uint16), np.array(tris, dtype=np.uint16)


class _Blob:
    """The binary buffer and its accessors, 4-byte aligned."""

    def __init__(self, doc: gl.GLTF2) -> None:
        self.doc = doc
        self.data = bytearray()

    def add(self, array: NDArray[np.generic], kind: str, *, minmax: bool = False, target: int | None = None) -> int:
        ctype = {np.dtype(np.float32): gl.FLOAT, np.dtype(np.uint16): gl.UNSIGNED_SHORT}[array.dtype]
        raw = np.ascontiguousarray(array).tobytes()
        view = gl.BufferView(buffer=0, byteOffset=len(self.data), byteLength=len(raw), target=target)
        self.data += raw + b"\0" * (-len(raw) % 4)
        self.doc.bufferViews.append(view)
        count = array.shape[0] if kind != "SCALAR" or array.ndim > 1 else array.size
        acc = gl.Accessor(bufferView=len(self.doc.bufferViews) - 1, componentType=ctype, count=int(count), type=kind)
        if minmax:
            flat = array.reshape(int(count), -1)
            acc.min = [float(v) for v in flat.min(axis=0)]
            acc.max = [float(v) for v in flat.max(axis=0)]
        self.doc.accessors.append(acc)
        return len(self.doc.accessors) - 1


def _subject(doc: gl.GLTF2, blob: _Blob, s: GltfSubject, scene: list[int]) -> None:
    offsets = np.asarray(s.offsets, dtype=np.float64)
    names, parents, ends = BONE_NAMES, PARENTS, None
    if s.hands is not None and s.hand_skeleton is not None:  # the finger bones join the body's (module doc)
        names, parents = EXTENDED_BONE_NAMES, EXTENDED_PARENTS
        ends = leaf_ends(offsets, s.hand_skeleton, END_FRACTION)
        offsets = extended_offsets(offsets, s.hand_skeleton)
    m = len(parents)
    rest = rest_positions(offsets, s.root_height, parents)
    base = len(doc.nodes) + 1  # node index of joint 0 (after the armature root)
    doc.nodes.append(gl.Node(name=s.name, children=[base]))
    scene.append(base - 1)
    for b in range(m):
        t = (0.0, float(s.root_height), 0.0) if b == 0 else tuple(float(v) for v in offsets[b])
        kids = [base + c for c in range(m) if parents[c] == b]
        doc.nodes.append(gl.Node(name=names[b], translation=list(t), children=kids or []))
    ibm = np.tile(np.eye(4, dtype=np.float32), (m, 1, 1))
    ibm[:, 3, :3] = -rest  # column-major: the translation is the last column, stored as the 4th row here
    skin = gl.Skin(name=s.name, joints=list(range(base, base + m)), skeleton=base,
                   inverseBindMatrices=blob.add(ibm.reshape(m, 16), "MAT4"))  # fmt: skip
    doc.skins.append(skin)
    verts, joint_of, tris = _octahedra(rest, offsets, parents, ends)
    joints4 = np.zeros((joint_of.size, 4), dtype=np.uint16)
    joints4[:, 0] = joint_of
    weights = np.zeros((joint_of.size, 4), dtype=np.float32)
    weights[:, 0] = 1.0
    attrs = gl.Attributes(
        POSITION=blob.add(verts.astype(np.float32), "VEC3", minmax=True, target=gl.ARRAY_BUFFER),
        JOINTS_0=blob.add(joints4, "VEC4", target=gl.ARRAY_BUFFER),
        WEIGHTS_0=blob.add(weights, "VEC4", target=gl.ARRAY_BUFFER),
    )
    indices = blob.add(tris.reshape(-1), "SCALAR", target=gl.ELEMENT_ARRAY_BUFFER)
    doc.meshes.append(gl.Mesh(name=f"{s.name} bones", primitives=[gl.Primitive(attributes=attrs, indices=indices)]))
    doc.nodes.append(gl.Node(name=f"{s.name} bones", mesh=len(doc.meshes) - 1, skin=len(doc.skins) - 1))
    scene.append(len(doc.nodes) - 1)

    th = np.asarray(s.thetas, dtype=np.float64)
    n = th.shape[0]
    times = blob.add(np.asarray(s.times, dtype=np.float32), "SCALAR", minmax=True)
    anim = gl.Animation(name=s.name, samplers=[], channels=[])
    wxyz = quat_from_rotvec(th[:, 3:].reshape(n, N_BONES, 3))
    if m > N_BONES and s.hands is not None:
        wxyz = np.concatenate([wxyz, np.asarray(s.hands, dtype=np.float64).reshape(n, -1, 4)], axis=1)
    wxyz = _continuous(wxyz)
    outputs = [(base, "translation", blob.add(th[:, 0:3].astype(np.float32), "VEC3"))]
    xyzw = wxyz[..., [1, 2, 3, 0]].astype(np.float32)
    outputs += [(base + b, "rotation", blob.add(xyzw[:, b], "VEC4")) for b in range(m)]
    for node, path, out in outputs:
        anim.samplers.append(gl.AnimationSampler(input=times, output=out, interpolation="LINEAR"))
        anim.channels.append(
            gl.AnimationChannel(sampler=len(anim.samplers) - 1, target=gl.AnimationChannelTarget(node=node, path=path))
        )
    doc.animations.append(anim)


def glb_bytes(subjects: Sequence[GltfSubject], generator: str = "mocapd") -> bytes:
    """The ``.glb`` file of ``subjects`` (see the module doc)."""
    if not subjects:
        raise InputError("glTF export needs at least one subject")
    doc = gl.GLTF2(asset=gl.Asset(version="2.0", generator=generator))
    blob = _Blob(doc)
    scene: list[int] = []
    for s in subjects:
        _subject(doc, blob, s, scene)
    doc.scenes = [gl.Scene(name="mocapd", nodes=scene)]
    doc.scene = 0
    doc.buffers = [gl.Buffer(byteLength=len(blob.data))]
    doc.set_binary_blob(bytes(blob.data))
    return b"".join(doc.save_to_bytes())


__all__ = ["GltfSubject", "glb_bytes", "rest_positions"]
