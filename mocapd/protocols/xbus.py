"""Xsens Xbus framing: a sans-I/O parser and the encoder for every message mocapd sends.

Wire format (all multi-byte fields big-endian)::

    offset  size  field
    0       1     PRE   preamble, always 0xFA
    1       1     BID   bus identifier (0xFF = master / the device itself on a point-to-point link)
    2       1     MID   message identifier (see :class:`MID`)
    3       1     LEN   payload length 0..254; 0xFF announces the extended form
   [4       2     EXTLEN  payload length 0..2048, only when LEN == 0xFF]
    4|6     LEN   DATA  payload
    end     1     CS    checksum: (BID + MID + LEN [+ EXTLEN bytes] + DATA + CS) % 256 == 0

The parser takes arbitrary byte chunks (:meth:`XbusParser.receive_data`), resynchronises on the next 0xFA
after garbage, counts checksum failures, oversize lengths and discarded bytes, and never raises on bad input.
Complete messages come out of :meth:`XbusParser.events_received` as :class:`XbusMessage`.

MTData2 payloads (MID 0x36) are decoded by :mod:`mocapd.protocols.mtdata2`.
"""

from __future__ import annotations

import enum
import struct
from dataclasses import dataclass, field

PREAMBLE = 0xFA
#: Bus identifier of the master device on a point-to-point serial link.
BID_MASTER = 0xFF
#: Largest payload the Xbus specification allows in the extended-length form (bytes).
MAX_PAYLOAD = 2048
_EXTENDED = 0xFF


class MID(enum.IntEnum):
    """Xbus message identifiers. An acknowledgement is the request's id + 1.

    Several ids are shared between a ``Req`` (empty payload) and a ``Set`` (with payload); the enum keeps
    the set name and documents the request alias in the comment.
    """

    REQ_DID = 0x00  # request device id
    DEVICE_ID = 0x01  # 4-byte device id (serial number)
    INIT_MT = 0x02
    INIT_MT_RESULTS = 0x03
    REQ_PERIOD = 0x04
    REQ_PERIOD_ACK = 0x05
    GOTO_MEASUREMENT = 0x10
    GOTO_MEASUREMENT_ACK = 0x11
    REQ_FW_REV = 0x12
    FIRMWARE_REV = 0x13  # major, minor, revision (+ optional build/svn fields on newer firmware)
    SET_BAUDRATE = 0x18  # also ReqBaudrate (empty payload)
    SET_BAUDRATE_ACK = 0x19
    REQ_PRODUCT_CODE = 0x1C
    PRODUCT_CODE = 0x1D  # ASCII product code, space padded
    REQ_HARDWARE_VERSION = 0x1E
    HARDWARE_VERSION = 0x1F
    GOTO_CONFIG = 0x30
    GOTO_CONFIG_ACK = 0x31
    MTDATA = 0x32  # legacy MTData (not decoded; counted)
    MTDATA2 = 0x36
    WAKE_UP = 0x3E  # sent by the device after power-up; answer with WAKE_UP_ACK to stay in config
    WAKE_UP_ACK = 0x3F
    RESET = 0x40
    RESET_ACK = 0x41
    ERROR = 0x42  # first payload byte is an error code (:data:`ERROR_CODES`)
    WARNING = 0x43  # 4-byte warning code + optional text
    SET_OPTION_FLAGS = 0x48
    SET_OPTION_FLAGS_ACK = 0x49
    # --- wireless master (Awinda station / dongle); ids public in the Xsens SDK headers, payloads partly not
    SCAN_CHANNELS = 0xB0
    SCAN_CHANNELS_ACK = 0xB1
    ENABLE_MASTER = 0xB2  # payload: radio channel (uint16)
    ENABLE_MASTER_ACK = 0xB3
    DISABLE_MASTER = 0xB4
    DISABLE_MASTER_ACK = 0xB5
    REQ_RADIO_CHANNEL = 0xB6
    REQ_RADIO_CHANNEL_ACK = 0xB7
    SET_CLIENT_PRIORITY = 0xB8  # also ReqClientPriority
    SET_CLIENT_PRIORITY_ACK = 0xB9
    SET_WIRELESS_CONFIG = 0xBA  # also ReqWirelessConfig
    SET_WIRELESS_CONFIG_ACK = 0xBB
    UPDATE_BIAS = 0xBC
    UPDATE_BIAS_ACK = 0xBD
    TOGGLE_IO_PINS = 0xBE
    TOGGLE_IO_PINS_ACK = 0xBF
    # 0xC0 is SetOutputConfiguration on an MTi/MTw and GotoOperational on a wireless master.
    SET_OUTPUT_CONFIGURATION = 0xC0
    SET_OUTPUT_CONFIGURATION_ACK = 0xC1
    SET_TRANSPORT_MODE = 0xC2  # also ReqTransportMode
    SET_TRANSPORT_MODE_ACK = 0xC3
    ACCEPT_MTW = 0xC4
    ACCEPT_MTW_ACK = 0xC5
    REJECT_MTW = 0xC6
    REJECT_MTW_ACK = 0xC7
    INFO_REQUEST = 0xC8
    INFO_REQUEST_ACK = 0xC9
    REQ_FRAME_RATES = 0xCA
    REQ_FRAME_RATES_ACK = 0xCB
    START_RECORDING = 0xCC
    START_RECORDING_ACK = 0xCD
    STOP_RECORDING = 0xCE
    STOP_RECORDING_ACK = 0xCF


#: Aliases that share an id with another message (wireless master naming).
GOTO_OPERATIONAL = MID.SET_OUTPUT_CONFIGURATION
GOTO_OPERATIONAL_ACK = MID.SET_OUTPUT_CONFIGURATION_ACK

#: Documented Xbus error codes (payload byte 0 of an ERROR message).
ERROR_CODES: dict[int, str] = {
    0x03: "period sent is not within the valid range",
    0x04: "message sent is invalid",
    0x1E: "timer overflow (period too short for the output)",
    0x20: "requested baud rate is not valid",
    0x21: "parameter sent is invalid or out of range",
    0x28: "device error",
    0x29: "data overflow: the device generates more data than the bus can carry",
    0x2A: "buffer overflow",
}


@dataclass(frozen=True, slots=True)
class XbusMessage:
    """One framed Xbus message (checksum already verified)."""

    bid: int
    mid: int
    payload: bytes


@dataclass(slots=True)
class XbusCounters:
    """What the parser had to throw away, for metrics. All counts since construction."""

    messages: int = 0
    checksum_errors: int = 0
    oversize: int = 0
    discarded_bytes: int = 0


def checksum(body: bytes | bytearray | memoryview) -> int:
    """The checksum byte that makes ``sum(body) + cs ≡ 0 (mod 256)``; ``body`` is BID..DATA."""
    return (-sum(body)) & 0xFF


def encode(mid: int, payload: bytes = b"", bid: int = BID_MASTER) -> bytes:
    """Frame one message (standard or extended length form).

    Raises
    ------
    ValueError
        If the payload is longer than :data:`MAX_PAYLOAD` or an id is outside 0..255 (a caller bug, not data).
    """
    n = len(payload)
    if n > MAX_PAYLOAD:
        raise ValueError(f"Xbus payload of {n} bytes exceeds the {MAX_PAYLOAD}-byte maximum")
    if not (0 <= mid <= 0xFF and 0 <= bid <= 0xFF):
        raise ValueError(f"Xbus ids must be bytes, got bid={bid} mid={mid}")
    header = bytes((bid, mid, n)) if n < _EXTENDED else bytes((bid, mid, _EXTENDED, n >> 8, n & 0xFF))
    body = header + payload
    return bytes((PREAMBLE,)) + body + bytes((checksum(body),))


class XbusParser:
    """Sans-I/O Xbus deframer.

    Parameters
    ----------
    max_payload : int
        Lengths above this are treated as a false preamble (counted in ``counters.oversize``).
    """

    def __init__(self, *, max_payload: int = MAX_PAYLOAD) -> None:
        self._buf = bytearray()
        self._events: list[XbusMessage] = []
        self._max_payload = max_payload
        self.counters = XbusCounters()

    def receive_data(self, data: bytes | bytearray | memoryview) -> None:
        """Feed bytes as they arrive; complete messages become available from :meth:`events_received`."""
        buf = self._buf
        buf += data
        counters = self.counters
        events = self._events
        n = len(buf)
        pos = 0
        while True:
            start = buf.find(PREAMBLE, pos)
            if start < 0:
                counters.discarded_bytes += n - pos
                pos = n
                break
            counters.discarded_bytes += start - pos
            pos = start
            if n - pos < 4:
                break
            length = buf[pos + 3]
            header = 4
            if length == _EXTENDED:
                if n - pos < 6:
                    break
                length = (buf[pos + 4] << 8) | buf[pos + 5]
                header = 6
            if length > self._max_payload:
                counters.oversize += 1
                counters.discarded_bytes += 1
                pos += 1
                continue
            end = pos + header + length + 1
            if end > n:
                break
            if sum(buf[pos + 1 : end]) & 0xFF:
                # A corrupted message or a 0xFA inside garbage: skip only the preamble so that a real message
                # starting inside the rejected span is still found.
                counters.checksum_errors += 1
                counters.discarded_bytes += 1
                pos += 1
                continue
            events.append(XbusMessage(buf[pos + 1], buf[pos + 2], bytes(buf[pos + header : end - 1])))
            counters.messages += 1
            pos = end
        del buf[:pos]

    def events_received(self) -> list[XbusMessage]:
        """Messages completed since the last call (oldest first)."""
        events, self._events = self._events, []
        return events

    @property
    def buffered(self) -> int:
        """Bytes held while waiting for the rest of a message."""
        return len(self._buf)


# ----------------------------------------------------------------------------------------------- payloads


@dataclass(frozen=True, slots=True)
class OutputSetting:
    """One entry of SetOutputConfiguration: a data identifier and its rate (Hz; 0xFFFF = every sample)."""

    data_id: int
    rate_hz: int


#: Rate value meaning "as fast as the device produces it" (sent for counters and time stamps).
RATE_MAX = 0xFFFF
_SETTING = struct.Struct(">HH")


def encode_output_configuration(settings: list[OutputSetting]) -> bytes:
    """Payload of SetOutputConfiguration (MID 0xC0): ``(data id uint16, rate uint16)`` per output."""
    return b"".join(_SETTING.pack(s.data_id, s.rate_hz) for s in settings)


def decode_output_configuration(payload: bytes) -> list[OutputSetting] | None:
    """Inverse of :func:`encode_output_configuration`; ``None`` when the length is not a multiple of 4."""
    if len(payload) % 4:
        return None
    return [OutputSetting(d, r) for d, r in _SETTING.iter_unpack(payload)]


@dataclass(frozen=True, slots=True)
class FirmwareRevision:
    """FirmwareRev payload: major.minor.revision (newer devices append build and SVN numbers, ignored)."""

    major: int
    minor: int
    revision: int

    def __str__(self) -> str:
        return f"{self.major}.{self.minor}.{self.revision}"


def decode_firmware_revision(payload: bytes) -> FirmwareRevision | None:
    """``None`` if shorter than the 3 mandatory bytes."""
    if len(payload) < 3:
        return None
    return FirmwareRevision(payload[0], payload[1], payload[2])


def decode_device_id(payload: bytes) -> int | None:
    """DeviceID payload: 4-byte (or 8-byte on newer devices) big-endian id, printed in hex on the case."""
    if len(payload) not in (4, 8):
        return None
    return int.from_bytes(payload, "big")


def decode_product_code(payload: bytes) -> str:
    """ProductCode payload: ASCII, padded with spaces or NULs."""
    return payload.decode("ascii", errors="replace").rstrip(" \x00")


@dataclass(frozen=True, slots=True)
class XbusErrorReport:
    """A decoded ERROR message."""

    code: int
    description: str
    extra: bytes = field(default=b"")


@dataclass(frozen=True, slots=True)
class XbusWarning:
    """A decoded WARNING message: a 32-bit code and optional text."""

    code: int
    text: str


def decode_warning(payload: bytes) -> XbusWarning:
    """Decode a WARNING payload (uint32 code + optional ASCII text); a short payload gives code -1."""
    if len(payload) < 4:
        return XbusWarning(-1, payload.hex())
    return XbusWarning(int.from_bytes(payload[:4], "big"), payload[4:].decode("ascii", errors="replace").rstrip("\x00"))


def decode_error(payload: bytes) -> XbusErrorReport:
    """Decode an ERROR payload; an empty payload gives code -1 rather than raising."""
    if not payload:
        return XbusErrorReport(-1, "error message without a code")
    code = payload[0]
    return XbusErrorReport(code, ERROR_CODES.get(code, f"undocumented error code 0x{code:02X}"), payload[1:])
