"""The camera demo's fake GigE Vision cameras: one ``mocapd/sim/fake_gige.py`` server process per camera, kept running.

Each camera serves its video at the video's own pace from a shared epoch (``--video-fps``, ``--epoch-ns``), so the
four cameras show the same instant of the synchronised Pose2Sim videos, and a frame the server misses is skipped
as a real camera would skip it. The short clips play forwards then backwards (``--bounce``): no teleporting.
A server process that ends (crashed, or killed to simulate unplugging the cable) is
counted and started again after ``replug_after_s``: the camera is "plugged back in", and mocapd's capture path has
to find it again on its own.

Must run inside a private network namespace with one loopback alias per camera (Aravis broadcasts otherwise).
The servers run from the source tree (``tools/`` is not installed), as ``mocapd demo --synthetic``'s simulators do.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mocapd.errors import DeviceError
from mocapd.io import cpu_budget
from mocapd.sim import fake_gige

log = logging.getLogger(__name__)

START_TIMEOUT_S = 120.0  # decoding and pre-encoding a video on a loaded 2-core machine


@dataclass(frozen=True)
class FakeCameraSpec:
    """One fake camera: what it serves, where, and how.

    Attributes
    ----------
    name : str
        The camera's name (the calibration's).
    video : Path
    address : str
        Loopback alias it serves on (127.0.0.x).
    size : (int, int)
        (width, height) the video is resized to.
    video_fps : float
        The video's frame rate (real pace).
    pixel_format : str
        Format pre-encoded at start (the one the capture asks for).
    max_frames : int
        Frames of the video served, looped.
    """

    name: str
    video: Path
    address: str
    size: tuple[int, int]
    video_fps: float
    pixel_format: str = "BayerRG8"
    max_frames: int = 100


@dataclass
class FakeCameraState:
    """Health of one fake camera process."""

    spec: FakeCameraSpec
    pid: int | None = None
    running: bool = False
    starts: int = 0
    exits: int = 0
    last_exit_code: int | None = None
    ready: asyncio.Event = field(default_factory=asyncio.Event)

    def as_dict(self) -> dict[str, Any]:
        return {"name": self.spec.name, "address": self.spec.address, "pid": self.pid, "running": self.running,
                "starts": self.starts, "exits": self.exits, "last_exit_code": self.last_exit_code}  # fmt: skip


async def _ready_line(proc: asyncio.subprocess.Process) -> tuple[dict[str, Any], str]:
    """The server's ready line (its JSON), or ({}, its last line of output) once it has ended without one: the
    cause of a failed start (no Aravis, a video that does not decode) in one line, not its whole output."""
    assert proc.stdout is not None
    last = ""
    while line := await proc.stdout.readline():
        text = line.decode(errors="replace").strip()
        with contextlib.suppress(ValueError):
            info = json.loads(text)
            if isinstance(info, dict) and info.get("ready"):
                return info, text
        last = text or last
    return {}, last


class FakeCameraFleet:
    """Starts the fake cameras, restarts any that ends after ``replug_after_s``, stops them all at the end.

    Parameters
    ----------
    specs : sequence of FakeCameraSpec
    epoch_ns : int
        ``time.monotonic_ns()`` of video frame 0, shared by all cameras.
    replug_after_s : float
        Pause between a server's end and its restart (the cable is out for that long).
    """

    def __init__(self, specs: list[FakeCameraSpec], epoch_ns: int, replug_after_s: float = 3.0) -> None:
        self.cameras = [FakeCameraState(s) for s in specs]
        self.epoch_ns = epoch_ns
        self.replug_after_s = replug_after_s
        self._procs: dict[str, asyncio.subprocess.Process] = {}
        self.stopping = False  # set by stop(): a server ending now was stopped, not unplugged

    def _command(self, spec: FakeCameraSpec) -> list[str]:
        cmd: list[str] = fake_gige.server_command(
            spec.video, spec.address, spec.max_frames, spec.pixel_format, serial=spec.name.upper(),
            size=f"{spec.size[0]}x{spec.size[1]}", video_fps=spec.video_fps, epoch_ns=self.epoch_ns, bounce=True,
        )  # fmt: skip
        return cmd

    async def _start(self, cam: FakeCameraState) -> asyncio.subprocess.Process:
        # Its own session: a terminal's Ctrl-C goes to the daemon, not to the cameras, which stay up (as real
        # cameras would) until stop() ends them after the daemon has closed its streams.
        # It ends with this process however this one ends (lifecycle.child_command): no server outlives the demo.
        proc = await asyncio.create_subprocess_exec(
            *self._command(cam.spec),
            stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.STDOUT,
            stdin=asyncio.subprocess.DEVNULL,
            start_new_session=True,
        )
        self._procs[cam.spec.name] = proc  # known at once, so a stop while it starts terminates it too
        cpu_budget.exempt(proc.pid)  # a camera encodes on its own: outside the daemon's CPU budget, if it has one
        try:
            info, said = await asyncio.wait_for(_ready_line(proc), START_TIMEOUT_S)
        except TimeoutError:
            info, said = {}, f"no ready line within {START_TIMEOUT_S:g} s"
        if not info.get("ready"):
            with contextlib.suppress(ProcessLookupError):
                proc.kill()
            await proc.wait()
            raise DeviceError(f"fake camera {cam.spec.name} did not start: {said or 'no output'}")
        cam.pid, cam.running = proc.pid, True
        cam.starts += 1
        cam.ready.set()
        return proc

    async def _keep(self, cam: FakeCameraState, proc: asyncio.subprocess.Process) -> None:
        while True:
            code = await proc.wait()
            cam.running, cam.exits, cam.last_exit_code = False, cam.exits + 1, code
            cam.ready.clear()
            if self.stopping:
                return
            log.warning("fake camera %s (pid %s) ended with %s; plugged back in after %.1f s",
                        cam.spec.name, cam.pid, code, self.replug_after_s)  # fmt: skip
            await asyncio.sleep(self.replug_after_s)
            if self.stopping:
                return
            try:
                proc = await self._start(cam)
            except DeviceError as exc:
                log.error("%s", exc)
                continue

    async def run(self, started: asyncio.Event) -> None:
        """Start every camera (in parallel), set ``started``, then keep them running until cancelled."""
        try:
            # A task group: the first camera that does not start cancels the others' starts (stop() below ends
            # their processes), and its error is the one raised.
            try:
                async with asyncio.TaskGroup() as starting:
                    starts = [starting.create_task(self._start(c)) for c in self.cameras]
            except* DeviceError as group:
                raise group.exceptions[0] from None
            procs = [t.result() for t in starts]
            started.set()
            async with asyncio.TaskGroup() as tg:
                for cam, proc in zip(self.cameras, procs, strict=True):
                    tg.create_task(self._keep(cam, proc))
        finally:
            await self.stop()

    async def stop(self) -> None:
        """Terminate every server (SIGTERM, then SIGKILL after 3 s); none is restarted from now on."""
        self.stopping = True
        procs, self._procs = list(self._procs.values()), {}
        for p in procs:
            if p.returncode is None:
                with contextlib.suppress(ProcessLookupError):
                    p.terminate()
        for p in procs:
            try:
                await asyncio.wait_for(p.wait(), 3.0)
            except TimeoutError:
                with contextlib.suppress(ProcessLookupError):
                    p.kill()
                await p.wait()
        for cam in self.cameras:
            cam.running = False

    def status(self) -> list[dict[str, Any]]:
        return [c.as_dict() for c in self.cameras]
