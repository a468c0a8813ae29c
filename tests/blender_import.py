"""Run inside Blender's Python (the ``bpy`` wheel in ``.venv-bpy``): import a glTF, BVH or FBX file and report what
Blender made of it, as JSON on stdout.

Usage: ``python tests/blender_import.py gltf|bvh|fbx FILE FPS SAMPLE [SAMPLE...]``. For each armature: its bone
names, the frames of its keyframes, and at the keyframes numbered ``SAMPLE`` (0 = first) every pose bone's head
in world coordinates, converted back from Blender's Z-up to Y-up (``(x, y, z)_yup = (x, z, -y)_blender``), in
metres. An FBX is imported with the importer's defaults (it reads the file's axes, unit and frame rate; the first
key lands on frame 1), and the file itself is read with the importer's parser: the GlobalSettings that engines
read (axes, unit scale, frame rate), the animation stacks, and the armature nodes' local transforms. Standalone:
Blender's Python has neither mocapd nor its dependencies.
"""

from __future__ import annotations

import json
import sys
from typing import Any

import bpy


def _fcurves(action: Any) -> list[Any]:
    """F-curves of an action, legacy or layered (Blender 4.4+)."""
    curves = getattr(action, "fcurves", None)
    if curves is not None and len(curves):
        return list(curves)
    out: list[Any] = []
    for layer in getattr(action, "layers", []):
        for strip in layer.strips:
            for bag in strip.channelbags:
                out.extend(bag.fcurves)
    return out


def _keyframes(action: Any) -> list[float]:
    frames = {round(k.co[0], 4) for fc in _fcurves(action) for k in fc.keyframe_points}
    return sorted(frames)


def main(argv: list[str]) -> dict[str, Any]:
    kind, path, fps, samples = argv[0], argv[1], int(argv[2]), [int(v) for v in argv[3:]]
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.fps, scene.render.fps_base = fps, 1.0
    if kind == "gltf":
        bpy.ops.import_scene.gltf(filepath=path)
    elif kind == "fbx":
        bpy.ops.import_scene.fbx(filepath=path)
    else:
        # BVH in centimetres, Y up; Blender's importer numbers the first frame 1.
        bpy.ops.import_anim.bvh(filepath=path, global_scale=0.01, frame_start=1, use_fps_scale=False,
                                rotate_mode="NATIVE", axis_forward="-Z", axis_up="Y")  # fmt: skip
    report: dict[str, Any] = {"version": bpy.app.version_string, "armatures": {}, "meshes": {},
                              "fps": scene.render.fps / scene.render.fps_base}  # fmt: skip
    if kind == "fbx":
        report["fbx"] = fbx_structure(path)
    for ob in scene.objects:
        if ob.type == "MESH":
            mods = [m.object.name for m in ob.modifiers if m.type == "ARMATURE" and m.object is not None]
            report["meshes"][ob.name] = {"vertices": len(ob.data.vertices), "armature": mods,
                                         "groups": len(ob.vertex_groups)}  # fmt: skip
    arms = [ob for ob in scene.objects if ob.type == "ARMATURE"]
    for arm in arms:
        anim = arm.animation_data
        action = anim.action if anim is not None else None
        if action is None:  # the importer may stash the animation in an NLA track
            tracks = [t for t in (anim.nla_tracks if anim else []) for _ in t.strips]
            action = tracks[0].strips[0].action if tracks else None
            if action is not None:
                arm.animation_data.action = action
        keys = _keyframes(action) if action is not None else []
        entry: dict[str, Any] = {"bones": [b.name for b in arm.data.bones], "keyframes": keys,
                                 "action": action.name if action else None, "samples": {}}  # fmt: skip
        for i in samples:
            if i >= len(keys):
                continue
            frame = keys[i]
            scene.frame_set(int(frame), subframe=frame - int(frame))
            bpy.context.view_layer.update()
            heads = {}
            for pb in arm.pose.bones:
                w = arm.matrix_world @ pb.head
                heads[pb.name] = [w.x, w.z, -w.y]
            entry["samples"][str(i)] = heads
        report["armatures"][arm.name] = entry
    return report


def _props70(elem: Any) -> dict[str, list[Any]]:
    """The ``P`` entries of an element's Properties70: name -> values (bytes decoded)."""
    out: dict[str, list[Any]] = {}
    for child in elem.elems:
        if child.id == b"Properties70":
            for prop in child.elems:
                vals = [v.decode("utf-8", "replace") if isinstance(v, bytes) else v for v in prop.props]
                out[vals[0]] = vals[4:]
    return out


def fbx_structure(path: str) -> dict[str, Any]:
    """What an engine's importer reads first: GlobalSettings, the takes, and each Null model's (armature node's)
    local transform (absent = identity), from the binary file itself."""
    from io_scene_fbx import parse_fbx

    root, version = parse_fbx.parse(path)
    top = {e.id: e for e in root.elems}
    settings = _props70(top[b"GlobalSettings"])
    keys = ("UpAxis", "UpAxisSign", "FrontAxis", "FrontAxisSign", "CoordAxis", "CoordAxisSign", "UnitScaleFactor",
            "TimeMode", "CustomFrameRate")  # fmt: skip
    models, stacks = {}, []
    for e in top[b"Objects"].elems:
        name = e.props[1].split(b"\x00")[0].decode() if len(e.props) > 1 else ""
        if e.id == b"Model":
            props = _props70(e)
            models[name] = {"type": e.props[2].decode(), **{k: props.get(k, []) for k in
                            ("Lcl Translation", "Lcl Rotation", "Lcl Scaling")}}  # fmt: skip
        elif e.id == b"AnimationStack":
            stacks.append(name)
    return {"version": version, "settings": {k: settings.get(k, [None])[0] for k in keys}, "models": models,
            "stacks": stacks}  # fmt: skip


if __name__ == "__main__":
    print("MOCAPD-REPORT " + json.dumps(main(sys.argv[1:])))
