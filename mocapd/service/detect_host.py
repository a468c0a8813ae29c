"""``mocapd detect-host``: a camera host. Runs the cameras of its config (any local source kind, built by the rig
code of ``mocapd run``) and their detector, and publishes over Zenoh, per camera frame, the detections on
``mocapd/<rig>/<camera>/detections``; its status on ``mocapd/<rig>/hosts/<host>/status`` every
``status_period_s``; and answers clock queries on ``mocapd/<rig>/hosts/<host>/clock`` with its monotonic clock
(the solver host's offset estimate). Messages: :mod:`mocapd.protocols.remote`; docs/scaling.md.

Detections are published best-effort and never queued behind a slow link (Zenoh's ``DROP`` congestion control):
a frame that cannot go now is worth nothing later, the solver host interpolates across the gap.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import secrets
import time
from collections.abc import Callable
from typing import Any

import zenoh

from mocapd.core.sorting import Detections2D
from mocapd.errors import ConfigError
from mocapd.io import lifecycle
from mocapd.io.zenoh_link import LinkWatch, clock_key, detections_key, host_name, open_session, status_key
from mocapd.pipeline.keypoint_source import KeypointSource
from mocapd.protocols.remote import CameraState, encode_clock, encode_detections, encode_status
from mocapd.service.config import Config
from mocapd.service.config.cameras import ZenohCamera
from mocapd.service.supervisor import Supervisor

log = logging.getLogger(__name__)


class DetectionPublisher:
    """Publishes a camera host's detections and status, and answers its clock queries (one host run).

    Parameters
    ----------
    session : zenoh.Session
    rig, host : str
        ``[zenoh] rig`` and this host's name.
    cameras : list of (name, width, height)
        The host's cameras in camera index order (the index a keypoint source passes to :meth:`sink`).
    """

    def __init__(
        self, session: zenoh.Session, rig: str, host: str, cameras: list[tuple[str, int, int]],
        *, clock: Callable[[], int] = time.monotonic_ns,
    ) -> None:  # fmt: skip
        self.host = host
        self.cameras = cameras
        self.clock = clock
        self.run_id = secrets.randbits(64)  # a restarted host is a new run: the solver host starts it over
        self.started_ns = clock()
        self.frames = [0] * len(cameras)
        self.errors = 0
        self._pubs = [
            session.declare_publisher(detections_key(rig, name), congestion_control=zenoh.CongestionControl.DROP,
                                      reliability=zenoh.Reliability.BEST_EFFORT, express=True)
            for name, _, _ in cameras
        ]  # fmt: skip
        self._status = session.declare_publisher(status_key(rig, host), express=True)
        self._clock = session.declare_queryable(clock_key(rig, host), self._on_clock)

    def _on_clock(self, query: zenoh.Query) -> None:
        # Answered on Zenoh's thread at once: the reply's time is read as late as possible before it leaves.
        query.reply(query.key_expr, encode_clock(self.host, self.run_id, self.clock()))

    def sink(self, camera: int, capture_ns: int, dets: Detections2D, arrival_ns: int) -> None:
        """A keypoint source's sink: one camera frame's detections out."""
        name, width, height = self.cameras[camera]
        data = encode_detections(self.host, name, self.run_id, self.frames[camera], capture_ns, self.clock(),
                                 width, height, dets)  # fmt: skip
        self.frames[camera] += 1
        try:
            self._pubs[camera].put(data)
        except zenoh.ZError as exc:  # counted; the next frame tries again
            self.errors += 1
            log.warning("camera %s: publish failed: %s", name, exc)

    def publish_status(self, up: list[bool]) -> None:
        cams = [CameraState(n, f, u) for (n, _, _), f, u in zip(self.cameras, self.frames, up, strict=True)]
        uptime = (self.clock() - self.started_ns) / 1e9
        with contextlib.suppress(zenoh.ZError):
            self._status.put(encode_status(self.host, self.run_id, self.clock(), uptime, cams))

    def close(self) -> None:
        with contextlib.suppress(zenoh.ZError):
            for pub in [*self._pubs, self._status]:
                pub.undeclare()  # type: ignore[no-untyped-call]
            self._clock.undeclare()  # type: ignore[no-untyped-call]


async def serve(
    config: Config,
    sources: list[KeypointSource],
    sizes: list[tuple[int, int]],
    *,
    stop: asyncio.Event,
    seconds: float | None = None,
    on_ready: Callable[[str], None] | None = None,
    clock: Callable[[], int] = time.monotonic_ns,
) -> dict[str, Any]:
    """Publish ``sources``' detections until ``stop`` (or ``seconds``); returns the last status.

    ``sources`` are the host's keypoint sources in camera order, ``sizes`` their (width, height).
    """
    z = config.zenoh
    host = host_name(z)
    loop = asyncio.get_running_loop()
    session = await loop.run_in_executor(None, functools.partial(open_session, z))
    cameras = [(s.name, w, h) for s, (w, h) in zip(sources, sizes, strict=True)]
    publisher = DetectionPublisher(session, z.rig, host, cameras, clock=clock)
    supervisor = Supervisor(config.daemon.restart_min_s, config.daemon.restart_max_s)

    def state() -> dict[str, Any]:
        return {"host": host, "run_id": f"{publisher.run_id:016x}", "frames": dict(zip([c[0] for c in cameras],
                publisher.frames, strict=True)), "publish_errors": publisher.errors,
                "cameras": [s.status() for s in sources]}  # fmt: skip

    try:
        async with asyncio.TaskGroup() as tg:
            runs = [(f"keypoints:{s.name}", functools.partial(s.run, _sink(publisher, i))) for i, s in
                    enumerate(sources)]  # fmt: skip
            tasks = [tg.create_task(supervisor.supervise(name, factory)) for name, factory in runs]
            end = None if seconds is None else loop.time() + seconds
            ready = False
            links = LinkWatch(session, z.connect, z.lost_after_s, loop.time())
            while not stop.is_set() and (end is None or loop.time() < end):
                said = links.check(loop.time())  # a link Zenoh cannot make is otherwise never said (issue 45)
                if said is not None:
                    getattr(log, said[0])("%s", said[1])
                up = [s.open_state().state == "open" for s in sources]
                publisher.publish_status(up)
                if not ready and all(up):
                    ready = True
                    lifecycle.enter_phase("running")
                    if on_ready is not None:
                        on_ready(host)
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(stop.wait(), z.status_period_s)
            for t in tasks:
                t.cancel()
        return state()
    finally:
        publisher.close()
        await loop.run_in_executor(None, session.close)


def _sink(publisher: DetectionPublisher, index: int) -> Callable[[int, int, Detections2D, int], None]:
    """The sink of the host's ``index``-th source (a source's own camera number is that of its rig, which for a
    host publishing part of a simulated rig is not its place among the host's cameras)."""
    return lambda _camera, capture_ns, dets, arrival_ns: publisher.sink(index, capture_ns, dets, arrival_ns)


def run(config: Config, *, seconds: float | None = None, on_ready: Callable[[str], None] | None = None) -> int:
    """``mocapd detect-host``: build the config's cameras and detector, publish until SIGINT/SIGTERM."""
    from mocapd.io.tls_files import check_tls_files
    from mocapd.service.rig import build_rig
    from mocapd.service.rig_plan import plan_rig

    remote = [c.name for c in config.cameras if isinstance(c, ZenohCamera)]
    if remote:
        raise ConfigError(f"cameras {remote}: a camera host runs its own cameras; source = \"zenoh\" is the solver "
                          "host's view of them")  # fmt: skip
    plan = plan_rig(config)
    z = config.zenoh
    check_tls_files(z.tls_root_ca, z.tls_cert, z.tls_key)  # a TLS link Zenoh cannot make fails without a word
    lifecycle.enter_phase("loading models")
    built = build_rig(config, plan)  # a stop signal now raises StopRequested: the detector is closed on the way out
    try:
        sizes = [(c.width, c.height) for c in plan.cameras]

        async def main(stop: asyncio.Event) -> int:
            lifecycle.enter_phase("opening devices")
            await serve(config, built.rig.sources, sizes, stop=stop, seconds=seconds, on_ready=on_ready)
            return 0

        return lifecycle.run_until_stopped(main)
    finally:
        lifecycle.enter_phase("stopping")
        built.close()
