"""Sans-I/O bring-up and streaming session for one Xsens device on a point-to-point serial link.

The session is a state machine fed with bytes (:meth:`XsensSession.receive_data`) and with the current time
(:meth:`XsensSession.handle_timeout`); it produces bytes to write (:meth:`XsensSession.data_to_send`) and
events (:meth:`XsensSession.events_received`). It never reads a clock and never touches a port.

Bring-up, each step a request and the reply that completes it::

    GoToConfig (0x30)                → GoToConfigAck (0x31)
    ReqDID (0x00)                    → DeviceID (0x01)
    ReqProductCode (0x1C)            → ProductCode (0x1D)
    ReqFWRev (0x12)                  → FirmwareRev (0x13)
    SetOutputConfiguration (0xC0)    → SetOutputConfigurationAck (0xC1)
    GoToMeasurement (0x10)           → GoToMeasurementAck (0x11)

A request without its reply within ``response_timeout_ns`` is sent again, up to ``attempts`` times; then the
session fails with a message naming the step. A WakeUp (0x3E) from a device that just powered up is answered
with WakeUpAck (0x3F) at any time, which keeps it in configuration mode. An Error (0x42) in reply to a request
counts as a failed attempt and is reported as an event.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

from mocapd.errors import ConfigError
from mocapd.protocols import xbus
from mocapd.protocols.mtdata2 import CoordFrame, DataId, MtData2, Precision, decode_mtdata2
from mocapd.protocols.xbus import MID, OutputSetting

MIN_RATE_HZ = 60
MAX_RATE_HZ = 120


def output_settings(
    rate_hz: int, *, precision: Precision = Precision.FLOAT32, frame: CoordFrame = CoordFrame.ENU
) -> list[OutputSetting]:
    """The outputs mocapd asks for: packet counter, SampleTimeFine, quaternion and acceleration.

    Raises
    ------
    ConfigError
        If ``rate_hz`` is outside 60..120 Hz.
    """
    if not MIN_RATE_HZ <= rate_hz <= MAX_RATE_HZ:
        raise ConfigError(f"imu rate_hz={rate_hz} not allowed: use {MIN_RATE_HZ}..{MAX_RATE_HZ} Hz")
    return [
        OutputSetting(DataId.PACKET_COUNTER, xbus.RATE_MAX),
        OutputSetting(DataId.SAMPLE_TIME_FINE, xbus.RATE_MAX),
        OutputSetting(DataId.QUATERNION | frame | precision, rate_hz),
        OutputSetting(DataId.ACCELERATION | precision, rate_hz),
    ]


class State(enum.Enum):
    IDLE = "idle"
    BRINGING_UP = "bringing-up"
    MEASURING = "measuring"
    FAILED = "failed"


@dataclass(frozen=True, slots=True)
class DeviceInfo:
    """What the device said about itself during bring-up."""

    device_id: int
    product_code: str
    firmware: str

    @property
    def serial(self) -> str:
        """Device id as printed on the case (8 hex digits)."""
        return f"{self.device_id:08X}"


@dataclass(frozen=True, slots=True)
class Streaming:
    """Bring-up finished; MTData2 samples follow."""

    info: DeviceInfo


@dataclass(frozen=True, slots=True)
class Sample:
    """One decoded MTData2 message (host time is attached by the I/O layer)."""

    bid: int
    data: MtData2


@dataclass(frozen=True, slots=True)
class DeviceReportedError:
    """The device sent an Error message."""

    report: xbus.XbusErrorReport


@dataclass(frozen=True, slots=True)
class DeviceReportedWarning:
    """The device sent a Warning message (streaming continues)."""

    warning: xbus.XbusWarning


@dataclass(frozen=True, slots=True)
class BringUpFailed:
    """Bring-up gave up; ``reason`` names the step and what went wrong."""

    reason: str


Event = Streaming | Sample | DeviceReportedError | DeviceReportedWarning | BringUpFailed


@dataclass(frozen=True, slots=True)
class Step:
    """One bring-up request and the message id of the reply that completes it."""

    name: str
    request: int
    payload: bytes
    reply: int


def identify_steps() -> list[Step]:
    """The first four steps of bring-up: into configuration mode, then what the device is. A session of only
    these ends in :class:`Streaming` with the :class:`DeviceInfo` and leaves the device in configuration mode
    (``mocapd devices`` identifies devices this way)."""
    return [
        Step("GoToConfig", MID.GOTO_CONFIG, b"", MID.GOTO_CONFIG_ACK),
        Step("ReqDID", MID.REQ_DID, b"", MID.DEVICE_ID),
        Step("ReqProductCode", MID.REQ_PRODUCT_CODE, b"", MID.PRODUCT_CODE),
        Step("ReqFWRev", MID.REQ_FW_REV, b"", MID.FIRMWARE_REV),
    ]


def standard_steps(settings: list[OutputSetting]) -> list[Step]:
    """Bring-up of an MTi / MTw on its own serial link (the table in the module docstring)."""
    return [
        *identify_steps(),
        Step(
            "SetOutputConfiguration",
            MID.SET_OUTPUT_CONFIGURATION,
            xbus.encode_output_configuration(settings),
            MID.SET_OUTPUT_CONFIGURATION_ACK,
        ),
        Step("GoToMeasurement", MID.GOTO_MEASUREMENT, b"", MID.GOTO_MEASUREMENT_ACK),
    ]


@dataclass(slots=True)
class SessionCounters:
    """Per-session counters for metrics."""

    samples: int = 0
    retries: int = 0
    device_errors: int = 0
    device_warnings: int = 0
    ignored_messages: int = 0
    unknown_data_ids: int = 0
    malformed_packets: int = 0


class XsensSession:
    """Bring-up and streaming for one device.

    Parameters
    ----------
    settings : list of OutputSetting
        What SetOutputConfiguration sends (see :func:`output_settings`).
    response_timeout_ns : int
        How long to wait for each reply.
    attempts : int
        Sends per request before giving up.
    steps : list of Step, optional
        Replaces :func:`standard_steps` (the experimental Awinda station uses its own).
    """

    def __init__(
        self,
        settings: list[OutputSetting],
        *,
        response_timeout_ns: int = 500_000_000,
        attempts: int = 3,
        steps: list[Step] | None = None,
    ) -> None:
        self.parser = xbus.XbusParser()
        self._steps = standard_steps(settings) if steps is None else list(steps)
        self._timeout = response_timeout_ns
        self._attempts = attempts
        self.state = State.IDLE
        self.counters = SessionCounters()
        self._out = bytearray()
        self._events: list[Event] = []
        self._step = 0
        self._attempt = 0
        self._deadline = 0
        self._last_error: str | None = None
        self._device_id = 0
        self._product = ""
        self._firmware = ""

    # ----------------------------------------------------------------------------------------- interface

    def start(self, now_ns: int) -> None:
        """Begin bring-up (queues GoToConfig)."""
        self.state = State.BRINGING_UP
        self._step = 0
        self._attempt = 0
        self._send_step(now_ns)

    def receive_data(self, data: bytes, now_ns: int) -> None:
        """Feed bytes read from the port."""
        self.parser.receive_data(data)
        for msg in self.parser.events_received():
            self._handle(msg, now_ns)

    def handle_timeout(self, now_ns: int) -> None:
        """Call at or after :attr:`deadline_ns` (harmless earlier): resends or fails the current step."""
        if self.state is not State.BRINGING_UP or now_ns < self._deadline:
            return
        step = self._steps[self._step]
        if self._attempt >= self._attempts:
            why = self._last_error or f"no {MID(step.reply).name} reply within {self._timeout / 1e9:.2f} s"
            self._fail(f"{step.name} failed after {self._attempts} attempts: {why}")
            return
        self.counters.retries += 1
        self._send_step(now_ns)

    @property
    def deadline_ns(self) -> int | None:
        """When :meth:`handle_timeout` must next be called, or None when nothing is pending."""
        return self._deadline if self.state is State.BRINGING_UP else None

    def data_to_send(self) -> bytes:
        """Bytes queued for the port since the last call."""
        out = bytes(self._out)
        self._out.clear()
        return out

    def events_received(self) -> list[Event]:
        """Events since the last call, oldest first."""
        events, self._events = self._events, []
        return events

    # ------------------------------------------------------------------------------------------ internals

    def _send_step(self, now_ns: int) -> None:
        step = self._steps[self._step]
        self._out += xbus.encode(step.request, step.payload)
        self._attempt += 1
        self._deadline = now_ns + self._timeout

    def _fail(self, reason: str) -> None:
        self.state = State.FAILED
        self._events.append(BringUpFailed(reason))

    def _handle(self, msg: xbus.XbusMessage, now_ns: int) -> None:
        mid = msg.mid
        if mid == MID.MTDATA2:
            if self.state is State.MEASURING:
                data = decode_mtdata2(msg.payload)
                self.counters.samples += 1
                self.counters.unknown_data_ids += data.unknown
                self.counters.malformed_packets += data.malformed
                self._events.append(Sample(msg.bid, data))
            else:
                self.counters.ignored_messages += 1  # still streaming from before GoToConfig
            return
        if mid == MID.WAKE_UP:
            self._out += xbus.encode(MID.WAKE_UP_ACK)
            return
        if mid == MID.WARNING:
            self.counters.device_warnings += 1
            self._events.append(DeviceReportedWarning(xbus.decode_warning(msg.payload)))
            return
        if mid == MID.ERROR:
            report = xbus.decode_error(msg.payload)
            self.counters.device_errors += 1
            self._events.append(DeviceReportedError(report))
            if self.state is State.BRINGING_UP:
                self._last_error = f"device error 0x{report.code:02X} ({report.description})"
                self._deadline = now_ns  # retry (or give up) at the next handle_timeout
            return
        if self.state is State.BRINGING_UP and mid == self._steps[self._step].reply:
            self._complete_step(msg.payload, now_ns)
            return
        self.counters.ignored_messages += 1

    def _complete_step(self, payload: bytes, now_ns: int) -> None:
        reply = self._steps[self._step].reply
        if reply == MID.DEVICE_ID:
            device_id = xbus.decode_device_id(payload)
            if device_id is None:
                self._last_error = f"DeviceID payload of {len(payload)} bytes"
                return  # wait for the time-out and ask again
            self._device_id = device_id
        elif reply == MID.PRODUCT_CODE:
            self._product = xbus.decode_product_code(payload)
        elif reply == MID.FIRMWARE_REV:
            fw = xbus.decode_firmware_revision(payload)
            if fw is None:
                self._last_error = f"FirmwareRev payload of {len(payload)} bytes"
                return
            self._firmware = str(fw)
        self._last_error = None
        self._step += 1
        self._attempt = 0
        if self._step == len(self._steps):
            self.state = State.MEASURING
            self._events.append(Streaming(DeviceInfo(self._device_id, self._product, self._firmware)))
        else:
            self._send_step(now_ns)
