"""mocapd live link for Blender: drive one armature per subject from the daemon's WebSocket stream, and record
the takes as keyframes.

Install (docs/blender.md): ``bash tools/blender/install_addon.sh [BLENDER]``, or zip this folder and use
Edit > Preferences > Add-ons > Install from Disk. Then the 3D view's sidebar (N) has a "mocapd" tab: the stream
URL, Connect/Disconnect, Record/Stop, and what arrives.

While connected, a timer on Blender's main thread takes the newest frame the reader thread received (older ones
are skipped, never queued) and poses every subject's armature (:mod:`.rig`); while recording it also keeps each
pose for the frame of the scene's timeline that its solve time falls on (scene fps, from the first recorded frame
at the scene's start frame), and keys the whole take when recording stops (one F-curve write per channel: keying
bone by bone as frames arrive is far too slow for 60 Hz).
"""

from __future__ import annotations

from typing import Any

import bpy

from . import rig
from .stream import StreamLink

bl_info = {
    "name": "mocapd live link",
    "author": "mocapd",
    "version": (1, 0, 0),
    "blender": (4, 2, 0),
    "location": "View3D > Sidebar > mocapd",
    "description": "Drive armatures from a running mocapd daemon (WebSocket stream) and record them as keyframes",
    "category": "Animation",
}

TIMER_S = 1.0 / 120.0
"""Timer interval: twice the stream's 60 Hz, so a frame waits at most half a frame before it is applied."""


class Link:
    """The add-on's state: the stream, the frame last applied, the recording."""

    def __init__(self, stream: StreamLink) -> None:
        self.stream = stream
        self.applied_frame = -1
        self.applied = 0
        self.lag_frames = 0  # newest received - applied, measured right after applying
        self.record_t0_ns: int | None = None
        self.recorded_frames = 0
        self.take: dict[str, tuple[list[int], list[list[float]]]] = {}  # armature -> (frames, channel rows)


class _Current:
    """The add-on's one link (None when disconnected); an object, so operators rebind it without ``global``."""

    link: Link | None = None


def link() -> Link | None:
    """The current link (None when disconnected)."""
    return _Current.link


def _drop_link() -> None:
    if _Current.link is not None:
        _Current.link.stream.stop()
        _Current.link = None


def tick() -> float | None:
    """Apply the newest frame (Blender timer callback; also callable directly, e.g. headless)."""
    state = _Current.link
    if state is None:
        return None
    msg, skeletons = state.stream.take()
    if msg is not None:
        apply_frame(state, msg, skeletons)
    return TIMER_S


def apply_frame(state: Link, msg: dict[str, Any], skeletons: dict[str, Any]) -> None:
    scene = bpy.context.scene
    recording = bool(scene.mocapd_recording)
    if recording and state.record_t0_ns is None:
        state.record_t0_ns = int(msg["t_solve_ns"])
    frame_no = 0
    if recording and state.record_t0_ns is not None:
        fps = scene.render.fps / scene.render.fps_base
        frame_no = scene.frame_start + round((int(msg["t_solve_ns"]) - state.record_t0_ns) * fps / 1e9)
    for subject in msg["subjects"]:
        skeleton = skeletons.get(subject["skeleton"])
        if skeleton is None:  # a frame before the hello that lists its skeleton: skip the subject
            continue
        ob = rig.ensure_armature(subject["id"], subject["skeleton"], skeleton)
        rig.pose(ob, subject, skeleton["bones"])
        if recording:
            frames, rows = state.take.setdefault(ob.name, ([], []))
            frames.append(frame_no)
            rows.append(rig.sample(ob))
    if recording:
        state.recorded_frames += 1
        scene.frame_end = max(frame_no, scene.frame_start)  # the take so far
    state.applied_frame = int(msg["frame"])
    state.applied += 1
    state.lag_frames = state.stream.newest_frame - state.applied_frame


class MOCAPD_OT_connect(bpy.types.Operator):  # type: ignore[misc]  # noqa: N801 (Blender's CATEGORY_OT_name)
    """Connect to the mocapd stream and drive the armatures"""

    bl_idname = "mocapd.connect"
    bl_label = "Connect"

    def execute(self, context: Any) -> set[str]:
        _drop_link()
        stream = StreamLink(context.scene.mocapd_url)
        try:
            stream.start()
        except (OSError, ValueError) as exc:
            self.report({"ERROR"}, f"mocapd: cannot connect to {stream.url}: {exc}")
            return {"CANCELLED"}
        _Current.link = Link(stream)
        if not bpy.app.timers.is_registered(tick):
            bpy.app.timers.register(tick, first_interval=TIMER_S)
        return {"FINISHED"}


class MOCAPD_OT_disconnect(bpy.types.Operator):  # type: ignore[misc]  # noqa: N801 (Blender's CATEGORY_OT_name)
    """Stop following the stream (the armatures keep their last pose; a take being recorded is keyed)"""

    bl_idname = "mocapd.disconnect"
    bl_label = "Disconnect"

    def execute(self, context: Any) -> set[str]:
        if context.scene.mocapd_recording and _Current.link is not None:
            write_takes(_Current.link)
        _drop_link()
        context.scene.mocapd_recording = False
        return {"FINISHED"}


class MOCAPD_OT_record(bpy.types.Operator):  # type: ignore[misc]  # noqa: N801 (Blender's CATEGORY_OT_name)
    """Start or stop recording the streamed poses as keyframes"""

    bl_idname = "mocapd.record"
    bl_label = "Record"

    start: bpy.props.BoolProperty(default=True)  # type: ignore[valid-type]

    def execute(self, context: Any) -> set[str]:
        scene = context.scene
        state = _Current.link
        if self.start:
            if state is not None:
                state.record_t0_ns, state.recorded_frames, state.take = None, 0, {}
        elif scene.mocapd_recording and state is not None:
            write_takes(state)
        scene.mocapd_recording = bool(self.start)
        return {"FINISHED"}


def write_takes(state: Link) -> None:
    """Key the buffered take of every armature (the subjects' keyframes are written when recording stops)."""
    for name, (frames, rows) in state.take.items():
        ob = bpy.data.objects.get(name)
        if ob is not None:
            rig.write_take(ob, frames, rows)
    state.take = {}


class MOCAPD_PT_panel(bpy.types.Panel):  # type: ignore[misc]  # noqa: N801 (Blender's CATEGORY_PT_name)
    bl_label = "mocapd live link"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "mocapd"

    def draw(self, context: Any) -> None:
        layout, scene = self.layout, context.scene
        layout.prop(scene, "mocapd_url", text="Stream")
        state = _Current.link
        if state is None:
            layout.operator("mocapd.connect")
            return
        layout.operator("mocapd.disconnect")
        if scene.mocapd_recording:
            layout.operator("mocapd.record", text=f"Stop ({state.recorded_frames} frames)").start = False
        else:
            layout.operator("mocapd.record", text="Record").start = True
        s = state.stream
        layout.label(text=f"frame {state.applied_frame}  received {s.received}")
        if s.error:
            layout.label(text=s.error, icon="ERROR")


CLASSES = (MOCAPD_OT_connect, MOCAPD_OT_disconnect, MOCAPD_OT_record, MOCAPD_PT_panel)


def register() -> None:
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Scene.mocapd_url = bpy.props.StringProperty(
        name="mocapd stream", default="ws://127.0.0.1:8766/", description="The daemon's WebSocket stream URL"
    )
    bpy.types.Scene.mocapd_recording = bpy.props.BoolProperty(name="Recording", default=False)


def unregister() -> None:
    _drop_link()
    if bpy.app.timers.is_registered(tick):
        bpy.app.timers.unregister(tick)
    del bpy.types.Scene.mocapd_recording
    del bpy.types.Scene.mocapd_url
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
