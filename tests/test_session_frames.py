"""Downscaled camera frames in sessions: the real synthetic daemon records them (``frames`` stream, T_FRAME
records), and ``mocapd replay`` of that session sends the camera panels to a real WebSocket client: the recorded
JPEGs, the recorded detections and the replayed subjects projected through the recorded calibration."""

from __future__ import annotations

import asyncio
import base64
import json
import os
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import websockets

from mocapd.io.session import open_session
from mocapd.protocols.session_format import FrameRecord, decode_frame, encode_frame
from mocapd.service.assembly import RunOptions, assembled
from mocapd.service.config import load_config
from mocapd.service.demo.synthetic import synthetic_config
from mocapd.service.outputs.recorder import FrameRecordOptions, attach_recorder
from mocapd.service.session.solve import session_rig
from tests.test_daemon import Recorder, wait_for
from tests.test_web_viewer import free_port

ROOT = Path(__file__).resolve().parents[1]


def test_frame_record_round_trip() -> None:
    r = FrameRecord(2, 123_456_789, 320, 180, b"\xff\xd8jpeg\xff\xd9")
    assert decode_frame(encode_frame(r)) == r


async def _record(path: Path, seconds: float) -> None:
    cfg = load_config()
    cfg = cfg.model_copy(update={"daemon": cfg.daemon.model_copy(update={"http_port": 0}),
                                 "websocket": cfg.websocket.model_copy(update={"enabled": False})})  # fmt: skip
    live = Recorder()
    with assembled(synthetic_config(cfg), RunOptions(sinks=[live])) as demo:
        rec = attach_recorder(cfg, demo.daemon, path, frames=FrameRecordOptions(enabled=True, rate_hz=5.0))
        assert rec is not None
        task = asyncio.create_task(demo.daemon.run())
        await asyncio.wait_for(demo.daemon.ready.wait(), 120)
        await wait_for(lambda: bool(live.frames) and len(live.frames[-1].people) == 2, 60, "both people tracked")
        await asyncio.sleep(seconds)
        demo.daemon.request_stop()
        assert await asyncio.wait_for(task, 10) == 0
        assert rec.frames_recorded > 0


async def _camera_messages(url: str, proc: asyncio.subprocess.Process) -> list[dict[str, Any]]:
    for _ in range(200):  # the replay's server starts after the session is read
        try:
            ws = await websockets.connect(url)
            break
        except OSError:
            await asyncio.sleep(0.1)
    else:
        raise AssertionError("the replay's WebSocket server never came up")
    out = []
    async with ws:
        await ws.send(json.dumps({"type": "subscribe", "encoding": "json", "cameras": True, "camera_rate_hz": 10}))
        async for msg in ws:  # until the replay ends and closes the server
            m = json.loads(msg) if isinstance(msg, str) else {}
            if m.get("type") == "camera":
                out.append(m)
    return out


@pytest.mark.asyncio
async def test_recorded_frames_replay_into_camera_panels(tmp_path: Path) -> None:
    path = tmp_path / "session"
    await _record(path, 3.0)
    session = open_session(path)
    frames = session.frames()
    assert session.manifest["streams"] == ["imu", "keypoints", "poses", "events", "frames"]
    cams = {f.camera for f in frames}
    assert cams == {0, 1, 2, 3} and all(f.width == 320 and f.height == 180 for f in frames)
    first = cv2.imdecode(np.frombuffer(frames[0].jpeg, np.uint8), cv2.IMREAD_COLOR)
    assert first is not None and first.shape == (180, 320, 3)

    port = free_port()
    config = tmp_path / "replay.toml"
    config.write_text(f"[websocket]\nport = {port}\n")
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "mocapd", "replay", str(path), "--config", str(config),
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE, env=dict(os.environ, PYTHONPATH=str(ROOT)),
    )  # fmt: skip
    messages = await asyncio.wait_for(_camera_messages(f"ws://127.0.0.1:{port}/", proc), 120)
    _, err = await proc.communicate()
    assert proc.returncode == 0, err.decode()

    assert {m["camera"] for m in messages} == {0, 1, 2, 3}, len(messages)
    recorded = {(f.camera, f.capture_ns): f.jpeg for f in frames}
    rig = session_rig(session)
    poses = {p.frame: p for p in session.poses()}
    with_people = [m for m in messages if m["subjects"] and m["image"] is not None]
    assert len(with_people) >= 4, [(m["camera"], len(m["subjects"]), m["image"] is not None) for m in messages]
    for m in with_people:
        assert base64.b64decode(m["image"]) == recorded[(m["camera"], m["t_capture_ns"])]  # the recorded JPEG
        assert (m["image_width"], m["image_height"]) == (320, 180)
        pose = poses[m["frame"]]
        nearest = min(poses.values(), key=lambda p: abs(p.t_solve_ns - m["t_capture_ns"]))
        assert pose.frame == nearest.frame  # the pose solved nearest the frame's capture
        cam = rig.cameras[m["camera"]]
        for s in m["subjects"]:
            joints = next(p.joints for p in pose.people if p.identity == s["id"])
            got = np.array([np.nan if v is None else v for v in s["joints"]]).reshape(21, 2)
            np.testing.assert_allclose(got, cam.project(joints), atol=0.01)
    assert any(m["detections"] for m in with_people) and any(m["detection_hz"] > 10 for m in with_people)
