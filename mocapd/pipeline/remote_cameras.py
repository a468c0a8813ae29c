"""The solver host's side of camera hosts: ``source = "zenoh"`` cameras as keypoint sources.

One :class:`RemoteRig` per daemon owns the Zenoh session (opened when the first remote camera starts), the camera
hosts' status subscription and a thread that times a clock round trip to each host every ``clock_period_s`` (a
Zenoh query answered by the host's monotonic clock, :mod:`mocapd.core.clock_offset`). Each
:class:`ZenohKeypointSource` subscribes to its camera's detections and hands each frame to the daemon's sink like a
local camera's, at the capture time mapped to this host's clock (remote time - estimated offset): the same
``DetectionTimeline`` then takes it.

Dropped and counted per camera, never delivered: bytes the decoder refuses (by reason), a frame of another camera
or host, a size or keypoint count that is not the rig's, a frame of a run that is not the host's current one
(``run_id``), a frame before the host's clock offset is known (``unsynced``), a capture time ahead of its arrival
by more than the offset's error bound and :data:`FUTURE_TOLERANCE_NS` (``future``: an hour-ahead stamp was
delivered, issue 34), a frame that arrives after its instant was solved (``late``: capture older than
``latency_s``), a frame number that repeats or is behind the last one of that host run (``duplicate``,
``out_of_order``) or jumps absurdly far (``frame_jump``: one frame numbered 2⁶³−1 locked a camera out until its
host restarted; :class:`~mocapd.protocols.sequence.SequenceNumbers` follows a real jump after two frames agree).

Who speaks for a host (issue 34; who may connect at all is ``[zenoh]``'s credentials, :mod:`mocapd.io.zenoh_link`):
a host's **run id** is taken only from status messages published on that host's own status key (its name in the
message and in the key must agree); a different run id replaces the current one only once the current run's
status has been silent for ``lost_after_s`` (a restart: a host takes longer than that to start again), otherwise
it is refused (``run_conflict``): a second peer publishing status for a host cannot flip it back and forth, even
when the real host's status comes late on a loaded machine (with two status periods as the limit, a soak on a
machine at load 20 saw the run flip 40 times in 30 minutes). Detections and clock
replies are accepted only with the host's current run id. A **clock reply** counts only if it is plausible: the
offset it gives must agree with the host's latest status message (sent at ``S`` on its clock, received at ``A`` on
ours: the offset lies in ``[S - A, S - A + lost_after_s]``), and every reply to one query is read: replies that
disagree (two peers answering for one host) are all refused (``clock_conflict``), and after the first accepted
reply of a run, replies from another Zenoh session (``replier_id``) are refused (``clock_other_peer``). What is
refused is counted per host (``rejected`` in ``/status``).

With ``[zenoh] identities`` (off loopback, or once one is named, the schema requires one per camera host) the
session admits a host's status, its cameras' detections and its clock replies from that host's authenticated
identity alone (Zenoh's access control, :func:`mocapd.io.zenoh_link.access_control`): a peer with valid
credentials of its own cannot publish as another host; ``/status`` shows each host's ``identity`` and
(``zenoh_links``) the identities of the links up.

A host not heard from (status, detections or clock replies) for ``lost_after_s`` is shown lost; its cameras deliver
nothing, so their timelines go stale and they drop out of the solve; when it is heard again it rejoins (a
restarted host has a new run id: its frame numbers and clock offset start again). A host never heard from
``lost_after_s`` after the session opened is said once (:meth:`RemoteRig.unheard_line`, issue 45): Zenoh reports
nothing of a link it refuses (a certificate ``tls_root_ca`` did not sign, a wrong password), so without that line
a camera host refused by TLS was as silent on this side as on its own; the line names the links that are up, and
those from identities ``[zenoh.identities]`` does not give any host.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import zenoh

from mocapd.core.clock_offset import ClockOffsetEstimator
from mocapd.errors import DeviceError, MocapdError
from mocapd.io.device_state import OpenState
from mocapd.io.loop_mailbox import loop_mailbox
from mocapd.io.zenoh_link import (
    ZenohConfig,
    clock_key,
    detections_key,
    link_identities,
    open_session,
    status_key,
)
from mocapd.pipeline.keypoint_source import KeypointSink
from mocapd.protocols.remote import ClockMessage, Decoder, DetectionsMessage, StatusMessage
from mocapd.protocols.sequence import SequenceNumbers

log = logging.getLogger(__name__)

FUTURE_TOLERANCE_NS = 20_000_000
"""A capture time may lie this far (beyond the clock offset's error bound) after its arrival before it is refused
as ``future``: the two hosts' clock ticks and the estimate's own rounding, not a plausible delay."""
MAX_FRAME_STEP = 1 << 20
"""Largest step of a camera's frame number taken as the next frame (hours of frames at any camera rate)."""
MAX_FRAME_BEHIND = 1 << 10
"""A frame number this far behind the last one is out of order; farther, a jump."""
MAX_CLOCK_REPLIES = 8
"""Replies to one clock query read (more means more than a few peers answer for one host)."""


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
    status_arrival_ns: int | None = None
    """When :attr:`status` (of the current run) arrived, on this host's clock."""
    round_trips: int = 0
    unanswered: int = 0
    rejected: Counter[str] = field(default_factory=Counter)
    clock_peer: str | None = None
    """The Zenoh session (replier id) whose clock replies the current run's offset comes from."""


class RemoteRig:
    """The Zenoh side of a solver host's remote cameras (see the module docstring)."""

    def __init__(
        self, z: ZenohConfig, hosts: list[str], *, cameras: Mapping[str, Sequence[str]] | None = None,
        clock: Callable[[], int] = time.monotonic_ns,
    ) -> None:  # fmt: skip
        self.z = z
        self.cameras = {h: list((cameras or {}).get(h, ())) for h in hosts}
        """Each host's ``source = "zenoh"`` cameras: only their detections are admitted from its identity."""
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
        self._opened_ns: int | None = None  # when the session opened: the unheard hosts' grace starts there
        self._unheard_said: set[str] = set()

    # ------------------------------------------------------------------------------------------ life cycle
    def start(self) -> zenoh.Session:
        """Open the session, subscribe to the hosts' status, start the clock thread (once; blocking)."""
        with self._start_lock:
            if self.session is not None:
                return self.session
            try:
                session = open_session(self.z, self.cameras)
            except MocapdError as exc:
                self.error = str(exc)
                raise
            self._subscribers.append(session.declare_subscriber(status_key(self.z.rig, "*"), self._on_status))
            self.session = session
            self._opened_ns = self.clock()
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
    def seen(self, host: RemoteHost, run_id: int, now: int) -> bool:
        """``host``'s status said run ``run_id`` (call under the lock): its current run, or a new one once the
        current run's status has been silent for ``lost_after_s`` (a restart: its clock offset starts over).
        False, counted as ``run_conflict``, for a different run while the current one talks."""
        if host.run_id != run_id:
            quiet_ns = self.z.lost_after_s * 1e9
            current_talks = host.status_arrival_ns is not None and now - host.status_arrival_ns <= quiet_ns
            if host.run_id is not None and current_talks:
                host.rejected["run_conflict"] += 1
                return False
            if host.run_id is not None:
                host.restarts += 1
            host.run_id = run_id
            host.estimator.reset()
            host.clock_peer = None
            host.status = None
        self.heard(host, run_id, now)
        return True

    def heard(self, host: RemoteHost, run_id: int, now: int) -> bool:
        """A detection or clock reply of run ``run_id`` from ``host`` (call under the lock): it counts as hearing
        from the host only in the host's current run (the run its status messages give)."""
        if host.run_id != run_id:
            host.rejected["run_id"] += 1
            return False
        host.last_seen_ns = now
        if host.lost:
            host.lost = False
            host.joins += 1
            log.warning("camera host %s joined (run %x)", host.name, run_id)
        return True

    def check_lost(self, now: int) -> None:
        unheard: list[str] = []
        with self.lock:
            for host in self.hosts.values():
                silent = host.last_seen_ns is None or now - host.last_seen_ns > self.z.lost_after_s * 1e9
                if silent and not host.lost:
                    host.lost = True
                    host.losses += 1
                    log.warning("camera host %s lost (silent for %.1f s)", host.name, self.z.lost_after_s)
                opened = self._opened_ns
                late = opened is not None and now - opened >= self.z.lost_after_s * 1e9
                if late and host.joins == 0 and host.name not in self._unheard_said:
                    self._unheard_said.add(host.name)
                    unheard.append(host.name)
        if unheard:  # the links are read outside the lock: Zenoh's call may take a moment
            log.warning("%s", self.unheard_line(unheard, self.links()))

    def unheard_line(self, hosts: Sequence[str], links: Sequence[str]) -> str:
        """The one line for camera hosts never heard from ``lost_after_s`` after the session opened (issue 45):
        what may keep them out (Zenoh does not say), the links up, and those of identities no host has."""
        expected = {self.z.identities[h] for h in self.hosts if h in self.z.identities}
        strangers = sorted({i for i in links if i.startswith("cert:") and expected and i not in expected})
        linked_silent = sorted(h for h in hosts if self.z.identities.get(h) in links)
        names = ", ".join(hosts)
        line = (
            f"camera host{'s' if len(hosts) > 1 else ''} {names}: not heard from {self.z.lost_after_s:g} s after "
            f"start: not running, or its link refused (TLS: a certificate tls_root_ca did not sign, or a name "
            f"[zenoh.identities] does not give it; user/password); links up: {', '.join(links) or 'none'}"
        )
        if strangers:
            line += f"; from identities [zenoh.identities] does not name: {', '.join(strangers)}"
        if linked_silent:
            line += f"; linked but silent (another [zenoh] rig name?): {', '.join(linked_silent)}"
        return line

    def _on_status(self, sample: zenoh.Sample) -> None:
        self.receive_status(str(sample.key_expr), sample.payload.to_bytes(), self.clock())

    def receive_status(self, key: str, data: bytes, now: int) -> None:
        """One message on a status key (``mocapd/<rig>/hosts/<host>/status``) received at ``now``."""
        msg = self._decoder.decode(data)
        if not isinstance(msg, StatusMessage):
            return
        with self.lock:
            host = self.hosts.get(msg.host)
            if host is None:
                return  # a camera host of this rig whose cameras this solver host does not use
            if key != status_key(self.z.rig, msg.host):  # another host's key speaking for this one
                host.rejected["status_key"] += 1
                return
            if self.seen(host, msg.run_id, now):
                host.status, host.status_arrival_ns = msg, now

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
        got: list[tuple[bytes, str | None, int]] = []  # every reply (payload, replier, arrival): not only the first
        try:
            # Every queryable of the key is asked (ALL) and every reply kept (no consolidation): by default Zenoh
            # asks the "best matching" queryable only and keeps one reply per key, so a rogue answering for a host
            # could be the only answer seen; here all answers are compared.
            replies = self.session.get(key, target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE,
                                       timeout=self.z.clock_timeout_s)  # fmt: skip
            for reply in replies:
                if reply.ok is not None and len(got) < MAX_CLOCK_REPLIES:
                    replier = getattr(reply, "replier_id", None)
                    got.append((reply.ok.payload.to_bytes(), None if replier is None else str(replier), self.clock()))
        except zenoh.ZError:
            pass
        self.clock_replies(host, t0, got)

    def clock_replies(self, host: RemoteHost, t0: int, replies: list[tuple[bytes, str | None, int]]) -> bool:
        """The replies to one clock query sent at ``t0``: (payload, replier id, arrival) each. One plausible reply
        of the host's run from its Zenoh session is a round trip; anything else is counted (module docstring)."""
        with self.lock:
            if not replies:
                host.unanswered += 1
                return False
            good: list[tuple[ClockMessage, str | None, int]] = []
            for data, replier, t2 in replies:
                reason = self._clock_reason(host, data, replier, t0, t2)
                if isinstance(reason, str):
                    host.rejected[reason] += 1
                else:
                    good.append((reason, replier, t2))
            if not good:
                return False
            lo = max(m.now_ns - t2 for m, _, t2 in good)  # each reply: offset in [now - t2, now - t0]
            hi = min(m.now_ns - t0 for m, _, _ in good)
            if len(good) > 1 and lo > hi:  # two answers for one host that cannot both be true
                host.rejected["clock_conflict"] += len(good)
                return False
            msg, replier, t2 = good[0]
            if not self.heard(host, msg.run_id, t2):
                return False
            host.clock_peer = host.clock_peer or replier
            host.estimator.add(t0, msg.now_ns, t2)
            host.round_trips += 1
            return True

    def _clock_reason(self, host: RemoteHost, data: bytes, replier: str | None, t0: int, t2: int) -> ClockMessage | str:
        """The reply's message, or why it is refused (under the lock)."""
        msg = Decoder().decode(data)
        if not isinstance(msg, ClockMessage) or msg.host != host.name:
            return "clock_reply"
        if host.run_id is None or host.status is None or host.status_arrival_ns is None:
            return "clock_before_status"  # the run id and a plausible offset come from the host's status
        if msg.run_id != host.run_id:
            return "clock_run_id"
        if host.clock_peer is not None and replier is not None and replier != host.clock_peer:
            return "clock_other_peer"
        # The status message bounds the offset: it left at S (host clock) and arrived at A (ours) at most
        # lost_after_s later, so S - A <= offset <= S - A + lost_after_s; the reply's offset lies in [now - t2,
        # now - t0]. The two must overlap (a millisecond of slack for the clocks' ticks).
        base = host.status.sent_ns - host.status_arrival_ns
        slack = 1_000_000
        if msg.now_ns - t0 < base - slack or msg.now_ns - t2 > base + self.z.lost_after_s * 1e9 + slack:
            return "clock_implausible"
        return msg

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
                    "round_trips": h.round_trips, "unanswered": h.unanswered, "rejected": dict(h.rejected),
                    "cameras": None if h.status is None else {
                        c.name: {"frames": c.frames, "up": c.up} for c in h.status.cameras},
                    "uptime_s": None if h.status is None else round(h.status.uptime_s, 3),
                    "identity": self.z.identities.get(name),
                }  # fmt: skip
        if self.error:
            out["error"] = self.error
        return out

    def links(self) -> list[str]:
        """The authenticated identities of the session's links now (:func:`~mocapd.io.zenoh_link.link_identities`)."""
        session = self.session
        if session is None:
            return []
        try:
            return link_identities(session)
        except zenoh.ZError:
            return []


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
        self._run: int | None = None  # the host run whose frame numbers :attr:`frames` follows
        self.frames = SequenceNumbers(MAX_FRAME_STEP, MAX_FRAME_BEHIND)
        self._subscribed = False
        #: (capture -> arrival, send -> arrival) of the last frames, ns on this host's clock
        self.delays: deque[tuple[int, int]] = deque(maxlen=4096)

    async def run(self, sink: KeypointSink) -> None:
        loop = asyncio.get_running_loop()
        session = await loop.run_in_executor(None, self.rig.start)
        mailbox = loop_mailbox(loop)  # the frames of every camera that arrive while the loop is busy: one wake-up

        def on_sample(sample: zenoh.Sample) -> None:  # a Zenoh thread: stamp now, hand over to the loop
            arrival = self.clock()
            data = sample.payload.to_bytes()
            mailbox.post(self.receive, sink, data, arrival)  # dropped once the loop is closed: the daemon is gone

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
        offset, bound = None, 0
        if reason is None:
            with self.rig.lock:
                host = self.rig.hosts[self.host]
                if not self.rig.heard(host, msg.run_id, arrival_ns):
                    reason = "run_id"
                else:
                    e = host.estimator.estimate(arrival_ns)
                    offset, bound = (None, 0) if e is None else (e.offset_ns, e.uncertainty_ns)
        if reason is None:
            reason = self._timing(msg, offset, bound, arrival_ns)
        if reason is None:
            reason = self._numbering(msg)
        if reason is not None:
            self.dropped[reason] += 1
            return
        assert offset is not None
        capture = msg.capture_ns - offset
        self.delays.append((arrival_ns - capture, arrival_ns - (msg.sent_ns - offset)))
        self.delivered += 1
        sink(self.camera, capture, msg.detections, arrival_ns)

    def _timing(self, msg: DetectionsMessage, offset: int | None, bound: int, arrival_ns: int) -> str | None:
        """Why a frame's capture time cannot be used (none known yet, in the future, too old), or None."""
        if offset is None:
            return "unsynced"
        capture = msg.capture_ns - offset
        if capture - arrival_ns > bound + FUTURE_TOLERANCE_NS:  # captured after it arrived: a false stamp
            return "future"
        if arrival_ns - capture > self.latency_ns:
            return "late"
        return None

    def _numbering(self, msg: DetectionsMessage) -> str | None:
        """Why a frame's number is refused (a repeat, behind, an absurd jump), or None (taken)."""
        if self._run != msg.run_id:  # a new run numbers its frames afresh
            self._run = msg.run_id
            self.frames.reset()
        verdict = self.frames.take(msg.frame)
        return {"duplicate": "duplicate", "reordered": "out_of_order", "jump": "frame_jump"}.get(verdict)

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
            "frame_resyncs": self.frames.resyncs,
            "decode_rejected": dict(self.decoder.rejected),
            "capture_to_arrival_ms": {"p50": pct(0, 50), "p95": pct(0, 95)},
            "hop_ms": {"p50": pct(1, 50), "p95": pct(1, 95)},
        }  # fmt: skip
