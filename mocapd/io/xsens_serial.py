"""An Xsens device on a serial port: open, bring up, stream, and reconnect with back-off.

The byte-level work is :class:`mocapd.protocols.xsens_session.XsensSession`; this module only opens the port
(:mod:`mocapd.io.serial_transport`), pumps bytes, stamps each read with ``time.monotonic_ns()`` and drives the
session's time-outs. Every decoded sample goes to a callback as an :class:`ImuSample`.

Failure handling:

- the port cannot be opened (not there yet, busy): retry after a back-off that doubles from
  ``reconnect_min_s`` to ``reconnect_max_s``;
- bring-up fails (no reply after ``attempts`` × ``response_timeout_s``, or device errors): same back-off, and
  :attr:`XsensSerialDevice.last_error` says which step failed and why;
- the port disappears while streaming (unplug: EIO / end of file) or stays silent for ``stall_timeout_s``:
  close, back off, reopen the same path (use a stable path such as ``/dev/serial/by-id/...``). Silence is counted
  only while mocapd was running to hear it, and what the kernel holds is read before judging: a pause of the
  whole process (SIGSTOP, a suspend) is not a stall (:mod:`mocapd.io.silence`).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from mocapd.errors import ConfigError, DeviceError, DeviceTimeout
from mocapd.io.device_state import OpenState
from mocapd.io.serial_transport import SerialTransport, create_serial_connection
from mocapd.io.silence import SilenceClock
from mocapd.protocols.awinda import AwindaConfig, SnapshotIntegrator, station_steps
from mocapd.protocols.mtdata2 import AwindaSnapshot, CoordFrame, DataId, MtData2, Precision
from mocapd.protocols.xsens_session import (
    BringUpFailed,
    DeviceInfo,
    DeviceReportedError,
    DeviceReportedWarning,
    Sample,
    State,
    Streaming,
    XsensSession,
    output_settings,
)

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class XsensPortConfig:
    """One serial Xsens device (a ``[[imu.serial]]`` entry of config.toml)."""

    path: str
    baudrate: int = 921_600
    rate_hz: int = 100
    precision: Precision = Precision.FLOAT32
    response_timeout_s: float = 0.5
    attempts: int = 3
    reconnect_min_s: float = 0.2
    reconnect_max_s: float = 5.0
    stall_timeout_s: float = 2.0

    def __post_init__(self) -> None:
        output_settings(self.rate_hz)  # validates the rate (ConfigError)
        if self.attempts < 1 or self.response_timeout_s <= 0:
            raise ConfigError(
                f"imu.serial {self.path}: attempts must be >= 1 and response_timeout_s > 0, "
                f"got {self.attempts} and {self.response_timeout_s}"
            )
        if not 0 < self.reconnect_min_s <= self.reconnect_max_s:
            raise ConfigError(
                f"imu.serial {self.path}: need 0 < reconnect_min_s <= reconnect_max_s, "
                f"got {self.reconnect_min_s} and {self.reconnect_max_s}"
            )


@dataclass(frozen=True, slots=True)
class ImuSample:
    """One IMU measurement as received.

    ``quat`` is (w, x, y, z) of the sensor in the device's global frame ``frame`` (ENU by default),
    ``acc`` the sensor-frame specific force in m/s²; ``device_ticks`` the SampleTimeFine counter (10 kHz) or
    None, ``host_ns`` the ``time.monotonic_ns()`` of the read that completed the message.
    """

    sensor: str
    host_ns: int
    device_ticks: int | None
    packet_counter: int | None
    quat: tuple[float, ...] | None
    acc: tuple[float, ...] | None
    frame: CoordFrame | None


@dataclass(slots=True)
class DeviceStats:
    connects: int = 0
    disconnects: int = 0
    bringup_failures: int = 0
    samples: int = 0
    stalls: int = 0
    device_errors: list[str] = field(default_factory=list)
    #: the most recent connection failures (open, bring-up, link lost, stall), newest last, at most 20
    failures: list[str] = field(default_factory=list)


class _SessionProtocol(asyncio.Protocol):
    def __init__(self, session: XsensSession, on_events: Callable[[int], None], clock: Callable[[], int]) -> None:
        self.session = session
        self.transport: SerialTransport | None = None
        self.lost: asyncio.Future[Exception | None] = asyncio.get_running_loop().create_future()
        self.last_rx_ns = clock()
        self._on_events = on_events
        self._clock = clock

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, SerialTransport)
        self.transport = transport

    def data_received(self, data: bytes) -> None:
        now = self._clock()
        self.last_rx_ns = now
        self.session.receive_data(data, now)
        self.flush()
        self._on_events(now)

    def flush(self) -> None:
        out = self.session.data_to_send()
        if out and self.transport is not None:
            self.transport.write(out)

    def connection_lost(self, exc: Exception | None) -> None:
        if not self.lost.done():
            self.lost.set_result(exc)


class XsensSerialDevice:
    """Runs one serial device until :meth:`stop`; samples go to ``on_sample``.

    With ``awinda`` the device is an Awinda station (EXPERIMENTAL, see :mod:`mocapd.protocols.awinda`): it is
    brought up with the station steps and each MTw's snapshots are integrated into samples.
    """

    def __init__(
        self,
        config: XsensPortConfig,
        on_sample: Callable[[ImuSample], None],
        *,
        clock: Callable[[], int] = time.monotonic_ns,
        awinda: AwindaConfig | None = None,
    ) -> None:
        self.awinda = awinda
        self._integrator: SnapshotIntegrator | None = None
        if awinda is not None:
            awinda.check()
            assert awinda.delta_q_scale is not None and awinda.delta_v_scale is not None
            self._integrator = SnapshotIntegrator(awinda.delta_q_scale, awinda.delta_v_scale, awinda.update_rate_hz)
        self.config = config
        self._on_sample = on_sample
        self._clock = clock
        self.stats = DeviceStats()
        self._info: DeviceInfo | None = None
        self._sensor = config.path
        self.last_error: str | None = None
        self.streaming = asyncio.Event()
        self._stopping = False
        self._stop_requested = asyncio.Event()
        self._proto: _SessionProtocol | None = None
        #: the current (or last) session, for its parser and session counters
        self.session: XsensSession | None = None

    @property
    def info(self) -> DeviceInfo | None:
        """What the device said about itself at its latest bring-up (None before the first)."""
        return self._info

    @info.setter
    def info(self, info: DeviceInfo | None) -> None:
        self._info = info
        # The sensor id every sample carries, worked out once per bring-up rather than per sample.
        self._sensor = info.serial if info is not None else self.config.path

    def open_state(self) -> OpenState:
        """Whether the device has streamed yet, or its first connection failed (with the reason)."""
        if self.stats.samples or self.streaming.is_set():
            return OpenState("open", "")
        if self.stats.failures:
            return OpenState("failed", self.stats.failures[-1])
        return OpenState("opening", "")

    def stop(self) -> None:
        """Ask :meth:`run` to return after closing the port."""
        self._stopping = True
        self._stop_requested.set()
        if self._proto is not None and self._proto.transport is not None:
            self._proto.transport.close()

    async def run(self) -> None:
        """Connect, stream, and reconnect with back-off until stopped. Never returns on device errors."""
        backoff = self.config.reconnect_min_s
        while not self._stopping:
            try:
                await self.run_once()
                backoff = self.config.reconnect_min_s  # streamed successfully: start the back-off over
            except DeviceError as exc:
                self.last_error = str(exc)
                self.stats.failures = [*self.stats.failures[-19:], str(exc)]
                log.warning("%s; retrying in %.1f s", exc, backoff)
            if self._stopping:
                break
            with contextlib.suppress(TimeoutError):  # sleep the back-off, but wake up at once on stop()
                await asyncio.wait_for(self._stop_requested.wait(), timeout=backoff)
            backoff = min(backoff * 2.0, self.config.reconnect_max_s)

    async def run_once(self) -> None:
        """Open, bring up and stream until the port is lost.

        Raises
        ------
        DeviceError
            Port could not be opened, or the link was lost.
        DeviceTimeout
            Bring-up failed (the message names the step) or the stream stalled.
        """
        cfg = self.config
        session = XsensSession(
            output_settings(cfg.rate_hz, precision=cfg.precision, frame=CoordFrame.ENU),
            response_timeout_ns=round(cfg.response_timeout_s * 1e9),
            attempts=cfg.attempts,
            steps=None if self.awinda is None else station_steps(self.awinda),
        )
        self.session = session
        failure: list[str] = []
        transport, proto = await create_serial_connection(
            lambda: _SessionProtocol(session, lambda now: self._dispatch(session, failure, now), self._clock),
            cfg.path,
            baudrate=cfg.baudrate,
        )
        assert isinstance(proto, _SessionProtocol)
        proto.transport = transport  # connection_made runs later (call_soon); the first request goes out now
        self._proto = proto
        self.stats.connects += 1
        try:
            session.start(self._clock())
            proto.flush()
            await self._bring_up(session, proto, failure)
            await self._stream(proto)
        finally:
            self.streaming.clear()
            transport.close()
            self._proto = None

    async def _bring_up(self, session: XsensSession, proto: _SessionProtocol, failure: list[str]) -> None:
        while session.state is State.BRINGING_UP:
            if proto.lost.done():
                raise DeviceError(f"imu {self.config.path}: port lost during bring-up")
            deadline = session.deadline_ns
            now = self._clock()
            wait_s = 0.0 if deadline is None else max(0.0, (deadline - now) / 1e9)
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(asyncio.shield(proto.lost), timeout=min(wait_s, 0.05) or 0.001)
            session.handle_timeout(self._clock())
            proto.flush()
            self._dispatch(session, failure, self._clock())
        if session.state is State.FAILED:
            self.stats.bringup_failures += 1
            raise DeviceTimeout(f"imu {self.config.path}: {failure[0] if failure else 'bring-up failed'}")

    async def _stream(self, proto: _SessionProtocol) -> None:
        stall_ns = round(self.config.stall_timeout_s * 1e9)
        period_s = self.config.stall_timeout_s / 4
        # Silence counted only while this loop was there to hear it: a pause of the whole process (SIGSTOP, a
        # suspend, a starved loop) is not the device's (mocapd.io.silence).
        silence = SilenceClock(self._clock(), round(period_s * 1e9), stall_ns)
        while True:
            try:
                exc = await asyncio.wait_for(asyncio.shield(proto.lost), timeout=period_s)
            except TimeoutError:
                silence.heard(proto.last_rx_ns)
                if silence.silent_ns(self._clock()) > stall_ns:
                    if proto.transport is not None:
                        proto.transport.read_pending()  # what the kernel holds for the port, before judging
                    silence.heard(proto.last_rx_ns)
                    if silence.silent_ns(self._clock()) > stall_ns:
                        self.stats.stalls += 1
                        raise DeviceTimeout(
                            f"imu {self.config.path}: no data for {self.config.stall_timeout_s} s while streaming"
                        ) from None
                continue
            if self._stopping:
                return
            self.stats.disconnects += 1
            raise DeviceError(f"imu {self.config.path}: link lost ({exc})")

    def _dispatch(self, session: XsensSession, failure: list[str], now: int) -> None:
        for ev in session.events_received():
            if isinstance(ev, Sample):
                self.stats.samples += 1
                if self._integrator is not None:
                    self._snapshot_samples(ev.data, now)
                    continue
                counter, ticks, quat, acc, frame = ev.data.imu_fields()
                self._on_sample(ImuSample(self._sensor, now, ticks, counter, quat, acc, frame))
            elif isinstance(ev, Streaming):
                self.info = ev.info
                self.last_error = None
                self.streaming.set()
                log.info(
                    "imu %s: %s %s firmware %s streaming at %d Hz",
                    self.config.path,
                    ev.info.product_code,
                    ev.info.serial,
                    ev.info.firmware,
                    self.config.rate_hz,
                    extra={"repeat_key": self.config.path},  # one line per device, not five of thirteen
                )
            elif isinstance(ev, DeviceReportedError):
                self.stats.device_errors.append(f"0x{ev.report.code:02X} {ev.report.description}")
            elif isinstance(ev, DeviceReportedWarning):
                log.warning("imu %s: device warning %d %s", self.config.path, ev.warning.code, ev.warning.text)
            elif isinstance(ev, BringUpFailed):
                failure.append(ev.reason)

    def _snapshot_samples(self, data: MtData2, now: int) -> None:
        assert self._integrator is not None
        item = data.items.get(DataId.AWINDA_SNAPSHOT)
        if item is None or not isinstance(item.value, AwindaSnapshot):
            return
        s = self._integrator.add(item.value)
        if s is not None:
            self._on_sample(ImuSample(s.sensor, now, s.device_ticks, s.frame_number & 0xFFFF, s.quat, s.acc, None))
