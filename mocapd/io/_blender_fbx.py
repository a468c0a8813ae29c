"""Runs inside Blender (``blender --background --python`` or a Python with the ``bpy`` module), never in mocapd's
own process: builds one armature per subject from a job written by :mod:`mocapd.io.fbx_export` and writes the
scene with Blender's own FBX exporter. Standalone: Blender's Python has numpy but not mocapd.

Usage: ``python _blender_fbx.py JOB.json`` (after ``--`` when run by the ``blender`` binary). The job names the
``.npz`` with the arrays (per subject ``k``: ``offsets_k`` (21, 3) m, ``root_k`` (n, 3) m, ``quat_k`` (n, 21, 4)
local rotations (w, x, y, z), all in mocapd's frame), the subjects (name, root height, first frame), the bone
names and parents (a subject with fingers has its own ``bones`` and ``parents``, 51 of them, and ``tails_k`` (51, 3)
m, each bone's rest tail: :mod:`mocapd.protocols.fingers`), the frame rate, the units (``cm`` or ``m``), the up
axis (``y`` or ``z``), the take's name and the output path. Prints ``MOCAPD-FBX {json}`` on success.

The scene, per subject:

- An armature object named after the subject (FBX and Maya reserve ``:``, so ``suit:suit0`` becomes
  ``suit_suit0``) with the 21 bones of DESIGN.md at the subject's rest joints (the T-pose facing forward, standing
  on the floor: Hips at the rest root height), each bone's tail at its first child's joint (a leaf's: half its
  offset further). Its bones are built directly in the file's frame and units and the object carries the inverse
  of the exporter's axis conversion, so the armature's FBX node is the identity and the bind pose is the rest.
  File frames: ``y`` = mocapd's own (right-handed, +Y up, facing +Z); ``z`` = Blender's (+Z up, facing -Y).
- A small skinned mesh bound to it (one octahedron per bone, rigidly weighted), so engines that import skeletons
  only with a skeletal mesh (Unreal) get one.
- Keys on every exported frame: each bone's rotation is its local rotation ``L`` seen from the bone's rest axes
  ``R`` (``Rᵀ L R``), the Hips' location the root's offset from its rest joint; so the posed bones reproduce
  mocapd's forward kinematics exactly. Before its first frame a subject holds its first pose, after its last its
  last (the take is one timeline for every subject).

Export: one take (the scene, named ``take``) baked at every frame, no leaf bones, no simplification; units by
the scene's unit scale (``cm``: numbers in centimetres, FBX UnitScaleFactor 1; ``m``: metres, 100), applied as
the FBX unit scale rather than as a node scale. Written to a temporary file beside the output, then renamed.
"""

from __future__ import annotations

import json
import math
import os
import sys
from typing import Any

import bpy
import numpy as np
from mathutils import Matrix, Quaternion, Vector

TO_BLENDER = Matrix.Rotation(math.radians(90.0), 3, "X")  # mocapd (+Y up, facing +Z) -> Blender (+Z up, facing -Y)
AXES = {"y": ("-Z", "Y"), "z": ("Y", "Z")}  # the exporter's (axis_forward, axis_up) per up axis
END_FRACTION = 0.5
MESH_WIDTH = 0.12  # octahedron half-width over bone length
MIN_WIDTH_M = 0.01


def file_frame(up: str) -> Matrix:
    """mocapd axes -> the file's axes (3×3)."""
    return Matrix.Identity(3) if up == "y" else TO_BLENDER.copy()


def rest_heads(offsets: np.ndarray, parents: list[int], root_height: float) -> list[Vector]:
    heads: list[Vector] = []
    for b, p in enumerate(parents):
        heads.append(Vector((0.0, root_height, 0.0)) if p < 0 else heads[p] + Vector(offsets[b].tolist()))
    return heads


def tails(heads: list[Vector], offsets: np.ndarray, parents: list[int]) -> list[Vector]:
    out = []
    for b, head in enumerate(heads):
        child = next((c for c, p in enumerate(parents) if p == b), None)
        tail = heads[child] if child is not None else head + END_FRACTION * Vector(offsets[b].tolist())
        out.append(tail if (tail - head).length > 1e-4 else head + Vector((0.0, 0.05, 0.0)))
    return out


def build_armature(name: str, bones: list[str], parents: list[int], heads: list[Vector], ends: list[Vector],
                   to_file: Matrix, scale: float, obj_rotation: Matrix) -> Any:  # fmt: skip
    data = bpy.data.armatures.new(name)
    ob = bpy.data.objects.new(name, data)
    bpy.context.scene.collection.objects.link(ob)
    ob.matrix_world = obj_rotation.to_4x4()
    bpy.context.view_layer.objects.active = ob
    bpy.ops.object.mode_set(mode="EDIT")
    made: list[Any] = []
    for b, bone in enumerate(bones):
        eb = data.edit_bones.new(bone)
        eb.head = scale * (to_file @ heads[b])
        eb.tail = scale * (to_file @ ends[b])
        if parents[b] >= 0:
            eb.parent = made[parents[b]]
        made.append(eb)
    bpy.ops.object.mode_set(mode="OBJECT")
    for pb in ob.pose.bones:
        pb.rotation_mode = "QUATERNION"
    return ob


def build_mesh(arm: Any, name: str, min_width: float) -> Any:
    """One octahedron per bone, in the armature's space, each vertex rigidly bound to its bone."""
    verts: list[tuple[float, float, float]] = []
    faces: list[tuple[int, int, int]] = []
    groups: list[tuple[str, list[int]]] = []
    for bone in arm.data.bones:
        head, tail = bone.head_local, bone.tail_local
        axis = tail - head
        length = axis.length
        w = max(MESH_WIDTH * length, min_width)
        side = axis.orthogonal().normalized() * w
        other = axis.normalized().cross(side)
        mid = head + 0.2 * axis
        k = len(verts)
        verts += [tuple(v) for v in (head, mid + side, mid + other, mid - side, mid - other, tail)]
        ring = [1, 2, 3, 4]
        for i in range(4):
            a, c = ring[i], ring[(i + 1) % 4]
            faces += [(k, k + c, k + a), (k + 5, k + a, k + c)]
        groups.append((bone.name, list(range(k, k + 6))))
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata(verts, [], faces)
    mesh.update()
    ob = bpy.data.objects.new(name, mesh)
    bpy.context.scene.collection.objects.link(ob)
    ob.parent = arm
    for bone, idx in groups:
        ob.vertex_groups.new(name=bone).add(idx, 1.0, "REPLACE")
    mod = ob.modifiers.new("Armature", "ARMATURE")
    mod.object = arm
    return ob


def key_subject(arm: Any, first: int, root: np.ndarray, quat: np.ndarray, to_file: Matrix, scale: float,
                names: list[str]) -> None:  # fmt: skip
    """Key every frame: bone rotations ``Rᵀ (C L Cᵀ) R`` and the Hips' location ``Rᵀ (C root s − head)``; ``quat``'s
    bones in the order of ``names`` (Blender lists pose bones depth first: with fingers that is not the job's order)."""
    column = {name: i for i, name in enumerate(names)}
    n = root.shape[0]
    frames = np.arange(first, first + n, dtype=np.float64)
    C = np.array(to_file)
    arm.animation_data_create()
    action = bpy.data.actions.new(f"{arm.name} take")
    arm.animation_data.action = action
    for pb in arm.pose.bones:
        R = np.array(pb.bone.matrix_local.to_3x3())
        # Quaternions in the file's frame: (w, C v) (C is a rotation), then seen from the bone's rest axes.
        q = quat[:, column[pb.name], :]
        v = q[:, 1:] @ C.T
        local = np.concatenate([q[:, :1], v], axis=1)
        r = Quaternion(Matrix(R.tolist()).to_quaternion())
        rw, rv = r.w, np.array(r[1:])
        # basis = r⁻¹ ⊗ local ⊗ r
        basis = _qmul(_qmul(np.array([rw, *(-rv)]), local), np.array([rw, *rv]))
        basis[basis[:, 0] < 0] *= -1.0
        _key(action, arm, f'pose.bones["{pb.name}"].rotation_quaternion', basis, frames)
        if pb.parent is None:
            loc = (scale * (root @ C.T) - np.array(pb.bone.head_local)) @ R  # Rᵀ (p − head)
            _key(action, arm, f'pose.bones["{pb.name}"].location', loc, frames)


def _qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    aw, ax, ay, az = np.moveaxis(np.broadcast_to(a, np.broadcast_shapes(a.shape, b.shape)), -1, 0)
    bw, bx, by, bz = np.moveaxis(np.broadcast_to(b, np.broadcast_shapes(a.shape, b.shape)), -1, 0)
    w = aw * bw - ax * bx - ay * by - az * bz
    x = aw * bx + ax * bw + ay * bz - az * by
    y = aw * by - ax * bz + ay * bw + az * bx
    z = aw * bz + ax * by - ay * bx + az * bw
    return np.stack([w, x, y, z], axis=-1)


def _key(action: Any, ob: Any, path: str, values: np.ndarray, frames: np.ndarray) -> None:
    """Key all frames of one property at once (one F-curve per component)."""
    for i in range(values.shape[1]):
        ensure = getattr(action, "fcurve_ensure_for_datablock", None)
        curve = ensure(ob, path, index=i) if ensure is not None else action.fcurves.new(path, index=i)
        points = curve.keyframe_points
        points.add(frames.size)
        points.foreach_set("co", np.stack([frames, values[:, i]], axis=1).ravel().tolist())
        curve.update()


def main(job_path: str) -> dict[str, Any]:
    with open(job_path, encoding="utf-8") as fh:
        job = json.load(fh)
    arrays = np.load(job["arrays"])
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.name = job["take"]
    rate = float(job["rate_hz"])
    scene.render.fps = max(1, round(rate))
    scene.render.fps_base = scene.render.fps / rate
    scale = 100.0 if job["units"] == "cm" else 1.0
    scene.unit_settings.system = "METRIC"
    scene.unit_settings.scale_length = 1.0 / scale  # the FBX unit scale: cm files are 1 cm per unit, m files 100
    to_file = file_frame(job["up"])
    obj_rotation = TO_BLENDER @ to_file.inverted()
    bones, parents = list(job["bones"]), [int(p) for p in job["parents"]]
    last = 0
    for k, subject in enumerate(job["subjects"]):
        offsets = arrays[f"offsets_{k}"]
        names, links = list(subject.get("bones", bones)), [int(p) for p in subject.get("parents", parents)]
        heads = rest_heads(offsets, links, float(subject["root_height"]))
        ends = ([Vector(v.tolist()) for v in arrays[f"tails_{k}"]] if f"tails_{k}" in arrays
                else tails(heads, offsets, links))  # fmt: skip
        arm = build_armature(subject["name"], names, links, heads, ends, to_file, scale, obj_rotation)
        build_mesh(arm, f"{subject['name']}_mesh", MIN_WIDTH_M * scale)
        root, quat = arrays[f"root_{k}"], arrays[f"quat_{k}"]
        key_subject(arm, int(subject["first_frame"]), root, quat, to_file, scale, names)
        last = max(last, int(subject["first_frame"]) + root.shape[0] - 1)
    scene.frame_start, scene.frame_end = 0, last
    out = job["output"]
    # Beside the output under a short name: the output's own name plus a suffix went over the 255 bytes a file name
    # may have for names of 241-255 bytes, which pass mocapd's check (issue 45). Cut on a character boundary.
    short = os.path.basename(out).encode()[:100].decode("utf-8", "ignore")
    tmp = os.path.join(os.path.dirname(out), f".{short}.part-{os.getpid()}.fbx")
    forward, up = AXES[job["up"]]
    try:
        result = bpy.ops.export_scene.fbx(
            filepath=tmp, use_selection=False, object_types={"ARMATURE", "MESH"}, apply_unit_scale=True,
            global_scale=1.0, apply_scale_options="FBX_SCALE_UNITS", axis_forward=forward, axis_up=up,
            use_space_transform=True, bake_space_transform=False, add_leaf_bones=False, primary_bone_axis="Y",
            secondary_bone_axis="X", armature_nodetype="NULL", use_armature_deform_only=False, bake_anim=True,
            bake_anim_use_all_bones=True, bake_anim_use_nla_strips=False, bake_anim_use_all_actions=False,
            bake_anim_force_startend_keying=True, bake_anim_step=1.0, bake_anim_simplify_factor=0.0,
            mesh_smooth_type="OFF", use_mesh_modifiers=False, use_custom_props=False, path_mode="AUTO",
        )  # fmt: skip
        if result != {"FINISHED"}:
            raise RuntimeError(f"Blender's FBX exporter returned {result}")
        os.replace(tmp, out)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
    return {"output": out, "frames": last + 1, "armatures": [s["name"] for s in job["subjects"]],
            "blender": bpy.app.version_string}  # fmt: skip


if __name__ == "__main__":
    argv = sys.argv[sys.argv.index("--") + 1 :] if "--" in sys.argv else sys.argv[1:]
    print("MOCAPD-FBX " + json.dumps(main(argv[0])), flush=True)
