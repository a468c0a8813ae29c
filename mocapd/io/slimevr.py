"""UDP adapter of the SlimeVR server (protocol: :mod:`mocapd.protocols.slimevr_server`): mocapd receives SlimeVR
trackers as their server does.

Binds ``127.0.0.1:6969`` by default; trackers on the local network need ``host`` set to this machine's address or
``"0.0.0.0"`` explicitly (they find a server by broadcasting their handshake to port 6969). Each datagram is
stamped with ``time.monotonic_ns()`` on arrival and fed to the pure server; a tick every ``tick_s`` sends
heartbeats and pings, times out silent trackers and holds quiet sensors. Every orientation becomes an
:class:`~mocapd.io.xsens_serial.ImuSample` in the tracker's +Z-up frame, treated as ENU (its heading is the
tracker's own; calibration and heading correction take care of it), without a device clock: the buffer time is
the arrival time. Send errors are counted, never raised.

**A receive thread.** A suit of trackers sends thousands of datagrams a second, and the kernel keeps only as many
as the socket's receive buffer holds (on a stock kernel ``net.core.rmem_max`` caps it at 208 KiB, a few hundred
small datagrams: each costs its buffer ~1 KiB of accounting). Read on the event loop, they wait while it solves a
tick, and on a busy machine a tick can take long enough that the kernel drops the rest (16 % of an emulated
suit's datagrams at load 6 before this thread). So the socket is read by a thread of its own
(``mocapd-slimevr-rx``), which only stamps each datagram and queues it; the event loop hands the queue to the
server in batches. The thread reads many datagrams per wake-up with ``recvmmsg`` (:mod:`mocapd.io.recvmmsg`), so it
needs the interpreter lock once per batch rather than once per datagram (a thread waiting for the lock gets it
back from a computing thread only every ``sys.getswitchinterval()``, 5 ms: one datagram each time would be 200 a
second). ``tools/bench_slimevr_loss.py`` measures the loss with 16 trackers at 100 Hz on a loaded machine, against
the event-loop reader (``receive_thread=False``) in the same run.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import logging
import os
import socket
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from mocapd.errors import DeviceError
from mocapd.io import ports
from mocapd.io.device_state import OpenState
from mocapd.io.recvmmsg import BatchReader
from mocapd.io.rejections import Rejections
from mocapd.io.xsens_serial import ImuSample
from mocapd.protocols.mtdata2 import CoordFrame
from mocapd.protocols.slimevr import PORT
from mocapd.protocols.slimevr_server import (
    Address,
    SensorSample,
    ServerOptions,
    SlimeVrServer,
    TrackerConnected,
    TrackerEvicted,
    TrackerGesture,
    TrackerRefused,
    TrackerTimedOut,
)

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class SlimeVrConfig:
    """``[imu.slimevr]``: mocapd as the SlimeVR server of SlimeVR trackers (UDP)."""

    enabled: bool = False
    host: str = "127.0.0.1"
    """Listening address: loopback by default; trackers on the network need this machine's address or "0.0.0.0"."""
    port: int = PORT
    assignment: dict[str, str] = field(default_factory=dict)
    """``"<MAC>/<sensor index>"`` -> bone (part of the merged IMU assignment)."""


class _ServerProtocol(asyncio.DatagramProtocol):
    def __init__(self, owner: SlimeVrListener) -> None:
        self._owner = owner

    def datagram_received(self, data: bytes, addr: tuple[str | Any, ...]) -> None:
        self._owner.received(data, (str(addr[0]), int(addr[1])))

    def error_received(self, exc: Exception) -> None:  # an ICMP error for an earlier send (tracker gone)
        self._owner.send_errors[type(exc).__name__] += 1


RCVBUF = 1 << 20
"""Receive buffer asked for (bytes; the kernel caps it at ``net.core.rmem_max`` and doubles it for bookkeeping)."""
INBOX_LIMIT = 1 << 16
"""Datagrams the receive thread holds for the event loop at most (40 s of 16 trackers at 100 Hz): beyond, the
oldest are dropped and counted (``inbox_dropped``), so a stopped event loop cannot grow the daemon."""
BATCH = 64
"""Datagrams read per wake-up of the receive thread at most."""
EVICTION_LOG_INTERVAL_NS = 10_000_000_000
"""Evictions of idle trackers are said at most once per this (with the count so far)."""
DRAIN_SLICE = 64
"""Datagrams handed to the server per event-loop callback at most (the rest in the next one)."""
DRAIN_BUDGET_NS = 2_000_000
"""Work per event-loop callback before the rest waits for the next one (a datagram is never cut)."""


class SlimeVrListener:
    """The SlimeVR server socket; samples go to ``on_sample``. ``await start()``, then ``await run()`` until
    :meth:`stop`; :meth:`close` at the end.

    ``receive_thread=False`` reads the socket on the event loop instead (the reader before the receive thread, kept
    as the benchmark's baseline); ``rcvbuf`` is the receive buffer asked for.
    """

    def __init__(
        self,
        on_sample: Callable[[ImuSample], None],
        *,
        host: str = "127.0.0.1",
        port: int = PORT,
        options: ServerOptions | None = None,
        clock: Callable[[], int] = time.monotonic_ns,
        tick_s: float = 0.01,
        receive_thread: bool = True,
        rcvbuf: int = RCVBUF,
    ) -> None:
        self.host = host
        self.port = port
        self.server = SlimeVrServer(options)
        self.tick_s = tick_s
        self.receive_thread = receive_thread
        self.rcvbuf = rcvbuf
        self.send_errors: Counter[str] = Counter()
        self.receive_errors: Counter[str] = Counter()
        #: what the server refused, logged at most every 10 s (the counts are also in the server's counters)
        self.rejections = Rejections("slimevr", log, clock=clock)
        self._on_sample = on_sample
        self._said: set[str] = set()  # sensors whose first sample was logged
        self._next_eviction_log_ns: int | None = None
        self._clock = clock
        self._transport: asyncio.DatagramTransport | None = None
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._inbox: deque[tuple[bytes, Address, int]] = deque()
        self._wake_pending = False
        self._closing = False
        #: called with (what, sensor ids of the tracker) when a wearer asks a tracker for a heading reset
        self.on_gesture: Callable[[str, list[str]], None] | None = None
        self.inbox_dropped = 0
        self.batches = 0
        self.largest_batch = 0
        self._bound = False
        self._bind_error = ""
        self._stop = asyncio.Event()

    async def start(self) -> int:
        """Bind (and start the receive thread); returns the bound port (useful with port 0)."""
        loop = asyncio.get_running_loop()
        self._loop = loop
        try:
            if self.receive_thread:
                sock = _bind(self.host, self.port, self.rcvbuf)
            else:
                transport, _ = await loop.create_datagram_endpoint(
                    lambda: _ServerProtocol(self), local_addr=(self.host, self.port)
                )
                sock = transport.get_extra_info("socket")
                with contextlib.suppress(OSError):  # a burst of a dozen trackers must survive a busy event loop
                    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, self.rcvbuf)
                self._transport = transport
        except OSError as exc:
            self._bind_error = "slimevr: " + ports.bind_failure("[imu.slimevr] port", self.host, self.port, exc, "udp")
            raise DeviceError(self._bind_error) from None
        self.port = int(sock.getsockname()[1])
        if self.receive_thread:
            self._sock = sock
            self._thread = threading.Thread(target=self._receive, args=(sock,), name="mocapd-slimevr-rx", daemon=True)
            self._thread.start()
        self._bound = True
        return self.port

    def open_state(self) -> OpenState:
        """Whether the socket has been bound (what the daemon waits for before READY)."""
        if self._bound:
            return OpenState("open", "")
        return OpenState("failed", self._bind_error) if self._bind_error else OpenState("opening", "")

    async def run(self) -> None:
        """Tick until :meth:`stop` (heartbeats, time-outs, held orientations); it ends within ``tick_s`` of it.

        A plain sleep between ticks: ``wait_for`` on the stop event made and cancelled a task every 10 ms, ~18 ms
        of the event loop's CPU a second with no tracker at all (issue 45)."""
        while not self._stop.is_set():
            inbox = self._inbox  # a backlog still being handed over in slices: its trackers are not silent
            self.server.tick(self._clock(), inbox[0][2] if inbox else None)
            self._flush()
            await asyncio.sleep(self.tick_s)

    def stop(self) -> None:
        self._stop.set()

    def close(self) -> None:
        self._stop.set()
        self._closing = True
        if self._thread is not None:
            self._thread.join(1.0)  # it wakes at least every RECEIVE_TIMEOUT_S to see _closing
            self._thread = None
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        if self._transport is not None:
            self._transport.close()
            self._transport = None

    # ------------------------------------------------------------------------------------------ receive thread
    def _receive(self, sock: socket.socket) -> None:
        """The receive thread: read datagrams in batches, stamp them, queue them for the event loop."""
        reader = BatchReader(sock, BATCH)
        # The kernel's arrival times are CLOCK_MONOTONIC: used unless a test runs the listener on a clock of its own.
        kernel_time = self._clock is time.monotonic_ns
        while not self._closing:
            try:
                batch = reader.read(RECEIVE_TIMEOUT_S)
            except OSError as exc:  # an ICMP error for an earlier send, or the socket closed under us
                if self._closing:
                    break
                self.receive_errors[errno.errorcode.get(exc.errno or 0, type(exc).__name__)] += 1
                continue
            if not batch:
                continue
            now = self._clock()
            inbox = self._inbox
            inbox.extend((data, address, t if kernel_time and t is not None else now) for data, address, t in batch)
            over = len(inbox) - INBOX_LIMIT
            for _ in range(max(0, over)):
                inbox.popleft()
                self.inbox_dropped += 1
            if not self._wake_pending:
                self._wake_pending = True
                loop = self._loop
                if loop is None or loop.is_closed():
                    break
                try:
                    loop.call_soon_threadsafe(self._drain)
                except RuntimeError:  # the loop closed between the check and the call: nobody listens
                    break

    def _drain(self) -> None:
        """On the event loop: hand queued datagrams to the server, then send the replies; at most
        :data:`DRAIN_SLICE` datagrams or :data:`DRAIN_BUDGET_NS` of work a call, then the rest in another call
        scheduled behind whatever else is ready (the output tick): a swarm's burst of 128 bundles of 128 sensor
        infos (~0.9 ms each) held the loop for a tenth of a second in one call, every ten seconds (issue 45)."""
        self._wake_pending = False
        inbox = self._inbox
        self.batches += 1
        self.largest_batch = max(self.largest_batch, len(inbox))  # the backlog found
        end = time.perf_counter_ns() + DRAIN_BUDGET_NS
        for _ in range(min(len(inbox), DRAIN_SLICE)):
            data, address, t_ns = inbox.popleft()
            self._receive_one(data, address, t_ns)
            if time.perf_counter_ns() > end:
                break
        self._flush()
        if inbox and not self._wake_pending and self._loop is not None:
            self._wake_pending = True
            self._loop.call_soon(self._drain)

    def received(self, data: bytes, address: Address) -> None:
        """One datagram from ``address``, received now (the event-loop reader's datagram protocol calls this)."""
        self._receive_one(data, address, self._clock())
        self._flush()

    def _receive_one(self, data: bytes, address: Address, t_ns: int) -> None:
        c = self.server.counters
        before = (c.bad_datagrams, c.unknown_source, c.unannounced_sensor)
        self.server.receive_datagram(data, address, t_ns)
        where = f"{len(data)} bytes from {address[0]}:{address[1]}"
        for reason, n0, n1 in zip(("bad datagram", "unknown source", "unannounced sensor"), before,
                                  (c.bad_datagrams, c.unknown_source, c.unannounced_sensor), strict=True):  # fmt: skip
            self.rejections.reject(reason, where, n1 - n0)

    def _flush(self) -> None:
        for event in self.server.events_received():
            if isinstance(event, SensorSample):
                if event.sensor not in self._said:  # the id a user assigns a bone to, said once it streams
                    self._said.add(event.sensor)
                    log.info('slimevr: sensor "%s" streaming (the key that gives it a bone in '
                             "[imu.slimevr.assignment])", event.sensor, extra={"repeat_key": event.sensor})  # fmt: skip
                self._on_sample(
                    ImuSample(event.sensor, event.host_ns, None, None, event.quat, event.acc, CoordFrame.ENU)
                )
            elif isinstance(event, TrackerConnected):
                what = "reconnected" if event.handover else "connected"
                log.info("slimevr: tracker %s %s from %s:%d", event.key, what, *event.address,
                         extra={"repeat_key": event.key})  # fmt: skip
            elif isinstance(event, TrackerTimedOut):
                log.warning("slimevr: tracker %s timed out", event.key, extra={"repeat_key": event.key})
            elif isinstance(event, TrackerEvicted):
                self._log_eviction(event)
            elif isinstance(event, TrackerRefused):
                self.rejections.reject("tracker table full", "handshake from {}:{}".format(*event.address))
            elif isinstance(event, TrackerGesture):
                tracker = self.server.trackers.get(event.key)
                sensors = [event.sensor] if event.sensor else [] if tracker is None else [
                    tracker.sensor_id(i) for i in tracker.sensors]  # fmt: skip
                log.info("slimevr: %s on tracker %s", event.kind, event.key)
                if self.on_gesture is not None:
                    self.on_gesture(f"{event.kind} on tracker {event.key}", sensors)
        transport, sock = self._transport, self._sock
        for data, address in self.server.datagrams_to_send():
            try:
                if sock is not None:
                    sock.sendto(data, socket.MSG_DONTWAIT, address)  # never waits: a full buffer is a counted error
                elif transport is not None:
                    transport.sendto(data, address)
                else:
                    self.send_errors["not_started"] += 1
            except OSError as exc:
                self.send_errors[errno.errorcode.get(exc.errno or 0, "OSError")] += 1

    def _log_eviction(self, event: TrackerEvicted) -> None:
        """One line for the first eviction and then at most one per :data:`EVICTION_LOG_INTERVAL_NS`, whatever MACs
        a swarm invents (a swarm churning through the table evicts one of its own every few seconds); the count is
        in /status (``evicted_trackers``)."""
        now = self._clock()
        if self._next_eviction_log_ns is not None and now < self._next_eviction_log_ns:
            return
        self._next_eviction_log_ns = now + EVICTION_LOG_INTERVAL_NS
        log.warning("slimevr: tracker %s (%s:%d, %d sensors) evicted for a newcomer: no rotation from it for %.1f s "
                    "while the table was full; %d evicted so far (imu.slimevr.evicted_trackers in /status)",
                    event.key, *event.address, event.sensors, event.idle_ns / 1e9,
                    self.server.counters.evicted_trackers)  # fmt: skip

    def status(self) -> dict[str, Any]:
        """Listening address, counters and trackers for /status; per tracker ``loss_percent``, the share of its
        datagrams that never arrived (packet numbers skipped), and for the socket the datagrams the kernel dropped
        because its receive buffer was full (``kernel_drops``, Linux)."""
        st = self.server.status()
        for t in st["trackers"]:
            sent = t["packets"] + t["lost"]
            t["loss_percent"] = round(100.0 * t["lost"] / sent, 3) if sent else 0.0
        sock = self._sock if self._sock is not None else (
            self._transport.get_extra_info("socket") if self._transport is not None else None)  # fmt: skip
        receiver = {
            "thread": self.receive_thread, "kernel_drops": None if sock is None else udp_drops(sock),
            "receive_buffer_bytes": None if sock is None else _rcvbuf(sock), "inbox_dropped": self.inbox_dropped,
            "batches": self.batches, "largest_batch": self.largest_batch, "errors": dict(self.receive_errors),
        }  # fmt: skip
        return {"listen": f"{self.host}:{self.port}", "send_errors": dict(self.send_errors), "receiver": receiver,
                **st}  # fmt: skip


RECEIVE_TIMEOUT_S = 0.1
"""The receive thread looks at least this often whether it should stop."""


def _bind(host: str, port: int, rcvbuf: int) -> socket.socket:
    """A bound, blocking UDP socket for the receive thread (with a time-out, so that it sees a stop)."""
    family, _, _, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)[0]
    sock = socket.socket(family, socket.SOCK_DGRAM)
    try:
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        sock.bind(address)
    except OSError:
        sock.close()
        raise
    return sock


def _rcvbuf(sock: socket.socket) -> int | None:
    try:
        return int(sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF))
    except OSError:
        return None


def udp_drops(sock: socket.socket) -> int | None:
    """Datagrams the kernel dropped for ``sock`` (its receive buffer full), from ``/proc/net/udp[6]``; None where
    the kernel does not say (not Linux, or the socket closed)."""
    try:
        inode = os.fstat(sock.fileno()).st_ino
    except (OSError, ValueError):
        return None
    for table in ("/proc/net/udp", "/proc/net/udp6"):
        try:
            with open(table, encoding="ascii") as fh:
                next(fh, None)  # the header
                for line in fh:
                    fields = line.split()
                    if len(fields) >= 13 and fields[9] == str(inode):
                        return int(fields[12])
        except (OSError, ValueError):
            continue
    return None
