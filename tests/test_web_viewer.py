"""The live web viewer in real headless Chromium against the real daemon on the synthetic rig: the page served by
the daemon connects to the WebSocket stream, receives frames and status, draws every subject's skeleton where
its joints project (checked on a screenshot), frames the people (their projected bounds fill a good part of the
canvas, inside it) and follows them until the user moves the view, draws none while disconnected, and reconnects
after the daemon restarts on the same port."""

from __future__ import annotations

import asyncio
import contextlib
import re
import socket
from collections.abc import AsyncIterator
from typing import Any

import cv2
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


def project_view(view: dict[str, Any], joints: NDArray[np.float64]) -> list[tuple[float, float] | None]:
    """Canvas pixels of world points through the viewer's camera, computed here from its parameters, not by the
    page: an orbit camera at ``dist`` from ``target``, at azimuth ``yaw`` (from +Z towards +X) and elevation
    ``pitch``, looking at the target with +Y up; a pinhole of focal length 0.9 · min(width, height) centred on the
    canvas. OpenCV projects (camera x right, y down, z forward)."""
    cam = view["cam"]
    yaw, pitch, dist = float(cam["yaw"]), float(cam["pitch"]), float(cam["dist"])
    target = np.array(cam["target"], dtype=np.float64)
    eye = target + dist * np.array([np.cos(pitch) * np.sin(yaw), np.sin(pitch), np.cos(pitch) * np.cos(yaw)])
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    R = np.stack([right, -up, forward])
    t = -R @ eye
    w, h = float(view["width"]), float(view["height"])
    f = 0.9 * min(w, h)
    K = np.array([[f, 0.0, w / 2], [0.0, f, h / 2], [0.0, 0.0, 1.0]])
    uv, _ = cv2.projectPoints(joints.reshape(-1, 1, 3), cv2.Rodrigues(R)[0], t, K, None)
    depth = (joints - eye) @ forward
    left, top = view["left"], view["top"]
    return [(u + left, v + top) if z > 0.05 else None for (u, v), z in zip(uv.reshape(-1, 2), depth, strict=True)]


VIEW = """(() => { const c = document.getElementById('view'), r = c.getBoundingClientRect();
  return {cam: mocapdViewer.cam, width: c.clientWidth, height: c.clientHeight, left: r.left, top: r.top,
          subjects: mocapdViewer.state.shown.subjects.map((s) => ({id: s.id, colour: mocapdViewer.colourOf(s.id),
                                                                  joints: s.joints}))}; })()"""


async def check_skeletons_drawn(page: Page) -> list[dict[str, Any]]:
    """Pause the view on a frame with both people; each one's colour must be on the screenshot where its joints
    project (projected here from the view's camera and the frame's joints, not by the page)."""
    # Pause on a frame with both people (atomic in the page: under load the tracker may briefly lose someone).
    pause_on_two = (
        "(() => { const s = mocapdViewer.state; const ok = s.shown && s.shown.subjects.length == 2;"
        " if (ok) mocapdViewer.pause(true); return ok; })()"
    )
    await page.wait_for(pause_on_two, 30, "a frame with both people")
    await asyncio.sleep(0.3)  # the paused frame is drawn
    view = await page.evaluate(VIEW)
    drawn = await page.evaluate("mocapdViewer.drawn()")
    img = await page.screenshot()
    h, w = img.shape[:2]
    assert view["subjects"], "no subject on screen"
    assert [d["id"] for d in drawn] == [s["id"] for s in view["subjects"]]
    for subject, page_drawn in zip(view["subjects"], drawn, strict=True):
        joints = np.array(subject["joints"], dtype=np.float64).reshape(-1, 3)
        assert joints.shape == (21, 3), subject
        projected = project_view(view, joints)
        # The page's own projection agrees with this one (a disagreement would show which side is wrong).
        for p, q in zip(projected, page_drawn["points"], strict=True):
            assert (p is None) == (q is None) and (p is None or np.hypot(p[0] - q[0], p[1] - q[1]) < 0.5), (p, q)
        mask = near(img, hex_bgr(subject["colour"]))
        points = [p for p in projected if p and 3 <= p[0] < w - PANEL_PX - 3 and 3 <= p[1] < h - 3]
        assert len(points) >= 15, subject
        hits = [bool(mask[round(y) - 3 : round(y) + 4, round(x) - 3 : round(x) + 4].any()) for x, y in points]
        assert sum(hits) >= 0.8 * len(points), (subject["id"], hits)
        assert mask[:, : w - PANEL_PX].sum() > 300  # lines, not a stray pixel
    await page.evaluate("mocapdViewer.pause(false)")
    return list(view["subjects"])


FRAMED = 0.45  # the people's projected bounds span at least this much of the canvas's width or height
SETTLED = (
    "(() => { const v = mocapdViewer, s = v.state.shown; return v.view.fitted && s && s.subjects.length == 2"
    " && Math.abs(v.cam.dist - v.fitOf(s.subjects).dist) < 0.05; })()"
)


async def check_people_framed(page: Page) -> dict[str, Any]:
    """Pause on a frame with both people once the view has settled on them: every joint projects (through the
    view's camera, computed here) inside the canvas, the joints' bounds span at least FRAMED of its width or
    height, and the view aims at their middle. Returns the view and the joints' middle."""
    await page.wait_for(SETTLED, 20, "the view to settle on the people")
    pause_on_two = (
        "(() => { const s = mocapdViewer.state; const ok = s.shown && s.shown.subjects.length == 2;"
        " if (ok) mocapdViewer.pause(true); return ok; })()"
    )
    await page.wait_for(pause_on_two, 30, "a frame with both people")
    view = await page.evaluate(VIEW)
    joints = np.concatenate([np.array(s["joints"], dtype=np.float64).reshape(-1, 3) for s in view["subjects"]])
    projected = project_view(view, joints)
    assert all(p is not None for p in projected)
    uv = np.array(projected, dtype=np.float64) - [view["left"], view["top"]]
    w, h = float(view["width"]), float(view["height"])
    assert uv.min() >= 0 and np.all(uv.max(axis=0) <= [w, h]), (uv.min(axis=0), uv.max(axis=0), w, h)
    span = (uv.max(axis=0) - uv.min(axis=0)) / [w, h]
    assert span.max() >= FRAMED, span
    middle = (joints.min(axis=0) + joints.max(axis=0)) / 2
    # Aimed at the people's middle (up to the glide of the last few frames).
    assert np.linalg.norm(np.array(view["cam"]["target"]) - middle) < 0.25, (view["cam"], middle)
    await page.evaluate("mocapdViewer.pause(false)")
    return {"cam": view["cam"], "middle": middle, "span": span}


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
            # The view frames the people from the first frame and follows them (not the fixed default view).
            assert await page.evaluate("mocapdViewer.view.auto")
            framed = await check_people_framed(page)
            await asyncio.sleep(2.0)
            later = await check_people_framed(page)
            assert framed["cam"]["target"] != later["cam"]["target"]
            panel = await page.evaluate("document.getElementById('panel').innerText")
            assert "cam0" in panel and "end_to_end" in panel and "streaming" in panel, panel
            palette = [hex_bgr(c) for c in await page.evaluate("mocapdViewer.palette")]
            # The heading reset a suit wearer asks for (IMUs without cameras drift in heading), from the page: a
            # real click on its button, the daemon's answer said under it.
            box = await page.evaluate(
                "(() => { const r = document.getElementById('headingButton')"
                ".getBoundingClientRect(); return [r.left + r.width / 2, r.top + r.height / 2]; })()"
            )
            for kind, buttons in (("mousePressed", 1), ("mouseReleased", 0)):
                await page.call("Input.dispatchMouseEvent", type=kind, x=box[0], y=box[1], button="left",
                                buttons=buttons, clickCount=1)  # fmt: skip
            await page.wait_for("mocapdViewer.state.headingResets == 1", 10, "the heading reset's answer")
            said = await page.evaluate("document.getElementById('headingMsg').innerText")
            assert re.fullmatch(r"heading reset · suit0: 13 sensors turned, up to \d+\.\d°", said), said

            # Orbit (drag) and zoom (wheel) with real input events; the skeletons follow the new view.
            yaw, dist = await page.evaluate("[mocapdViewer.cam.yaw, mocapdViewer.cam.dist]")
            for kind, x in (("mousePressed", 300), ("mouseMoved", 360), ("mouseMoved", 420), ("mouseReleased", 420)):
                await page.call("Input.dispatchMouseEvent", type=kind, x=x, y=300, button="left",
                                buttons=0 if kind == "mouseReleased" else 1, clickCount=1)  # fmt: skip
            await page.call("Input.dispatchMouseEvent", type="mouseWheel", x=400, y=300, deltaX=0, deltaY=-300)
            yaw2, dist2 = await page.evaluate("[mocapdViewer.cam.yaw, mocapdViewer.cam.dist]")
            assert yaw2 == pytest.approx(yaw - 1.2) and dist2 < dist
            await check_skeletons_drawn(page)
            # Moved by hand, the view stays where the user put it while the people move on.
            cam = await page.evaluate("JSON.stringify(mocapdViewer.cam)")
            await asyncio.sleep(1.0)
            assert not await page.evaluate("mocapdViewer.view.auto")
            assert await page.evaluate("JSON.stringify(mocapdViewer.cam)") == cam
            # Double-click: the default angle, following the people again.
            for count in (1, 2):
                for kind, buttons in (("mousePressed", 1), ("mouseReleased", 0)):
                    await page.call("Input.dispatchMouseEvent", type=kind, x=400, y=300, button="left",
                                    buttons=buttons, clickCount=count)  # fmt: skip
            assert await page.evaluate("mocapdViewer.view.auto && mocapdViewer.cam.yaw == 0.6")
            await check_people_framed(page)

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
