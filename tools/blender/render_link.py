"""Render what the Blender live link shows, headless (Cycles on the CPU): for the README's picture.

Run with a Python that has ``bpy`` (``.venv-bpy/bin/python``) while a daemon streams::

    .venv-bpy/bin/python tools/blender/render_link.py ws://127.0.0.1:8766/ OUT.png

It installs the add-on into a throw-away Blender user folder, connects it, follows the stream for two seconds,
then renders the armatures (a thin cylinder per bone, since armatures themselves do not render) with a floor.
"""

from __future__ import annotations

import importlib
import math
import os
import sys
import tempfile
import time
from pathlib import Path

import bpy
from mathutils import Vector

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from tools.blender import install_addon  # the add-on's installer, in the checkout

COLOURS = [(1.0, 0.23, 0.19, 1.0), (0.04, 0.52, 1.0, 1.0), (0.19, 0.82, 0.35, 1.0), (1.0, 0.84, 0.04, 1.0)]


def _material(name: str, rgba: tuple[float, float, float, float]) -> bpy.types.Material:
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    mat.node_tree.nodes["Principled BSDF"].inputs["Base Color"].default_value = rgba
    return mat


def _bones_as_cylinders(arm: bpy.types.Object, mat: bpy.types.Material) -> None:
    for pb in arm.pose.bones:
        head, tail = arm.matrix_world @ pb.head, arm.matrix_world @ pb.tail
        d = tail - head
        bpy.ops.mesh.primitive_cylinder_add(radius=0.03, depth=d.length, location=(head + tail) / 2)
        cyl = bpy.context.active_object
        cyl.rotation_mode = "QUATERNION"
        cyl.rotation_quaternion = Vector((0, 0, 1)).rotation_difference(d.normalized())
        cyl.data.materials.append(mat)
        bpy.ops.mesh.primitive_uv_sphere_add(radius=0.045, location=head)
        bpy.context.active_object.data.materials.append(mat)


def main(url: str, out: str) -> None:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    install_addon.install(save=False)
    link = importlib.import_module("mocapd_link")
    scene = bpy.context.scene
    scene.mocapd_url = url
    bpy.ops.mocapd.connect()
    end = time.monotonic() + 2.0
    while time.monotonic() < end:
        time.sleep(link.TIMER_S)
        link.tick()
    bpy.ops.mocapd.disconnect()
    bpy.context.view_layer.update()
    arms = sorted((o for o in scene.objects if o.type == "ARMATURE"), key=lambda o: o.name)
    for k, arm in enumerate(arms):
        _bones_as_cylinders(arm, _material(arm.name, COLOURS[k % len(COLOURS)]))
    bpy.ops.mesh.primitive_plane_add(size=12.0)
    bpy.context.active_object.data.materials.append(_material("floor", (0.35, 0.37, 0.4, 1.0)))
    bpy.ops.object.light_add(type="SUN", rotation=(math.radians(40), 0.0, math.radians(30)))
    bpy.context.active_object.data.energy = 3.0
    bpy.ops.object.empty_add(location=(0.0, -1.0, 0.9))
    target = bpy.context.active_object
    bpy.ops.object.camera_add(location=(5.5, -6.5, 3.0))
    scene.camera = bpy.context.active_object
    aim = scene.camera.constraints.new(type="TRACK_TO")
    aim.target, aim.track_axis, aim.up_axis = target, "TRACK_NEGATIVE_Z", "UP_Y"
    scene.world = bpy.data.worlds.new("world")
    scene.world.color = (0.05, 0.06, 0.07)
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = 24
    scene.render.resolution_x, scene.render.resolution_y = 640, 360
    scene.render.filepath = out
    bpy.ops.render.render(write_still=True)
    print(f"rendered {len(arms)} armature(s) to {out}")


if __name__ == "__main__":
    os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="mocapd-blender-"))
    main(sys.argv[1], sys.argv[2])
