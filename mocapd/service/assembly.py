"""The one assembly path: the daemon a config describes, built and run by one function.

``mocapd run`` feeds it the user's config; ``mocapd demo`` a generated config naming fake GigE Vision cameras
(:mod:`mocapd.service.demo.cameras`); ``mocapd demo --synthetic`` a generated config of ``synthetic`` cameras;
``mocapd bench latency`` either of those. Nothing else wires a daemon. What differs between them is only data:
the config, the sockets a parent process made (the camera demo runs in a private network namespace), where a
session is recorded, and a monitor that watches the running daemon (the benchmark's measurements).

What :func:`assemble` builds, in order: the rig (:mod:`mocapd.service.rig`: cameras and their sources, the shared
detector, the people's model, the IMU suits; for a synthetic rig its world and simulated devices), the daemon
(:class:`~mocapd.service.daemon.Daemon`: IMU inputs, scheduler, status server), and its outputs: the truth
score of a synthetic rig, the UDP streams (MVN, VMC), the WebSocket stream and viewer, the session recorder.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import threading
import time
from collections.abc import Awaitable, Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mocapd.io import lifecycle
from mocapd.pipeline.detector_pool import detector_status
from mocapd.pipeline.mattes import MatteSource, RingMattes
from mocapd.service.config import Config
from mocapd.service.config.udp import describe_streams
from mocapd.service.daemon import Daemon, PoseSink, in_daemon_thread
from mocapd.service.outputs.recorder import SessionRecorder, attach_recorder, synthetic_extra
from mocapd.service.outputs.udp import build_udp_sinks
from mocapd.service.outputs.websocket import build_websocket_sinks
from mocapd.service.rig import BuiltRig, build_rig
from mocapd.service.rig_plan import RigPlan, plan_rig
from mocapd.service.suits import calibration_line
from mocapd.sim.silhouettes import SyntheticMattes
from mocapd.sim.truth import TruthError

#: watches a running daemon (from READY) until it returns; the daemon then stops
Monitor = Callable[[Daemon], Awaitable[None]]


@dataclass(frozen=True)
class Sockets:
    """Sockets a parent process made for the daemon in its own network namespace (the camera demo runs in a
    private one): the status server's listener, the WebSocket listener and a UDP socket for MVN/VMC."""

    http: socket.socket | None = None
    websocket: socket.socket | None = None
    udp_fileno: int | None = None


@dataclass(frozen=True)
class RunOptions:
    """How to run what a config describes (everything that is not the config itself)."""

    record: Path | None = None
    """Record the run as a session into this new directory (also when ``[record] enabled``)."""
    sockets: Sockets = field(default_factory=Sockets)
    status_line: Callable[[str], None] | None = None
    """Called with a one-line summary every second."""
    sinks: Sequence[PoseSink] = ()
    """More pose sinks (a test's or a benchmark's)."""
    manifest_extra: dict[str, Any] = field(default_factory=dict)
    """More for the session manifest's ``extra`` (e.g. how a demo was generated)."""
    status_extras: dict[str, Callable[[], Any]] = field(default_factory=dict)
    """More sections of /status (e.g. the camera demo's fake cameras)."""


@dataclass
class Assembly:
    """A built daemon and what it owns: the rig (closed after the daemon stops), its truth score (synthetic)."""

    daemon: Daemon
    built: BuiltRig
    truth: TruthError | None
    recorder: SessionRecorder | None

    def close(self) -> None:
        self.built.close()


def assemble(
    config: Config,
    options: RunOptions = RunOptions(),
    *,
    plan: RigPlan | None = None,
    clock: Callable[[], int] = time.monotonic_ns,
) -> Assembly:
    """Build (not run) the daemon of ``config`` (blocking: checks the rig, loads the models, starts simulators).

    Raises
    ------
    ConfigError
        The rig does not check out against its calibration or files (see :func:`~mocapd.service.rig_plan.plan_rig`).
    ModelError
        The detector model or the pose prior cannot be loaded.
    """
    plan = plan if plan is not None else plan_rig(config)
    built = build_rig(config, plan, clock)
    try:
        daemon = Daemon(config, built.rig, imu=built.imu, sinks=list(options.sinks), clock=clock,
                        status_line=options.status_line, mattes=rig_mattes(config, built))  # fmt: skip
        daemon.handle_signals = False  # run() below owns them, from before the daemon exists to after it ends
        if options.sockets.http is not None:
            daemon.http = daemon.status_server(options.sockets.http)
        if built.remote is not None:
            daemon.status_extras["remote_hosts"] = built.remote.status
            daemon.status_extras["zenoh_links"] = built.remote.links
        daemon.status_extras.update(options.status_extras)
        if built.detector is not None:
            det = built.detector
            daemon.status_extras.setdefault("detector", lambda: detector_status(det))
        truth = None
        extra = dict(options.manifest_extra)
        if built.world is not None:
            truth = TruthError(built.world, built.epoch_ns)
            daemon.sinks.insert(0, truth)
            daemon.status_line_extras.append(truth.status_field)
            extra["synthetic"] = synthetic_extra(config.synthetic, [c.name for c in plan.cameras], built.epoch_ns)
        daemon.sinks.extend(build_udp_sinks(config, daemon, options.sockets.udp_fileno))
        daemon.sinks.extend(build_websocket_sinks(config, daemon, options.sockets.websocket))
        recorder = attach_recorder(config, daemon, options.record, extra=extra or None)
    except BaseException:
        built.close()
        raise
    return Assembly(daemon, built, truth, recorder)


def ready_lines(built: Assembly) -> list[str]:
    """What ``mocapd run`` and the demos say at READY besides the status URL: the viewer, where each enabled UDP
    stream goes, and the session being recorded with the commands that use it."""
    lines = []
    for sink in built.daemon.sinks:
        viewer = getattr(sink, "viewer_url", None)
        if viewer is not None:
            lines.append(f"viewer {viewer}  pose stream {getattr(sink, 'url', '')}")
    lines += describe_streams(built.daemon.config.udp)
    lines += [calibration_line(suit) for suit in built.daemon.rig.suits]
    if built.recorder is not None:
        where = built.recorder.writer.directory
        lines.append(f"recording the session to {where} (then `mocapd resolve {where}`, `mocapd export {where} "
                     "--resolved --gltf take.glb`)")  # fmt: skip
    return lines


def rig_mattes(config: Config, built: BuiltRig) -> MatteSource | None:
    """The foreground mattes of the learned fusion (``[fusion]``): rendered on the synthetic rig, background
    subtraction of the cameras' frames elsewhere; None in mode "solver" or without any camera frames."""
    if config.fusion.mode == "solver":
        return None
    if built.world is not None:
        return SyntheticMattes(built.world, built.epoch_ns, seed=config.synthetic.seed)
    rings = {c.name: c.ring for c in built.captures}
    if not rings:
        return None
    return RingMattes([rings.get(cam.name) for cam in built.rig.cameras])


@contextlib.contextmanager
def assembled(config: Config, options: RunOptions = RunOptions(), **kw: Any) -> Iterator[Assembly]:
    """:func:`assemble`, closed on exit (for callers that run ``daemon.run()`` themselves, e.g. tests)."""
    built = assemble(config, options, **kw)
    try:
        yield built
    finally:
        built.close()


async def run(
    config: Config,
    options: RunOptions = RunOptions(),
    *,
    monitor: Monitor | None = None,
    seconds: float | None = None,
    stop: asyncio.Event | None = None,
    on_ready: Callable[[Assembly], None] | None = None,
) -> int:
    """Build and run the daemon of ``config`` until ``stop`` is set (stop signals set it, see
    :func:`mocapd.io.lifecycle.stop_event`), ``seconds`` have passed since READY, or ``monitor`` returns.

    A stop in any phase ends the run: while the rig is built (models loaded, simulators started) the builder
    thread is abandoned — it closes what it made when it finishes, and a process that exits first
    (:func:`~mocapd.io.lifecycle.exit_now`) takes it along — rather than waited for.

    Returns the exit status (0). A start-up failure (a device that does not open, a stream that cannot listen)
    raises: :class:`~mocapd.service.daemon.StartupError`, :class:`~mocapd.errors.MocapdError`.
    """
    stop = stop if stop is not None else asyncio.Event()
    loop = asyncio.get_running_loop()
    lifecycle.enter_phase("loading models")
    abandoned = threading.Event()

    def build() -> Assembly:
        built = assemble(config, options)
        if abandoned.is_set():  # nobody waits for it any more
            built.close()
        return built

    building = in_daemon_thread(build)
    if not await _first(building, stop):
        abandoned.set()
        building.cancel()
        return 0
    assembly = building.result()
    daemon = assembly.daemon
    try:
        if stop.is_set():
            return 0
        task = asyncio.create_task(daemon.run(), name="daemon")
        stopper = asyncio.create_task(_stop_when(stop, daemon), name="stop")
        try:
            ready = asyncio.create_task(daemon.ready.wait())
            await asyncio.wait({task, ready}, return_when=asyncio.FIRST_COMPLETED)
            if ready.done():
                if on_ready is not None:
                    on_ready(assembly)
                watchers: list[asyncio.Future[Any]] = []
                if monitor is not None:
                    watchers.append(asyncio.ensure_future(monitor(daemon)))
                if seconds is not None:
                    watchers.append(asyncio.ensure_future(asyncio.sleep(seconds)))
                if watchers:
                    await asyncio.wait({task, *watchers}, return_when=asyncio.FIRST_COMPLETED)
                    for w in watchers:
                        w.cancel()
                    daemon.request_stop()
                    code = await task
                    for w in watchers:  # a monitor that failed is a bug in it: say so, after the clean stop
                        if w.done() and not w.cancelled() and (exc := w.exception()) is not None:
                            raise exc
                    return code
            else:
                ready.cancel()
            return await task
        finally:
            stopper.cancel()
    finally:
        await loop.run_in_executor(None, assembly.close)


async def _first(work: asyncio.Future[Any], stop: asyncio.Event) -> bool:
    """Wait for ``work`` or ``stop``, whichever comes first; True when ``work`` finished."""
    waiting = asyncio.ensure_future(stop.wait())
    try:
        await asyncio.wait({work, waiting}, return_when=asyncio.FIRST_COMPLETED)
    finally:
        waiting.cancel()
    return work.done()


async def _stop_when(stop: asyncio.Event, daemon: Daemon) -> None:
    await stop.wait()
    daemon.request_stop()


def stop_on_signals(stop: asyncio.Event) -> contextlib.AbstractContextManager[None]:
    """Stop signals set ``stop`` while inside (:func:`mocapd.io.lifecycle.stop_event`)."""
    return lifecycle.stop_event(stop)
