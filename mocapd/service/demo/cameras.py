"""``mocapd demo``: the full daemon on the camera rig — four fake GigE Vision cameras streaming the Pose2Sim
multi-person demo videos, the real detector, sorting/tracking, solving — in a private network namespace.

Why two processes. Aravis discovery broadcasts on every interface, so cameras must live on loopback aliases
inside a private network namespace (``unshare -rn``), and so must the daemon that talks to them. But the status
page must be reachable from the user's browser, in the host's namespace. A socket belongs to the namespace it was
created in, whatever process later uses it, so:

1. the parent (``mocapd demo``, host namespace) binds and listens on ``daemon.http_host:http_port``;
2. it starts ``unshare -rn python -m mocapd.service.demo.cameras --http-fd N ...`` with that socket inherited
   (``pass_fds``) and closes its own copy;
3. the child (new namespace) brings ``lo`` up with aliases 127.0.0.2-4, starts the four fake cameras there, builds
   the rig and runs the daemon, whose status server accepts on the inherited socket: connections from the host
   reach it, while every camera packet stays inside the namespace.

The parent only forwards SIGINT/SIGTERM and returns the child's exit status. No relay, no second port.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Coroutine
from dataclasses import asdict
from pathlib import Path
from typing import Any

from mocapd.errors import DeviceError, MocapdError
from mocapd.io.ws_server import listen_error
from mocapd.pipeline.scheduler import PoseFrame
from mocapd.service.config import Config, load_config
from mocapd.service.daemon import Daemon, PoseSink, Rig
from mocapd.service.demo.camera_rig import AnyDetector, CameraDemoOptions, build_rig, demo_cameras, make_detector
from mocapd.service.http_status import StatusServer
from mocapd.service.outputs.recorder import attach_recorder
from mocapd.service.outputs.udp import build_udp_sinks
from mocapd.service.outputs.websocket import build_websocket_sinks
from mocapd.sim.fake_cameras import FakeCameraFleet
from mocapd.sim.fake_gige import add_loopback_aliases


class CameraDemoDaemon(Daemon):
    """The daemon of the camera demo: serves on an inherited socket and reports its fake cameras in /status."""

    def __init__(
        self, config: Config, rig: Rig, fleet: FakeCameraFleet, *, http_socket: socket.socket | None, **kw: Any
    ) -> None:
        super().__init__(config, rig, **kw)
        self.fleet = fleet
        if http_socket is not None:
            self.http = StatusServer(self.status, self.metrics, sock=http_socket)

    def status(self) -> dict[str, Any]:
        out = super().status()
        out["fake_cameras"] = self.fleet.status()
        return out

    def status_line_text(self) -> str:
        cams = [s.status() for s in self.rig.sources]
        up = sum(1 for c in cams if c.get("capture", {}).get("up"))
        detected = sum(int(c["detected"]) for c in cams)
        return f"{super().status_line_text()}  cameras up {up}/{len(cams)}  detected {detected}"


class PeopleCount:
    """A pose sink counting what was solved: frames with people, the most people in a frame, identities."""

    def __init__(self) -> None:
        self.frames = 0
        self.frames_with_people = 0
        self.max_people = 0
        self.identities: set[str] = set()

    def publish(self, frame: PoseFrame) -> None:
        self.frames += 1
        if frame.people:
            self.frames_with_people += 1
            self.max_people = max(self.max_people, len(frame.people))
            self.identities.update(p.identity for p in frame.people)

    async def start(self) -> None:
        return None

    async def aclose(self) -> None:
        return None


Monitor = Callable[[CameraDemoDaemon], Coroutine[Any, Any, None]]


async def run_camera_demo(
    config: Config,
    opts: CameraDemoOptions,
    monitor: Monitor,
    *,
    http_socket: socket.socket | None = None,
    sinks: list[PoseSink] | None = None,
    status_line: Callable[[str], None] | None = None,
    configure: Callable[[CameraDemoDaemon], None] | None = None,
) -> int:
    """Start the fake cameras and the daemon (in this process's network namespace, which must be private), run
    ``monitor(daemon)`` once the daemon is ready, and stop everything when it returns or on SIGINT/SIGTERM.
    ``configure(daemon)`` runs once the daemon is built, before it starts (streams, recorder)."""
    loop = asyncio.get_running_loop()
    addresses = add_loopback_aliases(4)
    cameras, specs = demo_cameras(opts, addresses)
    fleet = FakeCameraFleet(specs, time.monotonic_ns(), opts.replug_after_s)
    stop = asyncio.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    started = asyncio.Event()
    fleet_task = asyncio.create_task(fleet.run(started))
    detector: AnyDetector | None = None
    try:
        detector = await loop.run_in_executor(None, make_detector, config.detector.options(), opts, cameras)
        rig, _ = await loop.run_in_executor(None, build_rig, config, opts, cameras, specs, detector)
        waits = {asyncio.create_task(w) for w in (started.wait(), stop.wait())} | {fleet_task}
        await asyncio.wait(waits, return_when=asyncio.FIRST_COMPLETED)
        for w in waits - {fleet_task}:
            w.cancel()
        if fleet_task.done():
            fleet_task.result()  # a camera did not start: raise its error
        if stop.is_set():
            return 0
        daemon = CameraDemoDaemon(config, rig, fleet, http_socket=http_socket, sinks=sinks, status_line=status_line)
        if configure is not None:
            configure(daemon)
        task = asyncio.create_task(daemon.run())  # installs its own SIGINT/SIGTERM handlers
        ready = asyncio.create_task(daemon.ready.wait())
        await asyncio.wait({task, ready}, return_when=asyncio.FIRST_COMPLETED)
        if ready.done():
            watch = asyncio.create_task(monitor(daemon))
            await asyncio.wait({task, watch}, return_when=asyncio.FIRST_COMPLETED)
            watch.cancel()
            daemon.request_stop()
        return await task
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)
        fleet_task.cancel()
        with contextlib.suppress(asyncio.CancelledError, DeviceError):  # a start failure was raised above
            await fleet_task
        if detector is not None:
            await loop.run_in_executor(None, detector.close)


def _demo_monitor(seconds: float | None) -> Monitor:
    async def monitor(daemon: CameraDemoDaemon) -> None:
        url = daemon.http.url
        print(f"ready: status {url}/status  metrics {url}/metrics  (Ctrl-C stops)", flush=True)
        if seconds is None:
            await asyncio.Event().wait()
        await asyncio.sleep(seconds or 0.0)

    return monitor


def _summary(daemon: CameraDemoDaemon | None, people: PeopleCount) -> dict[str, Any]:
    out: dict[str, Any] = {
        "frames": people.frames, "frames_with_people": people.frames_with_people, "max_people": people.max_people,
        "identities": sorted(people.identities),
    }  # fmt: skip
    if daemon is not None:
        st = daemon.status()
        out["missed_ticks"] = st["output"]["missed_ticks"]
        out["detected"] = {c["name"]: c["detected"] for c in st["cameras"]}
        out["end_to_end_ms"] = st["latency_ms"]["end_to_end"]
    return out


def child_main(argv: list[str] | None = None) -> int:
    """Entry point inside the private network namespace (``python -m mocapd.service.demo.cameras``)."""
    p = argparse.ArgumentParser(description="mocapd camera demo (inside a private network namespace)")
    p.add_argument("--config", type=Path, default=None)
    p.add_argument("--seconds", type=float, default=0.0)
    p.add_argument("--http-fd", type=int, default=None, help="inherited listening socket for /status")
    p.add_argument("--record", type=Path, default=None, help="record the run as a session into this directory")
    p.add_argument("--ws-fd", type=int, default=None, help="inherited listening socket for the WebSocket stream")
    p.add_argument("--udp-fd", type=int, default=None, help="inherited UDP socket for the MVN / VMC streams")
    p.add_argument("--options", default="{}", help="CameraDemoOptions fields as JSON")
    args = p.parse_args(argv)
    opts = CameraDemoOptions(**json.loads(args.options))
    config = opts.apply(load_config(args.config))
    sock = socket.socket(fileno=args.http_fd) if args.http_fd is not None else None
    people = PeopleCount()
    sinks: list[PoseSink] = [people]
    ws_sock = socket.socket(fileno=args.ws_fd) if args.ws_fd is not None else None

    def configure(daemon: CameraDemoDaemon) -> None:
        # Streams go out through sockets made in the host's namespace (this one is private): the viewer and the
        # engines on the host reach them; the recorder writes to the shared file system.
        daemon.sinks.extend(build_udp_sinks(config, daemon, args.udp_fd))
        daemon.sinks.extend(build_websocket_sinks(config, daemon, ws_sock))
        attach_recorder(config, daemon, args.record, extra={"camera_demo": asdict(opts)})

    holder: list[CameraDemoDaemon] = []

    async def monitor(daemon: CameraDemoDaemon) -> None:
        holder.append(daemon)
        await _demo_monitor(None if args.seconds <= 0 else args.seconds)(daemon)

    try:
        code = asyncio.run(
            run_camera_demo(config, opts, monitor, http_socket=sock, sinks=sinks,
                            status_line=lambda s: print(s, flush=True), configure=configure)
        )  # fmt: skip
    except MocapdError as exc:  # missing model or demo data, a camera that never started: say what, no traceback
        print(f"error: {exc}", file=sys.stderr, flush=True)
        return 2
    summary = _summary(holder[0] if holder else None, people)
    who = ", ".join(summary["identities"]) or "nobody"
    print(f"done: {summary['frames']} frames, {summary['frames_with_people']} with people solved "
          f"(at most {summary['max_people']} at once: {who})", flush=True)  # fmt: skip
    print(json.dumps({"summary": summary}), flush=True)
    return code


def in_private_netns(
    module: str,
    args: list[str],
    *,
    http_socket: socket.socket | None = None,
    inherited: dict[str, socket.socket] | None = None,
) -> int:
    """Run ``python -m module args`` under ``unshare -rn`` (with ``http_socket`` inherited as ``--http-fd``, and
    each of ``inherited`` as ``--<name> FD``), forwarding SIGINT/SIGTERM to it; returns its exit status."""
    cmd = ["unshare", "-rn", sys.executable, "-m", module, *args]
    passed = dict(inherited or {})
    if http_socket is not None:
        passed["http-fd"] = http_socket
    for flag, sock in passed.items():
        cmd += [f"--{flag}", str(sock.fileno())]
    proc = subprocess.Popen(cmd, pass_fds=tuple(sock.fileno() for sock in passed.values()))
    for sock in passed.values():
        sock.close()  # the child holds them now
    previous = {sig: signal.signal(sig, lambda s, _f: proc.send_signal(s)) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        return proc.wait()
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def run(
    config_path: Path | None,
    config: Config,
    seconds: float | None,
    *,
    opts: CameraDemoOptions,
    record: Path | None = None,
) -> int:
    """``mocapd demo``: bind the status port here, run the demo in a private network namespace."""
    d = config.daemon
    try:
        sock = socket.create_server((d.http_host, d.http_port))
    except OSError as exc:
        print(f"error: cannot listen on {d.http_host}:{d.http_port} ({exc}); try --http-port", file=sys.stderr)
        return 2
    print(
        f"mocapd demo: 4 fake GigE Vision cameras ({opts.pixel_format}, {opts.scale:g} x 1088x1920) streaming the "
        f"Pose2Sim {opts.demo} videos at their own 60 fps pace, in a private network namespace; detector "
        f"{config.detector.model.input_width}x{config.detector.model.input_height} on "
        f"{'packed (all cameras per pass)' if opts.packed else f'{config.detector.workers} worker(s)'}",
        flush=True,
    )
    print(f"status: http://{d.http_host}:{sock.getsockname()[1]}/status  (starting cameras and models ...)", flush=True)
    args = ["--seconds", str(seconds or 0.0), "--options", json.dumps(asdict(opts))]
    if config_path is not None:
        args += ["--config", str(config_path)]
    if record is not None:
        args += ["--record", str(record)]
    inherited = _stream_sockets(config)
    if config.websocket.enabled:
        port = inherited["ws-fd"].getsockname()[1]
        print(f"viewer: http://{config.websocket.host}:{port}/  pose stream ws://{config.websocket.host}:{port}/",
              flush=True)  # fmt: skip
    return in_private_netns("mocapd.service.demo.cameras", args, http_socket=sock, inherited=inherited)


def _stream_sockets(config: Config) -> dict[str, socket.socket]:
    """The streams' sockets, made here in the host's namespace so that what the daemon serves or sends from its
    private namespace reaches the host: the WebSocket listener, and one UDP socket for MVN and VMC."""
    out: dict[str, socket.socket] = {}
    ws = config.websocket
    if ws.enabled:
        try:
            out["ws-fd"] = socket.create_server((ws.host, ws.port))
        except OSError as exc:
            raise listen_error(ws.host, ws.port, exc) from exc
    if config.udp.mvn.enabled or config.udp.vmc.enabled:
        out["udp-fd"] = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    return out


if __name__ == "__main__":
    sys.exit(child_main())
