"""The README's pictures, made here: the live viewer with its camera panels (headless Chromium) and the Blender
live link (headless Blender, Cycles), both against the synthetic-rig daemon.

    .venv/bin/python -m tools.readme_images docs/images

Needs Debian's Chromium (setup/steps/25-chromium.sh) and ``.venv-bpy`` (setup/steps/40-bpy.sh).
"""

from __future__ import annotations

import argparse
import asyncio
import os
import sys
from pathlib import Path

import cv2

from mocapd.service.config import load_config
from tests.cdp import chromium_page
from tests.test_camera_panels import camera_daemon
from tests.test_web_viewer import free_port

ROOT = Path(__file__).resolve().parents[1]


async def make(out: Path) -> None:
    cfg = load_config()
    cfg = cfg.model_copy(update={"daemon": cfg.daemon.model_copy(update={"http_port": 0}),
                                 "websocket": cfg.websocket.model_copy(update={"port": free_port()})})  # fmt: skip
    async with camera_daemon(cfg) as (url, _cameras, _server):
        async with chromium_page(url + "?cameras=1") as page:
            ready = (
                "window.mocapdViewer && mocapdViewer.cameraPanels().length == 4 && mocapdViewer.cameraPanels()"
                ".every((c) => c.image && c.subjects.length == 2) && mocapdViewer.state.statusMessages > 2"
            )
            await page.wait_for(ready, 120, "camera panels with both people")
            await asyncio.sleep(2.0)  # settled solves
            await page.evaluate("mocapdViewer.pause(true)")
            await asyncio.sleep(0.5)
            img = await page.screenshot()
        cv2.imwrite(str(out / "viewer-camera-panels.png"), img, [cv2.IMWRITE_PNG_COMPRESSION, 9])
        bpy = ROOT / ".venv-bpy" / "bin" / "python"
        proc = await asyncio.create_subprocess_exec(
            str(bpy), str(ROOT / "tools" / "blender" / "render_link.py"), url.replace("http", "ws"),
            str(out / "blender-live-link.png"), env=dict(os.environ),
        )  # fmt: skip
        if await proc.wait() != 0:
            sys.exit("the Blender render failed")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("out", type=Path)
    args = p.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    asyncio.run(make(args.out))


if __name__ == "__main__":
    main()
