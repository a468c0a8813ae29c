"""GigE Vision Control Protocol (GVCP) device discovery, sans-I/O: DISCOVERY_CMD out, DISCOVERY_ACK in.

Sources: GigE Vision Specification version 2.0 (AIA, 2013), Part 2 "GVCP": the GVCP command and acknowledge
message headers and the DISCOVERY message pair of the control channel dictionary; the DISCOVERY_ACK payload is a
copy of the device's bootstrap registers 0x0000-0x00F7 (Part 3, bootstrap register map). Checked against the
layout Aravis documents for its discovery packet (aravis-gvcp, "Discovery acknowledge packet") and the offsets
of Aravis 0.8.26 ``arvgvcpprivate.h``, and against the bytes Aravis' fake GigE camera sends.

All fields are big-endian. A command (application → device, UDP port :data:`GVCP_PORT`)::

    offset  size  field
    0       1     key      0x42
    1       1     flags    bit 0 (0x01) acknowledge required; DISCOVERY_CMD bit 4 (0x10) allow a broadcast
                           acknowledge (a device outside the application's subnet may then broadcast its reply)
    2       2     command  0x0002 DISCOVERY_CMD
    4       2     length   payload bytes after the header: 0 for DISCOVERY_CMD
    6       2     req_id   1..65535 (0 is not allowed), echoed by the acknowledge

An acknowledge (device → application)::

    offset  size  field
    0       2     status       0x0000 success; anything else is an error code
    2       2     acknowledge  0x0003 DISCOVERY_ACK
    4       2     length       0x00F8 (248) for DISCOVERY_ACK
    6       2     ack_id       the command's req_id

DISCOVERY_ACK payload (offsets from the end of the header = bootstrap register addresses)::

    offset  size  field
    0x00    2     spec version major
    0x02    2     spec version minor
    0x04    4     device mode: bit 31 big-endian registers; bits 30-28 device class (0 transmitter, 1 receiver,
                  2 transceiver, 3 peripheral); bits 27-24 current link configuration; bits 7-0 character set of
                  the strings (1 UTF-8, 2 ASCII)
    0x08    2     reserved
    0x0A    6     MAC address
    0x10    4     supported IP configuration (bit 0 persistent IP, bit 1 DHCP, bit 2 link-local)
    0x14    4     current IP configuration (same bits)
    0x18    12    reserved
    0x24    4     current IP address
    0x28    12    reserved
    0x34    4     current subnet mask
    0x38    12    reserved
    0x44    4     default gateway
    0x48    32    manufacturer name     (strings: NUL-terminated unless they fill their field)
    0x68    32    model name
    0x88    32    device version
    0xA8    48    manufacturer specific information
    0xD8    16    serial number
    0xE8    16    user-defined name
    0xF8          end (248 bytes)

:class:`DiscoveryCollector` makes the commands and takes every datagram that arrives in reply; a datagram that is
not a well-formed DISCOVERY_ACK to one of its commands is counted by reason (:class:`DiscoveryCounters`), never
raised.
"""

from __future__ import annotations

import enum
import ipaddress
import struct
from dataclasses import dataclass, fields

GVCP_PORT = 3956
"""UDP port every GigE Vision device listens on for GVCP commands."""
CMD_KEY = 0x42
FLAG_ACK_REQUIRED = 0x01
FLAG_ALLOW_BROADCAST_ACK = 0x10
DISCOVERY_CMD = 0x0002
DISCOVERY_ACK = 0x0003
STATUS_SUCCESS = 0x0000
HEADER_SIZE = 8
DISCOVERY_ACK_SIZE = 0xF8
"""Payload bytes of a DISCOVERY_ACK (bootstrap registers 0x0000-0x00F7)."""

_HEADER = struct.Struct(">BBHHH")
_ACK_HEADER = struct.Struct(">HHHH")
_FIXED = struct.Struct(">HHI2x6sII12x4s12x4s12x4s")  # version .. gateway: bootstrap 0x00-0x47
# (name, offset, size) of the string fields
_STRINGS = (
    ("manufacturer", 0x48, 32),
    ("model", 0x68, 32),
    ("device_version", 0x88, 32),
    ("manufacturer_info", 0xA8, 48),
    ("serial", 0xD8, 16),
    ("user_name", 0xE8, 16),
)


class DeviceClass(enum.IntEnum):
    """Device mode bits 30-28."""

    TRANSMITTER = 0
    RECEIVER = 1
    TRANSCEIVER = 2
    PERIPHERAL = 3


class IpConfig(enum.IntFlag):
    """Supported / current IP configuration bits."""

    PERSISTENT = 0x1
    DHCP = 0x2
    LLA = 0x4


@dataclass(frozen=True, slots=True)
class DiscoveryAck:
    """What one device said about itself in a DISCOVERY_ACK."""

    ack_id: int
    spec_version: tuple[int, int]
    device_mode: int
    """The raw device mode register (see :attr:`big_endian`, :attr:`device_class`, :attr:`character_set`)."""
    mac: str
    """``"00:11:1c:f5:3a:02"`` (lower case)."""
    ip_config_supported: IpConfig
    ip_config_current: IpConfig
    ip: str
    subnet: str
    gateway: str
    manufacturer: str
    model: str
    device_version: str
    manufacturer_info: str
    serial: str
    user_name: str

    @property
    def big_endian(self) -> bool:
        return bool(self.device_mode >> 31)

    @property
    def device_class(self) -> int:
        """0 transmitter (a camera), 1 receiver, 2 transceiver, 3 peripheral (:class:`DeviceClass`)."""
        return (self.device_mode >> 28) & 0x7

    @property
    def character_set(self) -> int:
        """1 UTF-8, 2 ASCII, 0 not reported."""
        return self.device_mode & 0xFF


class Rejected(enum.Enum):
    """Why a datagram was not taken as a discovery acknowledge."""

    TRUNCATED = "truncated"
    """Shorter than a header, than its own length field, or than a DISCOVERY_ACK payload."""
    MALFORMED = "malformed"
    """Not a DISCOVERY_ACK header (another acknowledge, a command, garbage)."""
    ERROR_STATUS = "error_status"
    """A DISCOVERY_ACK whose status is not success."""
    UNKNOWN_ID = "unknown_id"
    """A DISCOVERY_ACK to a command we did not send (another application's discovery)."""


def encode_discovery_cmd(req_id: int, *, allow_broadcast_ack: bool = False) -> bytes:
    """The 8-byte DISCOVERY_CMD.

    Raises
    ------
    ValueError
        If ``req_id`` is not in 1..65535 (a caller bug, not data).
    """
    if not 0 < req_id <= 0xFFFF:
        raise ValueError(f"GVCP req_id must be 1..65535, got {req_id}")
    flags = FLAG_ACK_REQUIRED | (FLAG_ALLOW_BROADCAST_ACK if allow_broadcast_ack else 0)
    return _HEADER.pack(CMD_KEY, flags, DISCOVERY_CMD, 0, req_id)


def _ipv4(raw: bytes) -> str:
    return str(ipaddress.IPv4Address(raw))


def _string(raw: bytes) -> str:
    # Fixed-size field: NUL-terminated, or the whole field when it is full. Bytes that are not UTF-8 (a device
    # claiming ASCII and sending Latin-1) are replaced rather than refused: the rest of the ack is still good.
    return raw.split(b"\0", 1)[0].decode("utf-8", errors="replace")


def parse_discovery_ack(data: bytes | bytearray | memoryview) -> DiscoveryAck | Rejected:
    """Decode one datagram; never raises on bad bytes.

    Returns
    -------
    DiscoveryAck or Rejected
        The acknowledge, or why the datagram is not a good one (:attr:`Rejected.UNKNOWN_ID` is never returned
        here: this function does not know which commands were sent).
    """
    buf = bytes(data)
    if len(buf) < HEADER_SIZE:
        return Rejected.TRUNCATED
    status, answer, length, ack_id = _ACK_HEADER.unpack_from(buf)
    if answer != DISCOVERY_ACK:
        return Rejected.MALFORMED
    if status != STATUS_SUCCESS:
        return Rejected.ERROR_STATUS
    if length < DISCOVERY_ACK_SIZE or len(buf) < HEADER_SIZE + DISCOVERY_ACK_SIZE:
        return Rejected.TRUNCATED
    payload = buf[HEADER_SIZE : HEADER_SIZE + DISCOVERY_ACK_SIZE]
    major, minor, mode, mac, supported, current, ip, subnet, gateway = _FIXED.unpack_from(payload)
    strings = {name: _string(payload[offset : offset + size]) for name, offset, size in _STRINGS}
    return DiscoveryAck(
        ack_id=ack_id,
        spec_version=(major, minor),
        device_mode=mode,
        mac=":".join(f"{b:02x}" for b in mac),
        ip_config_supported=IpConfig(supported & 0x7),
        ip_config_current=IpConfig(current & 0x7),
        ip=_ipv4(ip),
        subnet=_ipv4(subnet),
        gateway=_ipv4(gateway),
        **strings,
    )


def encode_discovery_ack(ack: DiscoveryAck) -> bytes:
    """The datagram a device sends for ``ack`` (the inverse of :func:`parse_discovery_ack`; used by tests and
    simulators).

    Raises
    ------
    ValueError
        If a string does not fit its field or an address is not IPv4 (a caller bug).
    """
    mac = bytes(int(part, 16) for part in ack.mac.split(":"))
    if len(mac) != 6:
        raise ValueError(f"MAC address {ack.mac!r} is not 6 bytes")
    payload = bytearray(DISCOVERY_ACK_SIZE)
    _FIXED.pack_into(
        payload, 0, *ack.spec_version, ack.device_mode, mac, int(ack.ip_config_supported),
        int(ack.ip_config_current), *(ipaddress.IPv4Address(a).packed for a in (ack.ip, ack.subnet, ack.gateway)),
    )  # fmt: skip
    for name, offset, size in _STRINGS:
        raw = str(getattr(ack, name)).encode("utf-8")
        if len(raw) > size:
            raise ValueError(f"{name} {raw!r} is longer than its {size}-byte field")
        payload[offset : offset + len(raw)] = raw
    return _ACK_HEADER.pack(STATUS_SUCCESS, DISCOVERY_ACK, DISCOVERY_ACK_SIZE, ack.ack_id) + bytes(payload)


@dataclass(slots=True)
class DiscoveryCounters:
    """Datagrams a discovery received, by what became of them."""

    acks: int = 0
    """Good acknowledges from devices not seen before in this discovery."""
    duplicates: int = 0
    """Good acknowledges from a device already seen (it answered several commands)."""
    truncated: int = 0
    malformed: int = 0
    error_status: int = 0
    unknown_id: int = 0

    def rejected(self) -> int:
        """Datagrams that were not a good acknowledge to one of our commands."""
        return self.truncated + self.malformed + self.error_status + self.unknown_id

    def as_dict(self) -> dict[str, int]:
        return {f.name: int(getattr(self, f.name)) for f in fields(self)}


@dataclass(frozen=True, slots=True)
class DiscoveredDevice:
    """A device that answered, with the source address its acknowledge came from."""

    ack: DiscoveryAck
    source: str


class DiscoveryCollector:
    """One discovery: the commands to send and the devices that answered them.

    Parameters
    ----------
    first_req_id : int
        Request id of the first command (1..65535); the next ones count up, wrapping past 65535 to 1. A caller
        that runs discoveries back to back picks a fresh one each time, so late acks of the previous discovery
        count as :attr:`Rejected.UNKNOWN_ID` instead of being mistaken for answers.
    allow_broadcast_ack : bool
        Set the DISCOVERY_CMD flag that lets a device on another subnet broadcast its acknowledge.
    """

    def __init__(self, first_req_id: int = 1, *, allow_broadcast_ack: bool = False) -> None:
        if not 0 < first_req_id <= 0xFFFF:
            raise ValueError(f"GVCP req_id must be 1..65535, got {first_req_id}")
        self._next_id = first_req_id
        self._sent: set[int] = set()
        self._broadcast_ack = allow_broadcast_ack
        self._devices: dict[tuple[str, str, str], DiscoveredDevice] = {}
        self._events: list[DiscoveredDevice] = []
        self.counters = DiscoveryCounters()

    def command(self) -> bytes:
        """A new DISCOVERY_CMD (each with its own request id) to send."""
        req_id = self._next_id
        self._next_id = req_id % 0xFFFF + 1
        self._sent.add(req_id)
        return encode_discovery_cmd(req_id, allow_broadcast_ack=self._broadcast_ack)

    def receive_datagram(self, data: bytes | bytearray | memoryview, source: str) -> None:
        """Take one datagram received from ``source`` (the sender's IPv4 address)."""
        result = parse_discovery_ack(data)
        if isinstance(result, Rejected):
            setattr(self.counters, result.value, getattr(self.counters, result.value) + 1)
            return
        if result.ack_id not in self._sent:
            self.counters.unknown_id += 1
            return
        # A fake or unconfigured device may report MAC 00:00:00:00:00:00: the key includes its address and serial.
        key = (result.mac, result.ip, result.serial)
        if key in self._devices:
            self.counters.duplicates += 1
            return
        self.counters.acks += 1
        device = DiscoveredDevice(result, source)
        self._devices[key] = device
        self._events.append(device)

    def events_received(self) -> list[DiscoveredDevice]:
        """Devices that answered for the first time since the last call, in order of arrival."""
        events, self._events = self._events, []
        return events

    @property
    def devices(self) -> list[DiscoveredDevice]:
        """Every device that answered, in order of arrival."""
        return list(self._devices.values())
