"""Headless Chromium driven over the Chrome DevTools Protocol with the ``websockets`` library (no browser-automation
package): launch, open a page, evaluate JavaScript, take screenshots."""

from __future__ import annotations

import asyncio
import base64
import contextlib
import itertools
import json
import shutil
import subprocess
import tempfile
from collections.abc import AsyncIterator, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from websockets.asyncio.client import ClientConnection, connect

CHROMIUM = "/usr/bin/chromium"
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--remote-debugging-port=0", "--window-size=1100,700"]  # fmt: skip


class Page:
    """One tab, attached with a flat session: ``call`` sends a DevTools command and waits for its result."""

    def __init__(self, ws: ClientConnection, session: str) -> None:
        self.ws = ws
        self.session = session

    async def call(self, method: str, **params: Any) -> dict[str, Any]:
        return await _call(self.ws, method, params, self.session)

    async def evaluate(self, expression: str) -> Any:
        r = await self.call("Runtime.evaluate", expression=expression, returnByValue=True)
        if "exceptionDetails" in r:
            raise AssertionError(f"JavaScript error in {expression!r}: {r['exceptionDetails']}")
        return r["result"].get("value")

    async def wait_for(self, expression: str, timeout: float, what: str) -> Any:
        loop = asyncio.get_running_loop()
        end = loop.time() + timeout
        while True:
            value = await self.evaluate(expression)
            if value:
                return value
            if loop.time() > end:
                raise AssertionError(f"timed out waiting for {what} ({expression})")
            await asyncio.sleep(0.1)

    async def screenshot(self) -> NDArray[np.uint8]:
        """The page as a BGR image (height, width, 3)."""
        r = await self.call("Page.captureScreenshot", format="png")
        png = np.frombuffer(base64.b64decode(r["data"]), dtype=np.uint8)
        img = cv2.imdecode(png, cv2.IMREAD_COLOR)
        assert img is not None
        return np.asarray(img, dtype=np.uint8)


_ids = itertools.count(1)
_pending: dict[int, asyncio.Future[dict[str, Any]]] = {}


async def _call(ws: ClientConnection, method: str, params: dict[str, Any], session: str | None) -> dict[str, Any]:
    i = next(_ids)
    fut: asyncio.Future[dict[str, Any]] = asyncio.get_running_loop().create_future()
    _pending[i] = fut
    msg: dict[str, Any] = {"id": i, "method": method, "params": params}
    if session is not None:
        msg["sessionId"] = session
    await ws.send(json.dumps(msg))
    return await asyncio.wait_for(fut, 30)


async def _pump(ws: ClientConnection) -> None:
    async for raw in ws:
        m = json.loads(raw)
        fut = _pending.pop(m.get("id", -1), None)
        if fut is not None and not fut.done():
            if "error" in m:
                fut.set_exception(AssertionError(f"DevTools error: {m['error']}"))
            else:
                fut.set_result(m.get("result", {}))


@contextlib.asynccontextmanager
async def chromium_page(url: str, flags: Sequence[str] = ()) -> AsyncIterator[Page]:
    """Launch headless Chromium with a fresh profile (and more command-line ``flags``, e.g.
    ``--host-resolver-rules=MAP evil.example 127.0.0.1``), open ``url``; closes the browser afterwards."""
    profile = Path(tempfile.mkdtemp(prefix="mocapd-chromium-"))
    proc = subprocess.Popen([CHROMIUM, *FLAGS, *flags, f"--user-data-dir={profile}", "about:blank"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    try:
        port_file = profile / "DevToolsActivePort"
        async with asyncio.timeout(60):
            while not (port_file.exists() and len(port_file.read_text().splitlines()) >= 2):
                if proc.poll() is not None:
                    raise AssertionError(f"chromium exited with {proc.returncode}")
                await asyncio.sleep(0.1)
        port, path = port_file.read_text().splitlines()[:2]
        async with connect(f"ws://127.0.0.1:{port}{path}", max_size=None) as ws:
            pump = asyncio.create_task(_pump(ws))
            try:
                target = (await _call(ws, "Target.createTarget", {"url": "about:blank"}, None))["targetId"]
                attached = await _call(ws, "Target.attachToTarget", {"targetId": target, "flatten": True}, None)
                page = Page(ws, attached["sessionId"])
                await page.call("Page.enable")
                await page.call("Emulation.setDeviceMetricsOverride", width=1100, height=700, deviceScaleFactor=1,
                                mobile=False)  # fmt: skip
                await page.call("Page.navigate", url=url)
                yield page
            finally:
                pump.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await pump
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        shutil.rmtree(profile, ignore_errors=True)
