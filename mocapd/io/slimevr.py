"""UDP adapter of the SlimeVR server (protocol: :mod:`mocapd.protocols.slimevr_server`): mocapd receives SlimeVR
trackers as their server does.

Binds ``127.0.0.1:6969`` by default; trackers on the local network need ``host`` set to this machine's address or
``"0.0.0.0"`` explicitly (they find a server by broadcasting their handshake to port 6969). Each datagram is
stamped with ``time.monotonic_ns()`` on arrival and fed to the pure server; a tick every ``tick_s`` sends
heartbeats and pings, times out silent trackers and holds quiet sensors. Every orientation becomes an
:class:`~mocapd.io.xsens_serial.ImuSample` in the tracker's +Z-up frame, treated as ENU (its heading is the
tracker's own; calibration and heading correction take care of it), without a device clock: the buffer time is
the arrival time. Send errors are counted, never raised.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import logging
import socket
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from mocapd.errors import DeviceError
from mocapd.io import ports
from mocapd.io.device_state import OpenState
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


class SlimeVrListener:
    """The SlimeVR server socket; samples go to ``on_sample``. ``await start()``, then ``await run()`` until
    :meth:`stop`."""

    def __init__(
        self,
        on_sample: Callable[[ImuSample], None],
        *,
        host: str = "127.0.0.1",
        port: int = PORT,
        options: ServerOptions | None = None,
        clock: Callable[[], int] = time.monotonic_ns,
        tick_s: float = 0.01,
    ) -> None:
        self.host = host
        self.port = port
        self.server = SlimeVrServer(options)
        self.tick_s = tick_s
        self.send_errors: Counter[str] = Counter()
        #: what the server refused, logged at most every 10 s (the counts are also in the server's counters)
        self.rejections = Rejections("slimevr", log, clock=clock)
        self._on_sample = on_sample
        self._clock = clock
        self._transport: asyncio.DatagramTransport | None = None
        self._bound = False
        self._bind_error = ""
        self._stop = asyncio.Event()

    async def start(self) -> int:
        """Bind; returns the bound port (useful with port 0)."""
        loop = asyncio.get_running_loop()
        try:
            transport, _ = await loop.create_datagram_endpoint(
                lambda: _ServerProtocol(self), local_addr=(self.host, self.port)
            )
        except OSError as exc:
            self._bind_error = "slimevr: " + ports.bind_failure("[imu.slimevr] port", self.host, self.port, exc, "udp")
            raise DeviceError(self._bind_error) from None
        self._transport = transport
        self._bound = True
        sock = transport.get_extra_info("socket")
        with contextlib.suppress(OSError):  # a burst of a dozen trackers must survive a busy event loop: ask for
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)  # 1 MiB (the kernel caps it at rmem_max)
        self.port = int(transport.get_extra_info("sockname")[1])
        return self.port

    def open_state(self) -> OpenState:
        """Whether the socket has been bound (what the daemon waits for before READY)."""
        if self._bound:
            return OpenState("open", "")
        return OpenState("failed", self._bind_error) if self._bind_error else OpenState("opening", "")

    async def run(self) -> None:
        """Tick until :meth:`stop` (heartbeats, time-outs, held orientations)."""
        while not self._stop.is_set():
            self.server.tick(self._clock())
            self._flush()
            with contextlib.suppress(TimeoutError):  # the tick period passed without a stop
                await asyncio.wait_for(self._stop.wait(), self.tick_s)

    def stop(self) -> None:
        self._stop.set()

    def close(self) -> None:
        self._stop.set()
        if self._transport is not None:
            self._transport.close()
            self._transport = None

    def received(self, data: bytes, address: Address) -> None:
        """One datagram from ``address`` (called by the datagram protocol)."""
        c = self.server.counters
        before = (c.bad_datagrams, c.unknown_source, c.unannounced_sensor)
        self.server.receive_datagram(data, address, self._clock())
        where = f"{len(data)} bytes from {address[0]}:{address[1]}"
        for reason, n0, n1 in zip(("bad datagram", "unknown source", "unannounced sensor"), before,
                                  (c.bad_datagrams, c.unknown_source, c.unannounced_sensor), strict=True):  # fmt: skip
            self.rejections.reject(reason, where, n1 - n0)
        self._flush()

    def _flush(self) -> None:
        for event in self.server.events_received():
            if isinstance(event, SensorSample):
                self._on_sample(
                    ImuSample(event.sensor, event.host_ns, None, None, event.quat, event.acc, CoordFrame.ENU)
                )
            elif isinstance(event, TrackerConnected):
                what = "reconnected" if event.handover else "connected"
                log.info("slimevr: tracker %s %s from %s:%d", event.key, what, *event.address)
            elif isinstance(event, TrackerTimedOut):
                log.warning("slimevr: tracker %s timed out", event.key)
            elif isinstance(event, TrackerRefused):
                self.rejections.reject("tracker table full", "handshake from {}:{}".format(*event.address))
        transport = self._transport
        for data, address in self.server.datagrams_to_send():
            if transport is None:
                self.send_errors["not_started"] += 1
                continue
            try:
                transport.sendto(data, address)
            except OSError as exc:
                self.send_errors[errno.errorcode.get(exc.errno or 0, "OSError")] += 1

    def status(self) -> dict[str, Any]:
        """Listening address, counters and trackers for /status."""
        return {"listen": f"{self.host}:{self.port}", "send_errors": dict(self.send_errors), **self.server.status()}
