"""The Blender live-link add-on, in real Blender (``bpy``) against the running synthetic-rig daemon: installed as
a user installs it, its armatures follow the stream within one frame (every bone head within 1 mm of the
daemon's own global joint positions for the frame applied), and recording keys one keyframe per streamed frame.
"""

from __future__ import annotations

import asyncio
import json
import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import websockets

from mocapd.core.skeleton import BONE_NAMES
from mocapd.io.lifecycle import guarded_command
from mocapd.service.config import load_config
from tests.blender_support import ROOT, bpy_python
from tests.test_web_viewer import daemon, free_port


async def _reference(url: str, frames: dict[int, dict[str, Any]], stop: asyncio.Event) -> None:
    """The daemon's own global joint positions per frame, read by a real WebSocket client."""
    async with websockets.connect(url) as ws:
        await ws.send(json.dumps({"type": "subscribe", "encoding": "json", "convention": "native", "globals": True}))
        while not stop.is_set():
            msg = await ws.recv()
            if isinstance(msg, str):
                m = json.loads(msg)
                if m["type"] == "frame":
                    frames[m["frame"]] = {s["id"]: np.reshape(s["joints"], (21, 3)) for s in m["subjects"]}


@pytest.mark.asyncio
async def test_armatures_follow_the_stream_and_record(tmp_path: Path) -> None:
    cfg = load_config()
    cfg = cfg.model_copy(update={"daemon": cfg.daemon.model_copy(update={"http_port": 0}),
                                 "websocket": cfg.websocket.model_copy(update={"port": free_port()})})  # fmt: skip
    env = dict(os.environ, BLENDER_USER_RESOURCES=str(tmp_path / "blender-user"))  # not the user's own Blender
    async with daemon(cfg):
        url = f"ws://127.0.0.1:{cfg.websocket.port}/"
        ref: dict[int, dict[str, Any]] = {}
        stop = asyncio.Event()
        reader = asyncio.create_task(_reference(url, ref, stop))
        for _ in range(600):  # both people tracked before Blender connects
            if ref and len(ref[max(ref)]) == 2:
                break
            await asyncio.sleep(0.1)
        proc = await asyncio.create_subprocess_exec(  # guarded: Blender ends with the test, however it ends
            *guarded_command([str(bpy_python()), str(ROOT / "tests" / "blender_live.py"), url, "4", "3"]),
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE, env=env,
        )  # fmt: skip
        out, err = await asyncio.wait_for(proc.communicate(), 400)
        stop.set()
        await asyncio.wait_for(reader, 10)
    lines = [ln for ln in out.decode().splitlines() if ln.startswith("MOCAPD-REPORT ")]
    assert proc.returncode == 0 and lines, (out.decode()[-3000:], err.decode()[-3000:])
    report = json.loads(lines[-1].removeprefix("MOCAPD-REPORT "))
    assert report["error"] is None

    samples = report["samples"]
    assert sum(len(s["heads"]) == 2 for s in samples) >= 40, (len(samples), report["follow_s"], report["ticks"])
    assert all(s["lag"] <= 1 for s in samples), [s["lag"] for s in samples]  # within one frame of the newest
    frames = [s["frame"] for s in samples]
    assert frames == sorted(set(frames))  # always forward, never a stale frame
    checked = 0
    for s in samples:
        for who, heads in s["heads"].items():
            if who not in ref.get(s["frame"], {}):
                continue  # this armature shows an earlier frame of a subject missing from this one
            assert list(heads) == list(BONE_NAMES)
            got = np.array([heads[b] for b in BONE_NAMES])
            err_m = np.linalg.norm(got - ref[s["frame"]][who], axis=1)
            assert err_m.max() < 1e-3, f"frame {s['frame']} {who}: {1e3 * err_m.max():.2f} mm"
            checked += 1
    assert checked >= 40, checked

    actions = report["actions"]
    # Recording: every armature that was in the take has one keyframe per streamed frame it was in (a loaded
    # machine's tracker may drop or rename someone for a moment), on every channel, and the scene ends with it.
    actions = {k: a for k, a in report["actions"].items() if a["keyframes"]}
    recorded = report["recorded_frames"]
    assert recorded >= 5 and sum(a["keyframes"] >= 0.5 * recorded for a in actions.values()) >= 2, actions
    for a in actions.values():
        assert a["keyframes"] <= recorded, a
        assert a["curves"] == 21 * 4 + 3  # a quaternion per bone + the root's location
        assert a["bones"] == list(BONE_NAMES)
    assert report["frame_end"] == max(a["last"] for a in actions.values())
