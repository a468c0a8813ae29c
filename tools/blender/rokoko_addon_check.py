"""Rokoko's own Blender add-on receiving a live mocapd ``[udp.rokoko]`` stream, headless: the hand check of the
Rokoko Studio Live output (docs/streaming-udp.md). The add-on is Rokoko's (LGPL-3.0), fetched by whoever runs this,
never part of mocapd.

Run with Blender's Python (``.venv-bpy/bin/python``) while a daemon streams Rokoko to PORT and WebSocket to URL::

    .venv-bpy/bin/python tools/blender/rokoko_addon_check.py ADDON_PARENT PORT ws://127.0.0.1:8766/ OUT.png \\
        [--libs DIR] [--seconds S]

``ADDON_PARENT`` holds the add-on's package directory ``rokoko_studio_live`` (e.g. ``git archive`` of
github.com/Rokoko/rokoko-studio-live-blender); ``--libs`` a directory with the ``lz4`` module for Blender's
Python (``pip install --target DIR lz4``), which the add-on needs to read LZ4 datagrams.

What it does, as a user would in the add-on's panels: registers the add-on; builds, per subject, an armature with
the add-on's bone names in a T-pose facing -Y, sized from the daemon's skeleton (from the WebSocket hello), and
presses *Set as T-Pose* (``rsl.init_tpose``) and *Auto Detect* (``rsl.detect_actor_bones``) on it; starts the
add-on's receiver and calls it at 60 Hz, as its modal operator's timer would (headless Blender has no window, so no
modal operator runs); assigns each armature its actor once the add-on lists it. Each applied datagram's
``frame`` is matched with the same frame from the WebSocket stream (globals, native), and every driven bone's
world rotation and head is compared with mocapd's. Prints a JSON summary and renders the armatures to OUT.png.
"""

from __future__ import annotations

import importlib
import json
import math
import os
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import bpy
from mathutils import Matrix, Quaternion, Vector

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from tools.blender.mocapd_link.wsclient import Connection

# Rokoko bone -> (parent, mocapd bone whose global rotation drives it, head (mocapd bone joint, or a rule), tail).
BONES: dict[str, tuple[str | None, str, str, str]] = {
    "hip": (None, "Hips", "Hips", "up"),
    "spine": ("hip", "Spine", "Spine", "Spine3"),
    "chest": ("spine", "Spine3", "Spine3", "Neck"),
    "neck": ("chest", "Neck", "Neck", "Head"),
    "head": ("neck", "Head", "Head", "up"),
    "leftShoulder": ("chest", "Spine3", "clavicle:LeftUpperArm", "LeftUpperArm"),
    "leftUpperArm": ("leftShoulder", "LeftUpperArm", "LeftUpperArm", "LeftLowerArm"),
    "leftLowerArm": ("leftUpperArm", "LeftLowerArm", "LeftLowerArm", "LeftHand"),
    "leftHand": ("leftLowerArm", "LeftHand", "LeftHand", "end"),
    "rightShoulder": ("chest", "Spine3", "clavicle:RightUpperArm", "RightUpperArm"),
    "rightUpperArm": ("rightShoulder", "RightUpperArm", "RightUpperArm", "RightLowerArm"),
    "rightLowerArm": ("rightUpperArm", "RightLowerArm", "RightLowerArm", "RightHand"),
    "rightHand": ("rightLowerArm", "RightHand", "RightHand", "end"),
    "leftUpLeg": ("hip", "LeftUpperLeg", "LeftUpperLeg", "LeftLowerLeg"),
    "leftLeg": ("leftUpLeg", "LeftLowerLeg", "LeftLowerLeg", "LeftFoot"),
    "leftFoot": ("leftLeg", "LeftFoot", "LeftFoot", "LeftToes"),
    "leftToe": ("leftFoot", "LeftToes", "LeftToes", "end"),
    "rightUpLeg": ("hip", "RightUpperLeg", "RightUpperLeg", "RightLowerLeg"),
    "rightLeg": ("rightUpLeg", "RightLowerLeg", "RightLowerLeg", "RightFoot"),
    "rightFoot": ("rightLeg", "RightFoot", "RightFoot", "RightToes"),
    "rightToe": ("rightFoot", "RightToes", "RightToes", "end"),
}
# Bones whose heads are mocapd joints reached through the same rotations: the legs and the hips (the spine chain,
# and so the neck, head and arms, pass through Rokoko's two spine bones where mocapd has four).
EXACT_HEADS = ("hip", "leftUpLeg", "leftLeg", "leftFoot", "leftToe", "rightUpLeg", "rightLeg", "rightFoot", "rightToe")
TO_BLENDER = Matrix.Rotation(math.radians(90.0), 3, "X")  # mocapd (+Y up, facing +Z) -> Blender (+Z up, facing -Y)
COLOURS = [(1.0, 0.23, 0.19, 1.0), (0.19, 0.82, 0.35, 1.0), (0.04, 0.52, 1.0, 1.0), (1.0, 0.84, 0.04, 1.0)]


class Stream:
    """The daemon's WebSocket stream (JSON, native, globals) on a thread: hello skeletons and frames by counter."""

    def __init__(self, url: str) -> None:
        self.conn = Connection(url)
        self.conn.send_text(json.dumps({"type": "subscribe", "encoding": "json", "convention": "native",
                                        "globals": True}))  # fmt: skip
        self.skeletons: dict[str, Any] = {}
        self.bones: list[str] = []
        self.frames: dict[int, dict[str, Any]] = {}
        self.lock = threading.Lock()
        threading.Thread(target=self._run, daemon=True).start()

    def _run(self) -> None:
        while (msg := self.conn.receive()) is not None:
            if isinstance(msg, bytes):
                continue
            m = json.loads(msg)
            with self.lock:
                if m["type"] == "hello":
                    self.skeletons, self.bones = dict(m["skeletons"]), list(m["bones"])
                elif m["type"] == "frame":
                    self.frames[int(m["frame"])] = m
                    for old in [k for k in self.frames if k < int(m["frame"]) - 600]:
                        del self.frames[old]


def native_to_blender(v: Vector) -> Vector:
    return TO_BLENDER @ v


def rest_joints(skeleton: dict[str, Any]) -> dict[str, Vector]:
    """Rest joint positions (mocapd frame) by bone name."""
    heads: list[Vector] = []
    off = skeleton["offsets"]
    for b, p in enumerate(skeleton["parents"]):
        o = Vector(off[3 * b : 3 * b + 3])
        heads.append(o.copy() if p < 0 else heads[p] + o)
    return dict(zip(skeleton["bones"], heads, strict=True))


def offset(skeleton: dict[str, Any], bone: str) -> Vector:
    b = skeleton["bones"].index(bone)
    return Vector(skeleton["offsets"][3 * b : 3 * b + 3])


def build_armature(name: str, skeleton: dict[str, Any], hip_height: float) -> Any:
    """An armature with the add-on's bone names at mocapd's rest joints, T-pose facing -Y, Z up."""
    lift = Vector((0.0, hip_height, 0.0))  # the stream's offsets start at the Hips joint
    j = {b: v + lift for b, v in rest_joints(skeleton).items()}

    def point(rule: str, bone: str) -> Vector:
        if rule.startswith("clavicle:"):
            o = offset(skeleton, rule.split(":")[1])
            return j["Spine3"] + Vector((0.0, o.y, o.z))
        if rule == "up":
            return j[bone] + Vector((0.0, 0.12, 0.0))
        if rule == "end":
            return j[bone] + 0.5 * offset(skeleton, bone)
        return j[rule]

    data = bpy.data.armatures.new(name)
    ob = bpy.data.objects.new(name, data)
    bpy.context.scene.collection.objects.link(ob)
    bpy.context.view_layer.objects.active = ob
    bpy.ops.object.mode_set(mode="EDIT")
    made: dict[str, Any] = {}
    for bone, (parent, src, head, tail) in BONES.items():
        eb = data.edit_bones.new(bone)
        eb.head = native_to_blender(point(head, src))
        eb.tail = native_to_blender(point(tail, src))
        eb.roll = 0.0
        if parent is not None:
            eb.parent = made[parent]
        made[bone] = eb
    bpy.ops.object.mode_set(mode="OBJECT")
    return ob


def global_rotations(frame_subject: dict[str, Any], parents: list[int]) -> list[Quaternion]:
    """mocapd's global bone rotations (native frame) from a frame's local quaternions."""
    rot = frame_subject["rot"]
    out: list[Quaternion] = []
    for b, p in enumerate(parents):
        q = Quaternion(rot[4 * b : 4 * b + 4])
        out.append(q if p < 0 else out[p] @ q)
    return out


def compare(ob: Any, subject: dict[str, Any], skeleton: dict[str, Any], names: list[str]) -> dict[str, Any]:
    """Per driven bone: its world rotation's error (degrees) against mocapd's global rotation of the bone that
    drives it (times the bone's rest), and its head's distance (mm) from mocapd's joint."""
    glob = global_rotations(subject, skeleton["parents"])
    joints = subject["joints"]
    rest = rest_joints(skeleton)
    sp, s3 = names.index("Spine"), names.index("Spine3")
    lower_rest = rest["Spine3"] - rest["Spine"]
    lower_now = Vector(joints[3 * s3 : 3 * s3 + 3]) - Vector(joints[3 * sp : 3 * sp + 3])
    # The stream's spine: Spine's rotation swung to point the lower spine at mocapd's chest (mocapd.protocols.rokoko).
    spine = (glob[sp] @ lower_rest).rotation_difference(lower_now) @ glob[sp]
    rot_deg: dict[str, float] = {}
    head_mm: dict[str, float] = {}
    for bone, (_, src, head, _) in BONES.items():
        pb = ob.pose.bones[bone]
        g = (spine if bone == "spine" else glob[names.index(src)]).to_matrix()
        want = (TO_BLENDER @ g @ TO_BLENDER.transposed()) @ pb.bone.matrix_local.to_3x3()
        got = (ob.matrix_world.to_3x3() @ pb.matrix.to_3x3()).normalized()
        delta = (got @ want.transposed()).to_quaternion()
        rot_deg[bone] = math.degrees(2.0 * math.atan2(Vector((delta.x, delta.y, delta.z)).length, abs(delta.w)))
        if ":" not in head:
            b = names.index(src)
            want_head = native_to_blender(Vector(joints[3 * b : 3 * b + 3]))
            head_mm[bone] = 1e3 * ((ob.matrix_world @ pb.head) - want_head).length
    # What Rokoko's skeleton carries: one lower-spine bone from Spine's joint to the chest (Spine3's joint). With
    # Spine's own rotation it would end here, against where mocapd's chest is (the swing's gain).
    unswung = 1e3 * (glob[sp] @ lower_rest - lower_now).length
    return {"rotation_deg": rot_deg, "head_mm": head_mm, "unswung_chest_mm": unswung}


def _stick(a: Vector, b: Vector, radius: float, mat: Any) -> None:
    d = b - a
    bpy.ops.mesh.primitive_cylinder_add(radius=radius, depth=max(d.length, 1e-3), location=(a + b) / 2)
    cyl = bpy.context.active_object
    cyl.rotation_mode = "QUATERNION"
    cyl.rotation_quaternion = Vector((0, 0, 1)).rotation_difference(d.normalized())
    cyl.data.materials.append(mat)


def render(arms: list[Any], reference: list[list[Vector]], parents: list[int], out: str) -> None:
    """The add-on's armatures as coloured cylinders and spheres, mocapd's own joints of the same frame as thin white
    sticks inside them, on a floor; Cycles on the CPU."""
    scene = bpy.context.scene
    white = bpy.data.materials.new("mocapd")
    white.use_nodes = True
    white.node_tree.nodes["Principled BSDF"].inputs["Base Color"].default_value = (0.95, 0.95, 0.95, 1.0)
    for joints in reference:
        for b, p in enumerate(parents):
            if p >= 0:
                _stick(joints[p], joints[b], 0.008, white)
    for k, arm in enumerate(arms):
        mat = bpy.data.materials.new(arm.name)
        mat.use_nodes = True
        mat.node_tree.nodes["Principled BSDF"].inputs["Base Color"].default_value = COLOURS[k % len(COLOURS)]
        mat.node_tree.nodes["Principled BSDF"].inputs["Alpha"].default_value = 0.55  # mocapd's sticks show through
        for pb in arm.pose.bones:
            head, tail = arm.matrix_world @ pb.head, arm.matrix_world @ pb.tail
            _stick(head, tail, 0.022, mat)
            bpy.ops.mesh.primitive_uv_sphere_add(radius=0.04, location=head)
            bpy.context.active_object.data.materials.append(mat)
    centre = sum((a.matrix_world @ a.pose.bones["hip"].head for a in arms), Vector()) / max(len(arms), 1)
    bpy.ops.mesh.primitive_plane_add(size=14.0)
    floor = bpy.data.materials.new("floor")
    floor.use_nodes = True
    floor.node_tree.nodes["Principled BSDF"].inputs["Base Color"].default_value = (0.35, 0.37, 0.4, 1.0)
    bpy.context.active_object.data.materials.append(floor)
    bpy.ops.object.light_add(type="SUN", rotation=(math.radians(40), 0.0, math.radians(30)))
    bpy.context.active_object.data.energy = 3.0
    bpy.ops.object.empty_add(location=(centre.x, centre.y, 0.9))
    target = bpy.context.active_object
    bpy.ops.object.camera_add(location=(centre.x + 4.5, centre.y - 5.5, 2.6))
    scene.camera = bpy.context.active_object
    aim = scene.camera.constraints.new(type="TRACK_TO")
    aim.target, aim.track_axis, aim.up_axis = target, "TRACK_NEGATIVE_Z", "UP_Y"
    scene.world = bpy.data.worlds.new("world")
    scene.world.color = (0.05, 0.06, 0.07)
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = 24
    scene.render.resolution_x, scene.render.resolution_y = 800, 450
    scene.render.filepath = out
    bpy.ops.render.render(write_still=True)


def main(argv: list[str]) -> dict[str, Any]:
    addon_parent, port, url, out = argv[0], int(argv[1]), argv[2], argv[3]
    opts = dict(zip(argv[4::2], argv[5::2], strict=True))
    if "--libs" in opts:
        sys.path.insert(0, opts["--libs"])
    seconds = float(opts.get("--seconds", "4"))
    bpy.ops.wm.read_factory_settings(use_empty=True)
    sys.path.insert(0, addon_parent)
    addon = importlib.import_module("rokoko_studio_live")
    addon.register()
    from rokoko_studio_live.core import animations, live_data_manager, state_manager  # the add-on's own modules
    from rokoko_studio_live.operators import receiver as receiver_ops

    scene = bpy.context.scene
    scene.rsl_receiver_port = port
    stream = Stream(url)
    # "Start Receiver", minus the modal timer headless Blender cannot run: we call its timer's work ourselves.
    receiver = receiver_ops.receiver
    receiver.start(port)
    receiver_ops.receiver_enabled = True
    animations.clear_animations()
    state_manager.save_scene()
    live = animations.live_data

    def receive() -> bool:
        """One tick of the add-on's receiver; True when it applied a new datagram."""
        time.sleep(1 / scene.rsl_receiver_fps)
        before = id(live.data)
        receiver.run()
        return id(live.data) != before and isinstance(live.data, dict)

    end = time.monotonic() + 60
    while time.monotonic() < end:  # the add-on lists two actors and the WebSocket stream has their skeletons
        if receive() and len(live.actors) >= 2:
            with stream.lock:
                ref = stream.frames.get(int(live.data["frame"]))
            if ref is not None and {s["id"] for s in ref["subjects"]} >= {a["name"] for a in live.actors}:
                break
    else:
        raise AssertionError("no two actors from the add-on's receiver matched with the WebSocket stream")
    names = stream.bones
    arms: dict[str, Any] = {}
    missed: dict[str, list[str]] = {}
    for actor in live.actors:  # per actor, what a user does in the add-on's Objects panel
        subject = next(s for s in ref["subjects"] if s["id"] == actor["name"])
        sk = stream.skeletons[subject["skeleton"]]
        ob = build_armature(f"rokoko {actor['name']}", sk, float(actor["dimensions"]["hipHeight"]))
        ob["mocapd_skeleton"] = subject["skeleton"]
        with bpy.context.temp_override(object=ob, active_object=ob, selected_objects=[ob]):
            bpy.ops.rsl.init_tpose()  # "Set as T-Pose"
            bpy.ops.rsl.detect_actor_bones()  # "Auto Detect"
            missed[actor["name"]] = [b for b in BONES if getattr(ob, f"rsl_actor_{b}") != b]
            for b in BONES:  # what a user would pick where auto-detection missed a bone
                setattr(ob, f"rsl_actor_{b}", b)
            ob.rsl_animations_actors = actor["name"]  # "Actor"
        arms[actor["name"]] = ob

    results: list[dict[str, Any]] = []
    control = 0.0
    drifted = 0
    stop = time.monotonic() + seconds
    applied = 0
    while time.monotonic() < stop:
        if not receive():
            continue
        applied += 1
        bpy.context.view_layer.update()
        with stream.lock:
            ref = stream.frames.get(int(live.data["frame"]))
            earlier = stream.frames.get(int(live.data["frame"]) - 15)
        if ref is None:
            continue
        for name, ob in arms.items():
            actor = live.get_actor_by_obj(ob)  # the actor the add-on drove this armature with
            if actor is None or not actor["meta"]["hasBody"]:
                continue
            drifted += actor["name"] != name  # its Actor choice moved to another actor of the list
            for frame, kind in ((ref, "same"), (earlier, "control")):
                s = next((x for x in frame["subjects"] if x["id"] == actor["name"]), None) if frame else None
                if s is None or ob["mocapd_skeleton"] != s["skeleton"]:
                    continue
                c = compare(ob, s, stream.skeletons[s["skeleton"]], names)
                if kind == "same":
                    results.append({"frame": ref["frame"], "subject": s["id"], **c})
                else:  # the control: the same armature against a quarter second earlier
                    control = max(control, *c["rotation_deg"].values())
    receiver_ops.receiver_enabled = False
    receiver.stop()
    with stream.lock:  # mocapd's joints of the frame the armatures show now
        shown = stream.frames.get(int(live.data["frame"]))
    stream.conn.close()
    reference = [] if shown is None else [
        [native_to_blender(Vector(s["joints"][3 * b : 3 * b + 3])) for b in range(len(names))]
        for s in shown["subjects"] if s["id"] in arms
    ]  # fmt: skip
    parents = stream.skeletons[next(iter(stream.skeletons))]["parents"]
    render(list(arms.values()), reference, parents, out)
    rot = {b: max(r["rotation_deg"][b] for r in results) for b in BONES} if results else {}
    heads = {b: max(r["head_mm"][b] for r in results) for b in results[0]["head_mm"]} if results else {}
    worst = {
        "rotation_deg": max(rot.values(), default=None),
        "head_mm_hip": heads.get("hip"),
        "head_mm_legs": max((heads[b] for b in EXACT_HEADS), default=None),
        "head_mm_by_bone": {b: round(v, 2) for b, v in heads.items()},
        "control_rotation_deg_vs_15_frames_earlier": control,
        "chest_mm_with_spine_unswung": max(r["unswung_chest_mm"] for r in results),
    }
    return {
        "addon_version": list(addon.bl_info["version"]),
        "lz4": live_data_manager.loaded_lz4,
        "datagrams_applied": applied,
        "json_version": live.version,
        "actors": sorted(arms),
        "auto_detect_missed": missed,
        "frames_compared": len(results),
        "actor_choice_moved": drifted,
        "worst": worst,
        "render": out,
    }


if __name__ == "__main__":
    os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="mocapd-blender-"))
    print("MOCAPD-REPORT " + json.dumps(main(sys.argv[1:])))
