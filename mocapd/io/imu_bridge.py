"""UDP listener for the IMU bridge input (format: :mod:`mocapd.protocols.imu_bridge`).

Binds 127.0.0.1 by default (the forwarding script runs on the same machine); every record becomes an
:class:`~mocapd.io.xsens_serial.ImuSample` stamped with ``time.monotonic_ns()`` on arrival. The device time is
converted to 10 kHz ticks so that the same clock mapping as for serial devices applies.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from mocapd.errors import ConfigError, DeviceError
from mocapd.io import ports
from mocapd.io.device_state import OpenState
from mocapd.io.rejections import Rejections
from mocapd.io.xsens_serial import ImuSample
from mocapd.protocols.imu_bridge import decode

log = logging.getLogger(__name__)

DEFAULT_PORT = 9773  # not 9763: that is MVN network streaming, which mocapd sends
_TICK_HZ = 10_000


@dataclass(slots=True)
class BridgeStats:
    datagrams: int = 0
    records: int = 0
    """Records accepted (each became a sample)."""
    rejected: int = 0
    """Items rejected (a datagram that is not msgpack counts as one); per reason in ``rejections``."""
    rejections: Rejections = field(default_factory=lambda: Rejections("imu bridge", log))


class _BridgeProtocol(asyncio.DatagramProtocol):
    def __init__(self, on_sample: Callable[[ImuSample], None], stats: BridgeStats, clock: Callable[[], int]) -> None:
        self._on_sample = on_sample
        self._stats = stats
        self._clock = clock

    def datagram_received(self, data: bytes, addr: tuple[str | object, ...]) -> None:
        now = self._clock()
        decoded = decode(data)
        st = self._stats
        st.datagrams += 1
        for reason in decoded.rejected:
            st.rejected += 1
            st.rejections.reject(reason, f"datagram of {len(data)} bytes from {addr[0]}:{addr[1]}")
        for r in decoded.records:
            # |t| <= 2^32 s (checked by the decoder): the tick count is exact and never overflows
            ticks = round(r.device_time_s * _TICK_HZ) & 0xFFFFFFFF
            self._on_sample(ImuSample(r.sensor, now, ticks, r.packet_counter, r.quat, r.acc, r.frame))
            st.records += 1


class ImuBridgeListener:
    """Receives bridge datagrams until closed."""

    def __init__(
        self,
        on_sample: Callable[[ImuSample], None],
        *,
        host: str = "127.0.0.1",
        port: int = DEFAULT_PORT,
        clock: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        if host not in ("127.0.0.1", "::1", "localhost"):
            raise ConfigError(f"imu.bridge.host={host!r}: the bridge listens on loopback only")
        self.host = host
        self.port = port
        self.stats = BridgeStats()
        self._on_sample = on_sample
        self._clock = clock
        self._transport: asyncio.DatagramTransport | None = None
        self._bind_error = ""

    def open_state(self) -> OpenState:
        """Whether the socket has been bound (what the daemon waits for before READY)."""
        if self._transport is not None:
            return OpenState("open", "")
        return OpenState("failed", self._bind_error) if self._bind_error else OpenState("opening", "")

    async def start(self) -> int:
        """Bind and start receiving; returns the bound port (useful with port 0)."""
        loop = asyncio.get_running_loop()
        try:
            transport, _ = await loop.create_datagram_endpoint(
                lambda: _BridgeProtocol(self._on_sample, self.stats, self._clock),
                local_addr=(self.host, self.port),
            )
        except OSError as exc:
            failure = ports.bind_failure("[imu.bridge] port", self.host, self.port, exc, "udp")
            self._bind_error = f"imu bridge: {failure}"
            raise DeviceError(self._bind_error) from None
        self._transport = transport
        sockname = transport.get_extra_info("sockname")
        self.port = int(sockname[1])
        return self.port

    def close(self) -> None:
        if self._transport is not None:
            self._transport.close()
            self._transport = None
