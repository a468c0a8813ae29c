"""The live web viewer in real headless Chromium against the real daemon on the synthetic rig: the page served by
the daemon connects to the WebSocket stream, receives frames and status, draws every subject's skeleton where
its joints project (checked on a screenshot), draws none while disconnected, and reconnects after the daemon
restarts on the same port."""

from __future__ import annotations

import asyncio
import contextlib
import socket
from collections.abc import AsyncIterator
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray

from mocapd.io.ws_server import WebSocketStreamServer
from mocapd.service.assembly import assembled
from mocapd.service.config import Config, load_config
from mocapd.service.demo.synthetic import synthetic_config
from tests.cdp import Page, chromium_page

PANEL_PX = 300  # the status panel on the right of the canvas


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextlib.asynccontextmanager
async def daemon(cfg: Config) -> AsyncIterator[str]:
    """The synthetic-rig daemon with its WebSocket stream, running; yields the viewer URL."""
    with assembled(synthetic_config(cfg)) as demo:
        streams = [s for s in demo.daemon.sinks if isinstance(s, WebSocketStreamServer)]
        task = asyncio.create_task(demo.daemon.run())
        try:
            await asyncio.wait_for(demo.daemon.ready.wait(), 120)
            yield streams[0].viewer_url
        finally:
            demo.daemon.request_stop()
            assert await asyncio.wait_for(task, 10) == 0


def hex_bgr(colour: str) -> NDArray[np.int32]:
    return np.array([int(colour[5:7], 16), int(colour[3:5], 16), int(colour[1:3], 16)], dtype=np.int32)


def near(img: NDArray[np.uint8], bgr: NDArray[np.int32], tol: int = 40) -> NDArray[np.bool_]:
    result: NDArray[np.bool_] = np.abs(img.astype(np.int32) - bgr).max(axis=-1) <= tol
    return result


async def check_skeletons_drawn(page: Page) -> list[dict[str, Any]]:
    """Pause the view on a frame with both people; each one's colour must be on the screenshot at its joints."""
    # Pause on a frame with both people (atomic in the page: under load the tracker may briefly lose someone).
    pause_on_two = (
        "(() => { const s = mocapdViewer.state; const ok = s.shown && s.shown.subjects.length == 2;"
        " if (ok) mocapdViewer.pause(true); return ok; })()"
    )
    await page.wait_for(pause_on_two, 30, "a frame with both people")
    await asyncio.sleep(0.3)  # the paused frame is drawn
    drawn = await page.evaluate("mocapdViewer.drawn()")
    img = await page.screenshot()
    h, w = img.shape[:2]
    assert drawn, "no subject on screen"
    for subject in drawn:
        mask = near(img, hex_bgr(subject["colour"]))
        points = [p for p in subject["points"] if p and 3 <= p[0] < w - PANEL_PX - 3 and 3 <= p[1] < h - 3]
        assert len(points) >= 15, subject
        hits = [bool(mask[round(y) - 3 : round(y) + 4, round(x) - 3 : round(x) + 4].any()) for x, y in points]
        assert sum(hits) >= 0.8 * len(points), (subject["id"], hits)
        assert mask[:, : w - PANEL_PX].sum() > 300  # lines, not a stray pixel
    await page.evaluate("mocapdViewer.pause(false)")
    return list(drawn)


@pytest.mark.asyncio
async def test_viewer_draws_the_daemons_subjects_and_reconnects_after_a_restart() -> None:
    cfg = load_config()
    port = free_port()
    cfg = cfg.model_copy(
        update={
            "daemon": cfg.daemon.model_copy(update={"http_port": 0}),
            "websocket": cfg.websocket.model_copy(update={"port": port, "status_hz": 5.0}),
        }
    )
    first = contextlib.AsyncExitStack()
    try:
        url = await first.enter_async_context(daemon(cfg))
        async with chromium_page(url) as page:
            await page.wait_for("window.mocapdViewer && mocapdViewer.frames > 30", 60, "frames in the page")
            await page.wait_for("mocapdViewer.state.shown.subjects.length == 2", 30, "both people in the page")
            await page.wait_for("mocapdViewer.state.statusMessages > 0", 10, "a status message")
            drawn = await check_skeletons_drawn(page)
            assert len({d["colour"] for d in drawn}) == 2
            panel = await page.evaluate("document.getElementById('panel').innerText")
            assert "cam0" in panel and "end_to_end" in panel and "streaming" in panel, panel
            palette = [hex_bgr(c) for c in await page.evaluate("mocapdViewer.palette")]

            # Orbit (drag) and zoom (wheel) with real input events; the skeletons follow the new view.
            yaw, dist = await page.evaluate("[mocapdViewer.cam.yaw, mocapdViewer.cam.dist]")
            for kind, x in (("mousePressed", 300), ("mouseMoved", 360), ("mouseMoved", 420), ("mouseReleased", 420)):
                await page.call("Input.dispatchMouseEvent", type=kind, x=x, y=300, button="left",
                                buttons=0 if kind == "mouseReleased" else 1, clickCount=1)  # fmt: skip
            await page.call("Input.dispatchMouseEvent", type="mouseWheel", x=400, y=300, deltaX=0, deltaY=-300)
            yaw2, dist2 = await page.evaluate("[mocapdViewer.cam.yaw, mocapdViewer.cam.dist]")
            assert yaw2 == pytest.approx(yaw - 1.2) and dist2 < dist
            await check_skeletons_drawn(page)

            # The daemon stops: the page says so and draws no skeleton.
            await first.aclose()
            await page.wait_for("!mocapdViewer.connected", 10, "the page to notice the daemon stopped")
            await asyncio.sleep(0.3)
            img = (await page.screenshot())[:, :-PANEL_PX]
            assert all(near(img, c).sum() == 0 for c in palette)
            assert "reconnecting" in await page.evaluate("document.getElementById('conn').innerText")

            # A new daemon on the same port: the page reconnects by itself and draws again.
            frames = await page.evaluate("mocapdViewer.frames")
            async with daemon(cfg):
                await page.wait_for(f"mocapdViewer.connects == 2 && mocapdViewer.frames > {frames + 30}", 60,
                                    "the page to reconnect and receive frames")  # fmt: skip
                await page.wait_for("mocapdViewer.state.shown.subjects.length == 2", 30, "both people again")
                await check_skeletons_drawn(page)
    finally:
        await first.aclose()
