"""Runs inside a private network namespace the test made (``unshare -rn python -m tests.netns_rig ...``): four
Aravis fake GigE Vision cameras serving the Pose2Sim multi-person videos on 127.0.0.1-4, then ``mocapd run
--config FILE`` on them as a user would type it, a WebSocket client reading its pose stream, then Ctrl-C (SIGINT).
Prints one JSON line with what happened; the test asserts on it.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import signal
import sys
import time
from typing import Any

from websockets.asyncio.client import connect

from mocapd.io.pose2sim_demo import CAMERAS, demo_video
from mocapd.protocols.ws_stream import decode
from mocapd.service.demo.cameras import video_fps
from mocapd.sim.fake_cameras import FakeCameraFleet, FakeCameraSpec
from mocapd.sim.fake_gige import add_loopback_aliases

DEMO = "Demo_MultiPerson"


async def _lines(stream: asyncio.StreamReader, out: list[str]) -> None:
    while line := await stream.readline():
        out.append(line.decode(errors="replace"))


async def _wait_line(lines: list[str], prefix: str, timeout: float, proc: asyncio.subprocess.Process) -> str:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        for line in lines:
            if line.startswith(prefix):
                return line
        if proc.returncode is not None:
            break
        await asyncio.sleep(0.1)
    raise RuntimeError(f"no line starting {prefix!r}; the run printed:\n{''.join(lines[-40:])}")


async def _read_stream(url: str, seconds: float, want_two: int) -> dict[str, Any]:
    frames = 0
    with_two = 0
    identities: set[str] = set()
    most = 0
    roots: list[list[float]] = []
    async with connect(url, max_size=2**22) as ws:
        end = time.monotonic() + seconds
        while time.monotonic() < end and with_two < want_two:
            try:
                msg = decode(await asyncio.wait_for(ws.recv(), 5.0))
            except TimeoutError:
                continue
            if msg.get("type") != "frame":
                continue
            frames += 1
            subjects = msg["subjects"]
            most = max(most, len(subjects))
            with_two += len(subjects) >= 2
            for s in subjects:
                identities.add(s["id"])
                roots.append([float(v) for v in s["root"]])
    return {"frames": frames, "frames_with_two": with_two, "max_subjects": most, "identities": sorted(identities),
            "roots": roots[-20:]}  # fmt: skip


async def main(config: str, seconds: float, want_two: int) -> dict[str, Any]:
    addresses = add_loopback_aliases(len(CAMERAS))
    specs = [
        FakeCameraSpec(name, demo_video(DEMO, name), address, (544, 960), video_fps(demo_video(DEMO, name)))
        for name, address in zip(CAMERAS, addresses, strict=True)
    ]
    fleet = FakeCameraFleet(specs, time.monotonic_ns(), replug_after_s=1.0)
    started = asyncio.Event()
    fleet_task = asyncio.create_task(fleet.run(started))
    await asyncio.wait({asyncio.create_task(started.wait()), fleet_task}, return_when=asyncio.FIRST_COMPLETED)
    if fleet_task.done():
        fleet_task.result()
    lines: list[str] = []
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "mocapd", "run", "--config", config, "--verbose",
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.STDOUT,
    )  # fmt: skip
    assert proc.stdout is not None
    pump = asyncio.create_task(_lines(proc.stdout, lines))
    result: dict[str, Any] = {}
    try:
        viewer = await _wait_line(lines, "viewer http://", 300, proc)
        ws_url = viewer.split()[4]
        result["stream"] = await _read_stream(ws_url, seconds, want_two)
        starts_before = [c.starts for c in fleet.cameras]
        t0 = time.monotonic()
        proc.send_signal(signal.SIGINT)  # what Ctrl-C in the terminal sends
        result["exit_code"] = await asyncio.wait_for(proc.wait(), 30)
        result["stop_s"] = round(time.monotonic() - t0, 3)
        result["camera_restarts_during_stop"] = sum(c.starts for c in fleet.cameras) - sum(starts_before)
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
        await pump
        await fleet.stop()
        fleet_task.cancel()
        await asyncio.gather(fleet_task, return_exceptions=True)
    result["output"] = lines[-60:]
    return result


if __name__ == "__main__":
    p = argparse.ArgumentParser()
    p.add_argument("--config", required=True)
    p.add_argument("--seconds", type=float, default=120.0)
    p.add_argument("--want-two", type=int, default=20, help="stop reading after this many frames with 2 subjects")
    args = p.parse_args()
    print(json.dumps(asyncio.run(main(args.config, args.seconds, args.want_two))), flush=True)
