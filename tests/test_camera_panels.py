"""Camera panels of the live viewer in real headless Chromium against the real synthetic-rig daemon: each camera's
frame with the detections and every solved subject drawn where the camera's calibration projects them (the
projection computed here in Python from the calibration and the daemon's own joint positions for the drawn
frame, checked on the screenshot's pixels), per-camera reprojection error and detection rate, and camera
messages sent only while the page asks."""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import AsyncIterator
from typing import Any

import numpy as np
import pytest
import websockets

from mocapd.core.camera import Camera
from mocapd.io.ws_server import WebSocketStreamServer
from mocapd.service.assembly import assembled
from mocapd.service.config import Config, load_config
from mocapd.service.demo.synthetic import synthetic_config
from mocapd.sim.camera_frames import BODY
from tests.cdp import chromium_page
from tests.test_web_viewer import free_port, hex_bgr, near


@contextlib.asynccontextmanager
async def camera_daemon(cfg: Config) -> AsyncIterator[tuple[str, list[Camera], Any]]:
    """The synthetic-rig daemon with its stream; yields the viewer URL, the rig's cameras and the server."""
    with assembled(synthetic_config(cfg)) as demo:
        streams = [s for s in demo.daemon.sinks if isinstance(s, WebSocketStreamServer)]
        task = asyncio.create_task(demo.daemon.run())
        try:
            await asyncio.wait_for(demo.daemon.ready.wait(), 120)
            yield streams[0].viewer_url, demo.daemon.rig.cameras, streams[0]
        finally:
            demo.daemon.request_stop()
            assert await asyncio.wait_for(task, 10) == 0


async def _reference(url: str, frames: dict[int, dict[str, Any]]) -> None:
    """The daemon's global joint positions per frame counter (a second, independent client)."""
    async with websockets.connect(url) as ws:
        await ws.send(json.dumps({"type": "subscribe", "encoding": "json", "globals": True, "status": False}))
        async for msg in ws:
            if isinstance(msg, str):
                m = json.loads(msg)
                if m["type"] == "frame":
                    frames[m["frame"]] = {s["id"]: np.reshape(s["joints"], (21, 3)) for s in m["subjects"]}


ALL_DRAWN = (
    "(() => { const p = mocapdViewer.cameraPanels(); const ok = p.length == 4 && p.every((c) => c.image"
    " && c.subjects.length == 2 && c.detections.length >= 1); if (ok) mocapdViewer.pause(true); return ok; })()"
)


@pytest.mark.asyncio
async def test_camera_panels_draw_the_overlays_where_the_calibration_projects() -> None:
    cfg = load_config()
    cfg = cfg.model_copy(update={"daemon": cfg.daemon.model_copy(update={"http_port": 0}),
                                 "websocket": cfg.websocket.model_copy(update={"port": free_port()})})  # fmt: skip
    async with camera_daemon(cfg) as (url, cameras, server):
        ref: dict[int, dict[str, Any]] = {}
        reader = asyncio.create_task(_reference(url.replace("http", "ws"), ref))
        try:
            async with chromium_page(url + "?cameras=1") as page:
                await page.wait_for("window.mocapdViewer && mocapdViewer.frames > 10", 60, "frames in the page")
                await page.wait_for(ALL_DRAWN, 90, "four camera panels with image, detections and both people")
                await asyncio.sleep(0.5)  # the paused panels are drawn
                panels = await page.evaluate("mocapdViewer.cameraPanels()")
                img = await page.screenshot()
                checked = 0
                for p in panels:
                    cam = cameras[p["camera"]]
                    assert p["name"] == cam.name and p["image"]
                    body = near(
                        img[
                            round(p["top"]) : round(p["top"] + p["height"]),
                            round(p["left"]) : round(p["left"] + p["width"]),
                        ],
                        np.array(BODY[::-1]),
                        12,
                    )
                    assert body.sum() > 30, "the frame's image is drawn"  # fmt: skip
                    for s in p["subjects"]:
                        joints = ref[p["frame"]][s["id"]]  # the daemon's joints for the drawn frame
                        uv = cam.project(joints)  # Python's projection through the calibration
                        sent = np.array([np.nan if v is None else v for v in s["joints"]]).reshape(21, 2)
                        np.testing.assert_allclose(sent, uv, atol=0.02)
                        x = p["left"] + uv[:, 0] * p["scale_x"]
                        y = p["top"] + uv[:, 1] * p["scale_y"]
                        inside = (x > p["left"] + 2) & (x < p["left"] + p["width"] - 2)
                        inside &= (y > p["top"] + 2) & (y < p["top"] + p["height"] - 2)
                        mask = near(img, hex_bgr(s["colour"]))
                        hits = [bool(mask[round(b) - 3 : round(b) + 4, round(a) - 3 : round(a) + 4].any())
                                for a, b in zip(x[inside], y[inside], strict=True)]  # fmt: skip
                        assert len(hits) >= 10 and sum(hits) >= 0.85 * len(hits), (p["name"], s["id"], hits)
                        checked += 1
                    white = near(img, np.array([255, 255, 255]), 30)
                    dots = [(p["left"] + d[k] * p["scale_x"], p["top"] + d[k + 1] * p["scale_y"])
                            for d in p["detections"] for k in range(0, len(d), 3)
                            if d[k] is not None and d[k + 2] >= 0.3]  # fmt: skip
                    assert dots and np.mean([white[round(b) - 1 : round(b) + 2, round(a) - 1 : round(a) + 2].any()
                                             for a, b in dots]) >= 0.8  # fmt: skip
                    caption = p["caption"]
                    rep = float(caption.split("reprojection ")[1].split(" px")[0])
                    rate = float(caption.split("detections ")[1].split(" Hz")[0])
                    # A few pixels of 1920 when the solve is settled; tens for a person close to the camera or
                    # while a loaded machine misses ticks. The synthetic cameras detect at 30 Hz.
                    assert 0.0 <= rep < 0.1 * cam.width and 5.0 < rate < 60.0, caption
                assert checked == 8

                # Off: the page stops asking and the server stops sending.
                await page.evaluate("mocapdViewer.pause(false); mocapdViewer.setCameras(false)")
                await asyncio.sleep(1.0)
                sent = server.camera_messages
                await asyncio.sleep(1.5)
                assert server.camera_messages == sent
                assert server._camera_task is None or server._camera_task.done()
        finally:
            reader.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await reader
