"""The solver host's side of camera hosts: ``source = "zenoh"`` cameras as keypoint sources.

One :class:`RemoteRig` per daemon owns the Zenoh session (opened when the first remote camera starts), the camera
hosts' status subscription and a thread that times a clock round trip to each host every ``clock_period_s`` (a
Zenoh query answered by the host's monotonic clock, :mod:`mocapd.core.clock_offset`). Each
:class:`ZenohKeypointSource` subscribes to its camera's detections and hands each frame to the daemon's sink like a
local camera's, at the capture time mapped to this host's clock (remote time - estimated offset): the same
``DetectionTimeline`` then takes it.

Dropped and counted per camera, never delivered: bytes the decoder refuses (by reason), a frame of another camera
or host, a size or keypoint count that is not the rig's, a frame before the host's clock offset is known
(``unsynced``), a frame number not above the last one of that host run (``duplicate``, ``out_of_order``), a frame
that arrives after its instant was solved (``late``: capture older than ``latency_s``). A host not heard from
(status, detections or clock replies) for ``lost_after_s`` is shown lost; its cameras deliver nothing, so their
timelines go stale and they drop out of the solve; when it is heard again it rejoins (a restarted host has a new
run id: its frame numbers and clock offset start again).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import zenoh

from mocapd.core.clock_offset import ClockOffsetEstimator
from mocapd.errors import DeviceError, MocapdError
from mocapd.io.device_state import OpenState
from mocapd.io.zenoh_link import ZenohConfig, clock_key, detections_key, open_session, status_key
from mocapd.pipeline.keypoint_source import KeypointSink
from mocapd.protocols.remote import ClockMessage, Decoder, DetectionsMessage, StatusMessage

log = logging.getLogger(__name__)


@dataclass
class RemoteHost:
    """What the solver host knows of one camera host (guarded by :attr:`RemoteRig.lock`)."""

    name: str
    estimator: ClockOffsetEstimator
    run_id: int | None = None
    last_seen_ns: int | None = None
    lost: bool = True
    losses: int = 0
    joins: int = 0
    restarts: int = 0
    status: StatusMessage | None = None
    round_trips: int = 0
    unanswered: int = 0
    rejected: Counter[str] = field(default_factory=Counter)


class RemoteRig:
    """The Zenoh side of a solver host's remote cameras (see the module docstring)."""

    def __init__(self, z: ZenohConfig, hosts: list[str], *, clock: Callable[[], int] = time.monotonic_ns) -> None:
        self.z = z
        self.clock = clock
        self.lock = threading.Lock()
        self.hosts = {h: RemoteHost(h, ClockOffsetEstimator(z.clock_window, z.clock_drift_ppm)) for h in hosts}
        self.session: zenoh.Session | None = None
        self.error: str = ""
        self._subscribers: list[Any] = []
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._decoder = Decoder()
        self._start_lock = threading.Lock()

    # ------------------------------------------------------------------------------------------ life cycle
    def start(self) -> zenoh.Session:
        """Open the session, subscribe to the hosts' status, start the clock thread (once; blocking)."""
        with self._start_lock:
            if self.session is not None:
                return self.session
            try:
                session = open_session(self.z)
            except MocapdError as exc:
                self.error = str(exc)
                raise
            self._subscribers.append(session.declare_subscriber(status_key(self.z.rig, "*"), self._on_status))
            self.session = session
            self._thread = threading.Thread(target=self._clock_loop, name="mocapd-zenoh-clock", daemon=True)
            self._thread.start()
            return session

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2 * self.z.clock_timeout_s + 1.0)
            self._thread = None
        if self.session is not None:
            with contextlib.suppress(zenoh.ZError):
                self.session.close()  # type: ignore[no-untyped-call]
            self.session = None

    # ------------------------------------------------------------------------------------------ hosts
    def seen(self, host: RemoteHost, run_id: int, now: int) -> None:
        """``host`` was heard from (call under the lock): a new run resets its clock offset."""
        if host.run_id != run_id:
            if host.run_id is not None:
                host.restarts += 1
            host.run_id = run_id
            host.estimator.reset()
        host.last_seen_ns = now
        if host.lost:
            host.lost = False
            host.joins += 1
            log.warning("camera host %s joined (run %x)", host.name, run_id)

    def check_lost(self, now: int) -> None:
        with self.lock:
            for host in self.hosts.values():
                silent = host.last_seen_ns is None or now - host.last_seen_ns > self.z.lost_after_s * 1e9
                if silent and not host.lost:
                    host.lost = True
                    host.losses += 1
                    log.warning("camera host %s lost (silent for %.1f s)", host.name, self.z.lost_after_s)

    def _on_status(self, sample: zenoh.Sample) -> None:
        now = self.clock()
        msg = self._decoder.decode(sample.payload.to_bytes())
        if not isinstance(msg, StatusMessage):
            return
        with self.lock:
            host = self.hosts.get(msg.host)
            if host is None:
                return  # a camera host of this rig whose cameras this solver host does not use
            self.seen(host, msg.run_id, now)
            host.status = msg

    def _clock_loop(self) -> None:
        key = {h: clock_key(self.z.rig, h) for h in self.hosts}
        while not self._stop.wait(self.z.clock_period_s):
            for name, host in self.hosts.items():
                if self._stop.is_set() or self.session is None:
                    return
                self._round_trip(host, key[name])
            self.check_lost(self.clock())

    def _round_trip(self, host: RemoteHost, key: str) -> None:
        assert self.session is not None
        t0 = self.clock()
        try:
            replies = self.session.get(key, timeout=self.z.clock_timeout_s)
            reply = next(iter(replies), None)
        except zenoh.ZError:
            reply = None
        t2 = self.clock()
        with self.lock:
            if reply is None or reply.ok is None:
                host.unanswered += 1
                return
            msg = Decoder().decode(reply.ok.payload.to_bytes())
            if not isinstance(msg, ClockMessage) or msg.host != host.name:
                host.rejected["clock_reply"] += 1
                return
            self.seen(host, msg.run_id, t2)
            host.estimator.add(t0, msg.now_ns, t2)
            host.round_trips += 1

    def offset_ns(self, host: RemoteHost, run_id: int, now: int) -> int | None:
        """``host``'s clock - ours for frames of run ``run_id`` (None: not known yet). Under the lock."""
        if host.run_id != run_id:
            return None
        e = host.estimator.estimate(now)
        return None if e is None else e.offset_ns

    def status(self) -> dict[str, Any]:
        """Per camera host, for /status ``remote_hosts``."""
        now = self.clock()
        self.check_lost(now)
        out: dict[str, Any] = {}
        with self.lock:
            for name, h in self.hosts.items():
                e = h.estimator.estimate(now)
                out[name] = {
                    "lost": h.lost,
                    "last_seen_s": None if h.last_seen_ns is None else round((now - h.last_seen_ns) / 1e9, 3),
                    "run_id": None if h.run_id is None else f"{h.run_id:016x}",
                    "joins": h.joins, "losses": h.losses, "restarts": h.restarts,
                    "clock_offset_ms": None if e is None else round(e.offset_ns / 1e6, 4),
                    "clock_uncertainty_ms": None if e is None else round(e.uncertainty_ns / 1e6, 4),
                    "clock_rtt_ms": None if e is None else round(e.rtt_ns / 1e6, 4),
                    "round_trips": h.round_trips, "unanswered": h.unanswered,
                    "cameras": None if h.status is None else {
                        c.name: {"frames": c.frames, "up": c.up} for c in h.status.cameras},
                    "uptime_s": None if h.status is None else round(h.status.uptime_s, 3),
                }  # fmt: skip
        if self.error:
            out["error"] = self.error
        return out


class ZenohKeypointSource:
    """One remote camera's detections, from its camera host over Zenoh (see the module docstring).

    Parameters
    ----------
    camera : int
        The camera's index in the rig.
    name, host : str
        The camera's and its camera host's names.
    size : (width, height)
        The calibrated image size the host must report.
    n_kp : int
        Keypoints per person the rig's detector format has.
    latency_ns : int
        The scheduler's fixed latency: a frame older than this on arrival is late.
    """

    def __init__(
        self, camera: int, name: str, host: str, rig: RemoteRig, size: tuple[int, int], n_kp: int, latency_ns: int,
        *, clock: Callable[[], int] = time.monotonic_ns,
    ) -> None:  # fmt: skip
        self.camera = camera
        self.name = name
        self.host = host
        self.rig = rig
        self.size = size
        self.n_kp = n_kp
        self.latency_ns = latency_ns
        self.clock = clock
        self.decoder = Decoder()
        self.received = 0
        self.delivered = 0
        self.dropped: Counter[str] = Counter()
        self._last: tuple[int, int] | None = None  # (run id, frame) of the last frame delivered
        self._subscribed = False
        #: (capture -> arrival, send -> arrival) of the last frames, ns on this host's clock
        self.delays: deque[tuple[int, int]] = deque(maxlen=4096)

    async def run(self, sink: KeypointSink) -> None:
        loop = asyncio.get_running_loop()
        session = await loop.run_in_executor(None, self.rig.start)

        def on_sample(sample: zenoh.Sample) -> None:  # a Zenoh thread: stamp now, hand over to the loop
            arrival = self.clock()
            data = sample.payload.to_bytes()
            with contextlib.suppress(RuntimeError):  # the loop closed: the daemon is gone
                loop.call_soon_threadsafe(self.receive, sink, data, arrival)

        try:
            subscriber = session.declare_subscriber(detections_key(self.rig.z.rig, self.name), on_sample)
        except zenoh.ZError as exc:
            raise DeviceError(f"camera {self.name}: zenoh subscriber: {exc}") from None
        self._subscribed = True
        try:
            await asyncio.Future()  # until cancelled
        finally:
            self._subscribed = False
            with contextlib.suppress(zenoh.ZError):
                subscriber.undeclare()  # type: ignore[no-untyped-call]

    def receive(self, sink: KeypointSink, data: bytes, arrival_ns: int) -> None:
        """One message (on the event loop): delivered to ``sink`` or dropped and counted."""
        self.received += 1
        msg = self.decoder.decode(data)
        if not isinstance(msg, DetectionsMessage):
            if msg is not None:
                self.dropped["not_detections"] += 1
            return
        reason = self._check(msg)
        if reason is None:
            with self.rig.lock:
                host = self.rig.hosts[self.host]
                self.rig.seen(host, msg.run_id, arrival_ns)
                offset = self.rig.offset_ns(host, msg.run_id, arrival_ns)
            if offset is None:
                reason = "unsynced"
            else:
                capture = msg.capture_ns - offset
                if self._last is not None and self._last[0] == msg.run_id and msg.frame <= self._last[1]:
                    reason = "duplicate" if msg.frame == self._last[1] else "out_of_order"
                elif arrival_ns - capture > self.latency_ns:
                    reason = "late"
        if reason is not None:
            self.dropped[reason] += 1
            return
        self._last = (msg.run_id, msg.frame)
        self.delays.append((arrival_ns - capture, arrival_ns - (msg.sent_ns - offset)))  # type: ignore[operator]
        self.delivered += 1
        sink(self.camera, capture, msg.detections, arrival_ns)

    def _check(self, msg: DetectionsMessage) -> str | None:
        if msg.camera != self.name or msg.host != self.host:
            return "wrong_camera"
        if (msg.width, msg.height) != self.size:
            return "size"
        if msg.detections.keypoints.shape[1] != self.n_kp:
            return "keypoints"
        return None

    def open_state(self) -> OpenState:
        if self.rig.error:
            return OpenState("failed", self.rig.error)
        return OpenState("open" if self._subscribed else "opening", "")

    def status(self) -> dict[str, Any]:
        delays = np.array(self.delays, dtype=np.float64).reshape(-1, 2) / 1e6

        def pct(col: int, q: float) -> float | None:
            return round(float(np.percentile(delays[:, col], q)), 3) if len(delays) else None

        with self.rig.lock:
            lost = self.rig.hosts[self.host].lost
        return {
            "name": self.name, "kind": "zenoh", "host": self.host, "host_lost": lost,
            "received": self.received, "delivered": self.delivered, "dropped": dict(self.dropped),
            "decode_rejected": dict(self.decoder.rejected),
            "capture_to_arrival_ms": {"p50": pct(0, 50), "p95": pct(0, 95)},
            "hop_ms": {"p50": pct(1, 50), "p95": pct(1, 95)},
        }  # fmt: skip
