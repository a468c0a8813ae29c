"""Run inside Blender's Python (``.venv-bpy``): install the live-link add-on as a user does, connect it to a
running daemon and follow the stream, then record; print a JSON report after ``MOCAPD-REPORT``.

Usage: ``python tests/blender_live.py URL FOLLOW_S RECORD_S`` (following goes on past FOLLOW_S, for at most a
minute, until 40 applied frames showed both subjects). Headless Blender runs no timers, so the script
calls the add-on's timer callback (``mocapd_link.tick``) itself at the add-on's interval. For every frame applied
while following it reports the frame counter, the lag behind the newest frame received, and every armature's
bone heads (mocapd's +Y-up frame).
"""

from __future__ import annotations

import importlib
import json
import sys
import time
from pathlib import Path
from typing import Any

import bpy

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from tools.blender import install_addon  # the add-on's installer, in the checkout

MIN_FULL = 40


def _armatures() -> list[Any]:
    return [ob for ob in bpy.context.scene.objects if ob.type == "ARMATURE" and "mocapd_subject" in ob]


def main(url: str, follow_s: float, record_s: float) -> dict[str, Any]:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    install_addon.install(save=False)
    link_mod = importlib.import_module("mocapd_link")
    rig = importlib.import_module("mocapd_link.rig")
    scene = bpy.context.scene
    scene.render.fps = 60
    scene.mocapd_url = url
    assert bpy.ops.mocapd.connect() == {"FINISHED"}
    samples: list[dict[str, Any]] = []
    end = time.monotonic() + follow_s
    last, full, ticks, start = -1, 0, 0, time.monotonic()
    # At least follow_s seconds, then until MIN_FULL frames showed two subjects (a loaded machine is slow).
    while time.monotonic() < end or (full < MIN_FULL and time.monotonic() < end + 60.0):
        time.sleep(link_mod.TIMER_S)
        link_mod.tick()
        ticks += 1
        state = link_mod.link()
        if state.applied_frame != last:
            last = state.applied_frame
            bpy.context.view_layer.update()
            heads = {ob["mocapd_subject"]: rig.world_heads(ob) for ob in _armatures()}
            samples.append({"frame": last, "lag": state.lag_frames, "heads": heads})
            full += len(heads) >= 2
    follow_elapsed = time.monotonic() - start
    bpy.ops.mocapd.record(start=True)
    end = time.monotonic() + record_s
    while time.monotonic() < end:
        time.sleep(link_mod.TIMER_S)
        link_mod.tick()
    state = link_mod.link()
    recorded = state.recorded_frames
    record_ticks = state.applied
    bpy.ops.mocapd.record(start=False)
    error = state.stream.error
    bpy.ops.mocapd.disconnect()
    actions = {}
    for ob in _armatures():
        act = ob.animation_data.action if ob.animation_data else None
        curves = list(act.fcurves) if act is not None else []
        keys = sorted({round(k.co[0]) for fc in curves for k in fc.keyframe_points})
        actions[ob["mocapd_subject"]] = {"keyframes": len(keys), "first": keys[0] if keys else None,
                                         "last": keys[-1] if keys else None, "curves": len(curves),
                                         "bones": [b.name for b in ob.data.bones]}  # fmt: skip
    return {"samples": samples, "follow_s": follow_elapsed, "ticks": ticks, "recorded_frames": recorded,
            "applied": record_ticks, "actions": actions, "error": error, "frame_end": scene.frame_end}  # fmt: skip


if __name__ == "__main__":
    report = main(sys.argv[1], float(sys.argv[2]), float(sys.argv[3]))
    print("MOCAPD-REPORT " + json.dumps(report))
