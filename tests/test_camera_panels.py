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
from mocapd.core.skeleton import PARENTS
from mocapd.io.ws_server import WebSocketStreamServer
from mocapd.service.assembly import assembled
from mocapd.service.config import Config, load_config
from mocapd.service.demo.synthetic import synthetic_config
from mocapd.sim.camera_frames import BACKGROUND, BODY
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


def _css(panel: dict[str, Any], uv: np.ndarray) -> np.ndarray:
    """Image pixels (N, 2) -> the screenshot's pixels (N, 2) in ``panel``."""
    return np.asarray(np.array([panel["left"], panel["top"]]) + uv * np.array([panel["scale_x"], panel["scale_y"]]))


def _segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance (N,) of points ``p`` (N, 2) to the segment ``a``-``b`` (2,)."""
    ab = b - a
    t = np.clip(((p - a) @ ab) / max(float(ab @ ab), 1e-12), 0.0, 1.0)
    return np.asarray(np.linalg.norm(p - (a + t[:, None] * ab), axis=1))


def _covered(xy: np.ndarray, later: list[np.ndarray], dots: np.ndarray) -> np.ndarray:
    """Which joints (N, 2) may be hidden (bool, N): within 4 px of a later subject's bones or joints (lines and
    dots 2.5 px), or with two or more detection dots (2 px and a 1 px outline) within 5 px (its own detection's
    dot alone leaves its bones visible)."""
    covered = (np.linalg.norm(xy[:, None] - dots[None], axis=2) < 5.0).sum(axis=1) >= 2
    for other in later:
        for child, parent in enumerate(PARENTS):
            if parent >= 0 and np.isfinite(other[[child, parent]]).all():
                covered |= _segment_distance(xy, other[parent], other[child]) < 4.0
        covered |= (np.linalg.norm(xy[:, None] - other[None], axis=2) < 4.0).any(axis=1)
    return np.asarray(covered)


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
                checked = well_seen = 0
                for p in panels:
                    cam = cameras[p["camera"]]
                    assert p["name"] == cam.name and p["image"]
                    view = img[round(p["top"]) : round(p["top"] + p["height"]),
                               round(p["left"]) : round(p["left"] + p["width"])]  # fmt: skip
                    # The frame's image under the overlays: its background (the canvas alone is black), and the
                    # people's body colour where the overlay leaves it visible.
                    assert near(view, np.array(BACKGROUND[::-1]), 12).mean() > 0.3, "the frame's image is drawn"
                    assert near(view, np.array(BODY[::-1]), 20).sum() > 30, "the people in the frame are drawn"
                    dots = [(p["left"] + d[k] * p["scale_x"], p["top"] + d[k + 1] * p["scale_y"])
                            for d in p["detections"] for k in range(0, len(d), 3)
                            if d[k] is not None and d[k + 2] >= 0.3]  # fmt: skip
                    # Python's projection through the calibration of the daemon's joints for the drawn frame
                    projected = [cam.project(ref[p["frame"]][s["id"]]) for s in p["subjects"]]
                    drawn = [_css(p, uv) for uv in projected]
                    for i, s in enumerate(p["subjects"]):
                        sent = np.array([np.nan if v is None else v for v in s["joints"]]).reshape(21, 2)
                        np.testing.assert_allclose(sent, projected[i], atol=0.02)
                        xy = drawn[i]
                        inside = (xy[:, 0] > p["left"] + 2) & (xy[:, 0] < p["left"] + p["width"] - 2)
                        inside &= (xy[:, 1] > p["top"] + 2) & (xy[:, 1] < p["top"] + p["height"] - 2)
                        # Where the people overlap in this camera, a subject drawn later or the other person's
                        # detection dots may bury a joint; those joints are no evidence either way.
                        visible = inside & ~_covered(xy, drawn[i + 1 :], np.array(dots).reshape(-1, 2))
                        mask = near(img, hex_bgr(s["colour"]))
                        # The detection dot on a joint (2 px + a 1 px outline) covers the subject's own dot
                        # (2.5 px); its bones leave the dot: look 4 px around.
                        hits = [bool(mask[round(b) - 4 : round(b) + 5, round(a) - 4 : round(a) + 5].any())
                                for a, b in xy[visible]]  # fmt: skip
                        assert sum(hits) >= 0.85 * len(hits), (p["name"], s["id"], hits)
                        checked += 1
                        # A subject may be mostly covered or out of one camera's frame at the drawn instant (5
                        # visible joints, all hit, in one run): the count of evidence is checked over all panels.
                        well_seen += len(hits) >= 6
                    white = near(img, np.array([255, 255, 255]), 30)
                    assert dots and np.mean([white[round(b) - 1 : round(b) + 2, round(a) - 1 : round(a) + 2].any()
                                             for a, b in dots]) >= 0.8  # fmt: skip
                    caption = p["caption"]
                    rep = float(caption.split("reprojection ")[1].split(" px")[0])
                    rate = float(caption.split("detections ")[1].split(" Hz")[0])
                    # A few pixels of 1920 when the solve is settled; tens for a person close to the camera or
                    # while a loaded machine misses ticks. The synthetic cameras detect at 30 Hz.
                    assert 0.0 <= rep < 0.1 * cam.width and 5.0 < rate < 60.0, caption
                assert checked == 8 and well_seen >= 6, well_seen

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
