"""Armatures driven by the stream: one per subject, built from its skeleton, posed from each frame.

The armature object is rotated +90° about X, so inside it everything is in mocapd's native frame (+Y up, metres,
T-pose facing +Z) and Blender shows it Z-up. Bones are built at the rest joint positions (head: the joint, tail:
its first child or, for a leaf, half its offset further). A frame gives each bone's rotation ``L_b`` relative to
the T-pose in its parent's frame; Blender's pose basis is relative to the bone's own rest frame ``R_b``, so the
basis rotation is ``R_bᵀ · L_b · R_b`` (the same rotation seen from the bone's axes), and the root's location
is ``R_0ᵀ (root − head_0)``. Posing therefore reproduces mocapd's forward kinematics exactly (float32).
"""

from __future__ import annotations

import math
from typing import Any

import bpy
from mathutils import Matrix, Quaternion, Vector

PREFIX = "mocapd "
"""Armature object names: PREFIX + subject id."""


def rest_heads(offsets: list[float], parents: list[int]) -> list[Vector]:
    """Rest joint positions (native frame) from the stream's 63 offsets."""
    heads: list[Vector] = []
    for b, p in enumerate(parents):
        off = Vector(offsets[3 * b : 3 * b + 3])
        heads.append(off.copy() if p < 0 else heads[p] + off)
    return heads


def _build(ob: Any, skeleton: dict[str, Any]) -> None:
    bones, parents, offsets = skeleton["bones"], skeleton["parents"], skeleton["offsets"]
    heads = rest_heads(offsets, parents)
    view_layer = bpy.context.view_layer
    previous = view_layer.objects.active
    view_layer.objects.active = ob
    bpy.ops.object.mode_set(mode="EDIT")
    eb = ob.data.edit_bones
    for bone in list(eb):
        eb.remove(bone)
    made: list[Any] = []
    for b, name in enumerate(bones):
        bone = eb.new(name)
        child = next((c for c, p in enumerate(parents) if p == b), None)
        bone.head = heads[b]
        own = Vector(offsets[3 * b : 3 * b + 3])
        tail = heads[child] if child is not None else heads[b] + 0.5 * own
        if (tail - heads[b]).length < 1e-4:
            tail = heads[b] + Vector((0.0, 0.05, 0.0))
        bone.tail = tail
        if parents[b] >= 0:
            bone.parent = made[parents[b]]
        made.append(bone)
    bpy.ops.object.mode_set(mode="OBJECT")
    view_layer.objects.active = previous
    for pb in ob.pose.bones:
        pb.rotation_mode = "QUATERNION"


def ensure_armature(subject: str, key: str, skeleton: dict[str, Any]) -> Any:
    """The armature object of ``subject``, (re)built when its skeleton key changed."""
    name = PREFIX + subject
    ob = bpy.data.objects.get(name)
    if ob is None:
        data = bpy.data.armatures.new(name)
        ob = bpy.data.objects.new(name, data)
        bpy.context.scene.collection.objects.link(ob)
        ob.rotation_euler = (math.radians(90.0), 0.0, 0.0)  # mocapd's +Y up → Blender's +Z up
        ob["mocapd_subject"] = subject
    if ob.get("mocapd_skeleton") != key or len(ob.data.bones) != len(skeleton["bones"]):
        _build(ob, skeleton)
        ob["mocapd_skeleton"] = key
    return ob


def pose(ob: Any, subject: dict[str, Any], names: list[str]) -> None:
    """Pose ``ob`` from one subject map of a frame message (``root``, ``rot``); ``names``: the stream's bones."""
    rot = subject["rot"]
    index = {n: i for i, n in enumerate(names)}
    for pb in ob.pose.bones:
        rest = pb.bone.matrix_local
        r = rest.to_quaternion()
        i = 4 * index[pb.name]
        pb.rotation_quaternion = r.inverted() @ Quaternion(rot[i : i + 4]) @ r
        if pb.parent is None:
            pb.location = r.inverted().to_matrix() @ (Vector(subject["root"]) - rest.to_translation())


def sample(ob: Any) -> list[float]:
    """The posed armature's channels as one row: per pose bone its quaternion (w, x, y, z), then the root's
    location (x, y, z) — what :func:`write_take` keys."""
    row: list[float] = []
    for pb in ob.pose.bones:
        row.extend(pb.rotation_quaternion)
    root = next(pb for pb in ob.pose.bones if pb.parent is None)
    row.extend(root.location)
    return row


def write_take(ob: Any, frames: list[int], rows: list[list[float]]) -> int:
    """Key a recorded take in one go: one F-curve per channel, all its keyframes set at once (keying bone by
    bone while streaming costs milliseconds per key, far too slow at 60 Hz). Returns the keyframes per curve."""
    if not frames:
        return 0
    if ob.animation_data is None:
        ob.animation_data_create()
    action = ob.animation_data.action
    if action is None:
        action = ob.animation_data.action = bpy.data.actions.new(f"{ob.name} take")
    channels: list[tuple[str, int, str]] = []
    for pb in ob.pose.bones:
        channels += [(f'pose.bones["{pb.name}"].rotation_quaternion', i, pb.name) for i in range(4)]
    root = next(pb for pb in ob.pose.bones if pb.parent is None)
    channels += [(f'pose.bones["{root.name}"].location', i, root.name) for i in range(3)]
    for c, (path, index, group) in enumerate(channels):
        curve = _fcurve(action, ob, path, index, group)
        points = curve.keyframe_points
        old = [v for p in points for v in p.co]
        new = [v for f, row in zip(frames, rows, strict=True) for v in (float(f), row[c])]
        points.add(len(frames))
        points.foreach_set("co", old + new)
        for p in points:
            p.interpolation = "LINEAR"
        curve.update()
    return len(frames)


def _fcurve(action: Any, ob: Any, path: str, index: int, group: str) -> Any:
    """The action's F-curve for a channel, made when missing (layered actions of Blender 4.4+, or legacy)."""
    ensure = getattr(action, "fcurve_ensure_for_datablock", None)
    if ensure is not None:
        return ensure(ob, path, index=index)  # Blender 4.4+ groups the curves per bone itself
    curve = action.fcurves.find(path, index=index)
    return curve if curve is not None else action.fcurves.new(path, index=index, action_group=group)


def world_heads(ob: Any) -> dict[str, list[float]]:
    """Each pose bone's head in mocapd's frame (+Y up), after the depsgraph update: for checks and tools."""
    to_native = Matrix.Rotation(math.radians(-90.0), 4, "X")
    out = {}
    for pb in ob.pose.bones:
        w = to_native @ ob.matrix_world @ pb.head
        out[pb.name] = [w.x, w.y, w.z]
    return out
