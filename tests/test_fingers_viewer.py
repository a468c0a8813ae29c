"""The live web viewer draws fingers (issue 44), in real headless Chromium against the real WebSocket server: a
subject closing its fists streams ``hands``; paused on a bent frame and zoomed onto the left hand, the subject's
colour is on the screenshot where every finger joint and fingertip projects (projected here from the view's camera,
tests/test_web_viewer.py), the page's own projection agrees, and its forward kinematics from local rotations (a
client without global joints) gives the joints the server sent. The screenshot is written as ``fingers.png`` under
the test's directory (``$MOCAPD_SCREENSHOTS``, when set, gets a copy)."""

from __future__ import annotations

import asyncio
import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from mocapd.core.hand_skeleton import HandSkeleton
from mocapd.core.skeleton import Skeleton
from mocapd.io.ws_server import ServerSettings, WebSocketStreamServer
from mocapd.pipeline.scheduler import PoseFrame
from mocapd.protocols.ws_stream import StreamDescription
from tests.cdp import chromium_page
from tests.finger_support import fist, person_with_fingers
from tests.test_web_viewer import hex_bgr, near, project_view

SKEL = Skeleton.from_height(1.75)
HANDS = HandSkeleton.from_body(SKEL)


def frame(n: int) -> PoseFrame:
    """The subject in its T-pose, both fists closing and opening every 2 s (closure in the frame's fraction)."""
    theta = SKEL.rest_pose()
    closure = 0.5 - 0.5 * np.cos(2 * np.pi * n / 120)
    person = person_with_fingers("suit:suit0", theta, SKEL, fist(float(closure), HANDS))
    return PoseFrame(n, 1_000_000_000 + n * 16_666_667, 0, [person], 0)


@pytest.mark.asyncio
async def test_the_viewer_draws_bent_fingers(tmp_path: Path) -> None:
    srv = WebSocketStreamServer(ServerSettings(port=0, status_hz=0), StreamDescription(60.0, {"default": SKEL}))
    await srv.start()

    async def stream() -> None:
        n = 0
        while True:
            srv.publish(frame(n))
            n += 1
            await asyncio.sleep(1 / 60)

    task = asyncio.create_task(stream())
    try:
        async with chromium_page(srv.viewer_url) as page:
            await page.wait_for("window.mocapdViewer && mocapdViewer.frames > 10", 60, "frames in the page")
            # Pause on a bent frame, then look at the left hand from the front, 0.7 m away.
            pause_bent = (
                "(() => { const s = mocapdViewer.state.shown; const h = s && s.subjects[0].hands;"
                " const ok = h && h.joints && mocapdViewer.state.hello.finger_bones &&"
                " Math.abs(h.rot[4 * 4]) < 0.7; if (ok) mocapdViewer.pause(true); return !!ok; })()"
            )  # the left index's middle joint's w below cos(45.6°): bent more than 91° of the fist's 100° (closure
            # over 0.91); at 0.75 (closure 0.83) a run that paused on the first such frame saw the tip only 19.6 px
            # below the knuckle, under the 20 px asked below
            await page.wait_for(pause_bent, 30, "a frame with bent fingers")
            await page.evaluate(
                "(() => { const v = mocapdViewer, s = v.state.shown.subjects[0], j = s.joints;"
                " v.view.auto = false; v.cam.yaw = 0.0; v.cam.pitch = 0.1; v.cam.dist = 0.7;"
                " v.cam.target = [j[27] + 0.08, j[28] - 0.02, j[29]]; v.pause(true); return true; })()"
            )
            await asyncio.sleep(0.4)  # drawn
            view = await page.evaluate(
                "(() => { const c = document.getElementById('view'), r = c.getBoundingClientRect();"
                " return {cam: mocapdViewer.cam, width: c.clientWidth, height: c.clientHeight, left: r.left,"
                " top: r.top, drawn: mocapdViewer.drawn(), subject: mocapdViewer.state.shown.subjects[0]}; })()"
            )
            fk = await page.evaluate(
                "(() => { const s = JSON.parse(JSON.stringify(mocapdViewer.state.shown.subjects[0]));"
                " delete s.joints; delete s.hands.joints; delete s.hands.tip_joints;"
                " return mocapdViewer.fingersOf(s).map((h) => h.joints.concat(h.tips)); })()"
            )
            img = await page.screenshot()
    finally:
        task.cancel()
        await srv.aclose()
    shot = tmp_path / "fingers.png"
    cv2.imwrite(str(shot), img)
    if os.environ.get("MOCAPD_SCREENSHOTS"):
        shutil.copy(shot, Path(os.environ["MOCAPD_SCREENSHOTS"]) / "viewer_fingers.png")
    (drawn,) = view["drawn"]
    hands = view["subject"]["hands"]
    left = np.concatenate([np.reshape(hands["joints"], (2, 15, 3))[0], np.reshape(hands["tip_joints"], (2, 5, 3))[0]])
    np.testing.assert_allclose(np.array(drawn["fingers"][0]["world"]), left, atol=1e-9)
    np.testing.assert_allclose(np.array(fk[0]), left, atol=1e-5)  # the page's own FK (JSON: 6 decimals)
    projected = project_view(view, left)
    page_points = drawn["fingers"][0]["joints"] + drawn["fingers"][0]["tips"]
    for p, q in zip(projected, page_points, strict=True):
        assert p is not None and q is not None and np.hypot(p[0] - q[0], p[1] - q[1]) < 0.5, (p, q)
    h, w = img.shape[:2]
    mask = near(img, hex_bgr(drawn["colour"]))
    inside = [(x, y) for x, y in projected if 3 <= x < w - 303 and 3 <= y < h - 3]  # type: ignore[misc]
    assert len(inside) == 20, "every left finger joint and tip on the canvas"
    hits = [bool(mask[round(y) - 3 : round(y) + 4, round(x) - 3 : round(x) + 4].any()) for x, y in inside]
    assert all(hits), hits
    # Bent: the index fingertip hangs well below its knuckle on screen (+y is down), not straight out beside it.
    knuckle, tip = projected[3], projected[16]
    assert knuckle is not None and tip is not None and tip[1] - knuckle[1] > 20
