"""SlimeVR tracker UDP protocol: the datagrams of SlimeVR tracker firmware and a SlimeVR server's replies (pure).

Written from the public protocol definitions, not copied: SlimeVR-Server ``UDPProtocolParser.kt``,
``UDPPacket.kt``, ``TrackersUDPServer.kt`` and ``FeatureFlags.kt`` at commit ``554976390b7c`` (2026-08-21), and
SlimeVR-Tracker-ESP ``src/network/packets.h`` and ``connection.cpp`` at commit ``12f4b22dacf2`` (2026-01-07,
firmware protocol version 22). The server state machine (connections, replies, time-outs) is
:mod:`mocapd.protocols.slimevr_server`.

Every multi-byte value is big-endian. Trackers send to UDP port 6969 (the server's); a tracker looking for a server
broadcasts its handshake once a second and then talks to whichever address answered it.

Tracker → server datagram::

    offset  type        field
    0       u32         packet type (the firmware writes three 0 bytes and the type byte)
    4       u64         packet number: per connection, increasing by one; 0 in the handshake
    12      ...         payload of that type (below)

Payloads (``f32`` IEEE 754, ``u8`` unsigned, ``s16`` two's complement)::

    0    heartbeat                  (nothing): the tracker's answer to the server's heartbeat
    1    rotation (legacy)          f32 x, y, z, w                         sensor 0
    3    handshake                  u32 board, u32 imu, u32 mcu, 3 × u32 unused, u32 protocol version
                                    (firmware build), u8 n + n ASCII bytes firmware version, 6 bytes MAC, then
                                    newer fields (tracker type, vendor strings) that a server may ignore. Every
                                    field is optional from the end (owoTrack sends a short handshake); a MAC of
                                    all zeros means none.
    4    acceleration               f32 x, y, z (m/s², sensor frame, gravity removed), u8 sensor (optional: 0)
    10   ping/pong                  u32 ping id: the tracker echoes the server's ping verbatim
    11   serial (log text)          u32 n, n bytes
    12   battery                    f32 voltage, f32 level (0..1); older firmware: f32 level only
    13   tap                        u8 sensor, u8 tap flags
    14   error                      u8 sensor, u8 error code
    15   sensor info                u8 sensor, u8 status (0 offline, 1 ok, 2 error), u8 IMU type, then optional
                                    u16 config bits, u8 rest-calibrated, u8 position, u8 data type, f32 × 2 rates
    16   rotation 2 (legacy)        f32 x, y, z, w                         sensor 1
    17   rotation data              u8 sensor, u8 data type (1 normal, 2 correction), f32 x, y, z, w,
                                    u8 calibration accuracy
    18   magnetometer accuracy      u8 sensor, f32 accuracy
    19   signal strength            u8 sensor (255: the whole tracker), s8 RSSI (dBm)
    20   temperature                u8 sensor, f32 °C
    21   user action                u8 action (2 full reset, 3 yaw reset, 4 mounting reset, 5 pause)
    22   feature flags              flag bytes (bit k of byte k // 8 = firmware feature k)
    23   rotation + acceleration    u8 sensor, s16 × 4 quaternion x, y, z, w in Q15 (value / 2¹⁵), s16 × 3
                                    acceleration in Q7 (value / 2⁷, m/s²)
    24   config change ack          u8 sensor, u16 config type
    26   flex data                  u8 sensor, f32 value
    27   position                   u8 sensor, f32 x, y, z
    100  bundle                     repeated: u16 n, then n bytes = one inner packet without packet number
                                    (u32 type + payload)
    101  compact bundle             repeated: u8 n, then n bytes = u8 type + payload
    200  protocol change            u8 protocol, u8 version

Quaternions are (x, y, z, w) on the wire, the sensor's orientation in the tracker's fusion frame: right-handed,
+Z up, with a heading of its own (each tracker's yaw reference is where its gyroscope started unless a
magnetometer is used). mocapd treats that frame as ENU with an unknown heading offset per tracker.

Server → tracker::

    handshake reply   64 bytes: 0x03, ASCII "Hey OVR =D 5", zero padding (no packet type word: the firmware
                      compares byte 0 and the 12 bytes after it)
    heartbeat         u32 1, u64 0                       the tracker answers with its heartbeat (0)
    ping              u32 10, u64 0, u32 ping id         echoed by the tracker
    sensor info ack   u32 15, u8 sensor, u8 status       (6 bytes, no packet number)
    feature flags     u32 22, u64 0, flag bytes          server features: bit 0 bundles (100), bit 1 compact
                                                         bundles (101) and packet 23

Bad bytes never raise here: :func:`decode_datagram` returns what it could read and a reason for what it could not.
"""

from __future__ import annotations

import enum
import math
import struct
from collections.abc import Callable
from dataclasses import dataclass

PORT = 6969
"""UDP port of a SlimeVR server (trackers send here)."""
PROTOCOL_VERSION = 22
"""Firmware protocol version of the definitions followed (``PROTOCOL_VERSION`` in the firmware's debug.h)."""
HANDSHAKE_MAGIC = b"Hey OVR =D 5"
HANDSHAKE_REPLY = (b"\x03" + HANDSHAKE_MAGIC).ljust(64, b"\x00")
NO_SENSOR = 255
"""Sensor id meaning "the whole tracker" (signal strength, global config flags)."""


class Tx(enum.IntEnum):
    """Packet types a tracker sends."""

    HEARTBEAT = 0
    ROTATION = 1
    HANDSHAKE = 3
    ACCELERATION = 4
    PING_PONG = 10
    SERIAL = 11
    BATTERY = 12
    TAP = 13
    ERROR = 14
    SENSOR_INFO = 15
    ROTATION_2 = 16
    ROTATION_DATA = 17
    MAGNETOMETER_ACCURACY = 18
    SIGNAL_STRENGTH = 19
    TEMPERATURE = 20
    USER_ACTION = 21
    FEATURE_FLAGS = 22
    ROTATION_ACCELERATION = 23
    ACK_CONFIG_CHANGE = 24
    FLEX_DATA = 26
    POSITION = 27
    BUNDLE = 100
    BUNDLE_COMPACT = 101
    PROTOCOL_CHANGE = 200


class Rx(enum.IntEnum):
    """Packet types a server sends."""

    HEARTBEAT = 1
    HANDSHAKE = 3
    PING_PONG = 10
    SENSOR_INFO = 15
    FEATURE_FLAGS = 22


class ServerFeature(enum.IntFlag):
    """Server feature flag bits (SlimeVR-Server ``ServerFeatureFlags``)."""

    BUNDLE = 1
    BUNDLE_COMPACT = 2


DATA_TYPE_NORMAL = 1
DATA_TYPE_CORRECTION = 2
SENSOR_OK = 1
SENSOR_ERROR = 2

_HEADER = struct.Struct(">IQ")
_U32 = struct.Struct(">I")
_F32x3 = struct.Struct(">3f")
_F32x4 = struct.Struct(">4f")
_Q15 = 1.0 / (1 << 15)
_Q7 = 1.0 / (1 << 7)

Quat = tuple[float, float, float, float]
Vec3 = tuple[float, float, float]


# ---------------------------------------------------------------------------------------------- packets
@dataclass(frozen=True, slots=True)
class Handshake:
    board: int
    imu: int
    mcu: int
    protocol_version: int
    firmware: str
    mac: str | None  # "AA:BB:CC:DD:EE:FF", None when absent or all zeros


@dataclass(frozen=True, slots=True)
class Heartbeat:
    pass


@dataclass(frozen=True, slots=True)
class Rotation:
    """Packets 1, 16, 17 and 23: a sensor's orientation (w, x, y, z); ``acc`` only in packet 23."""

    sensor: int
    quat: Quat
    data_type: int = DATA_TYPE_NORMAL
    accuracy: int = 0
    acc: Vec3 | None = None


@dataclass(frozen=True, slots=True)
class Acceleration:
    sensor: int
    acc: Vec3  # m/s², sensor frame, gravity removed


@dataclass(frozen=True, slots=True)
class PingPong:
    ping_id: int


@dataclass(frozen=True, slots=True)
class Battery:
    voltage: float | None
    level: float  # 0..1


@dataclass(frozen=True, slots=True)
class SignalStrength:
    sensor: int
    rssi_dbm: int


@dataclass(frozen=True, slots=True)
class SensorInfo:
    sensor: int
    status: int
    imu_type: int


@dataclass(frozen=True, slots=True)
class Temperature:
    sensor: int
    celsius: float


@dataclass(frozen=True, slots=True)
class TrackerError:
    sensor: int
    code: int


@dataclass(frozen=True, slots=True)
class FeatureFlags:
    flags: bytes


@dataclass(frozen=True, slots=True)
class Tap:
    """Packet 13: the tracker's own tap detector fired (BNO08x): ``flags`` bit 6 (0x40) is a double tap."""

    sensor: int
    flags: int

    @property
    def double(self) -> bool:
        return bool(self.flags & 0x40)


USER_ACTION_RESET_FULL = 2
USER_ACTION_RESET_YAW = 3
USER_ACTION_RESET_MOUNTING = 4
USER_ACTION_PAUSE = 5


@dataclass(frozen=True, slots=True)
class UserAction:
    """Packet 21: the wearer asked the server for something on the tracker (a button): ``action`` is 2 full
    reset, 3 yaw reset, 4 mounting reset, 5 pause tracking."""

    action: int


@dataclass(frozen=True, slots=True)
class Ignored:
    """A well-formed packet mocapd has no use for (serial log, tap, user action, flex data, ...)."""

    packet_type: int


Packet = (
    Handshake | Heartbeat | Rotation | Acceleration | PingPong | Battery | SignalStrength | SensorInfo | Temperature
    | TrackerError | FeatureFlags | Tap | UserAction | Ignored
)  # fmt: skip


@dataclass(frozen=True, slots=True)
class Decoded:
    """What one datagram held: its packet number, the packets read, and why the rest could not be (or None)."""

    packet_type: int
    number: int
    packets: tuple[Packet, ...]
    error: str | None = None


class _ShortError(Exception):
    """A payload ended before a required field (internal: turned into a :class:`Decoded` error)."""


class _Reader:
    def __init__(self, data: bytes | memoryview) -> None:
        self.data = memoryview(data)
        self.pos = 0

    @property
    def remaining(self) -> int:
        return len(self.data) - self.pos

    def take(self, n: int) -> bytes:
        if self.remaining < n:
            raise _ShortError
        out = bytes(self.data[self.pos : self.pos + n])
        self.pos += n
        return out

    def u8(self) -> int:
        return self.take(1)[0]

    def s8(self) -> int:
        v = self.u8()
        return v - 256 if v > 127 else v

    def u16(self) -> int:
        return int.from_bytes(self.take(2), "big")

    def s16(self) -> int:
        return int.from_bytes(self.take(2), "big", signed=True)

    def u32(self) -> int:
        return int.from_bytes(self.take(4), "big")

    def f32(self) -> float:
        v: float = struct.unpack(">f", self.take(4))[0]
        return v


def _finite(*values: float) -> bool:
    return all(math.isfinite(v) for v in values)


def _quat(x: float, y: float, z: float, w: float) -> Quat:
    """(w, x, y, z) normalised; ValueError when it is not a rotation (non-finite, or far from unit norm)."""
    if not _finite(x, y, z, w):
        raise ValueError("non-finite quaternion")
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if not 0.9 < n < 1.1:
        raise ValueError(f"quaternion norm {n:.3g}, not a rotation")
    return (w / n, x / n, y / n, z / n)


MAX_ACC = 2000.0
"""Largest acceleration component accepted, m/s² (about 200 g; tracker IMUs measure up to 16 g)."""


def _vec(x: float, y: float, z: float) -> Vec3:
    if not _finite(x, y, z):
        raise ValueError("non-finite vector")
    if max(abs(x), abs(y), abs(z)) > MAX_ACC:
        raise ValueError(f"acceleration beyond {MAX_ACC:g} m/s²")
    return (x, y, z)


def _handshake(r: _Reader) -> Handshake:
    # Every field is optional from the end, as the server reads it (short owoTrack handshakes).
    board = r.u32() if r.remaining > 3 else 0
    imu = r.u32() if r.remaining > 3 else 0
    mcu = r.u32() if r.remaining > 3 else 0
    if r.remaining > 11:
        r.take(12)  # unused IMU info
    version = r.u32() if r.remaining > 3 else 0
    n = r.u8() if r.remaining > 0 else 0
    raw = bytearray()
    while n > 0 and r.remaining:  # up to n bytes, or through a NUL (as the server reads it)
        n -= 1
        c = r.u8()
        if c == 0:
            break
        raw.append(c)
    firmware = raw.decode("ascii", errors="replace")
    mac = None
    if r.remaining >= 6:
        b = r.take(6)
        if any(b):
            mac = ":".join(f"{v:02X}" for v in b)
    return Handshake(board, imu, mcu, version, firmware, mac)


def _rotation_legacy(sensor: int) -> Callable[[_Reader], Packet]:
    def read(r: _Reader) -> Packet:
        x, y, z, w = _F32x4.unpack(r.take(16))
        return Rotation(sensor, _quat(x, y, z, w))

    return read


def _acceleration(r: _Reader) -> Packet:
    acc = _vec(*_F32x3.unpack(r.take(12)))
    return Acceleration(r.u8() if r.remaining else 0, acc)  # owoTrack omits the sensor byte


def _battery(r: _Reader) -> Packet:
    voltage = r.f32() if r.remaining >= 8 else None  # older firmware sends the level only
    level = r.f32()
    if not _finite(level, 0.0 if voltage is None else voltage):
        raise ValueError("non-finite battery reading")
    return Battery(voltage, level)


def _rotation_data(r: _Reader) -> Packet:
    sensor, data_type = r.u8(), r.u8()
    x, y, z, w = _F32x4.unpack(r.take(16))
    return Rotation(sensor, _quat(x, y, z, w), data_type, r.u8())


def _temperature(r: _Reader) -> Packet:
    sensor, celsius = r.u8(), r.f32()
    if not _finite(celsius):
        raise ValueError("non-finite temperature")
    return Temperature(sensor, celsius)


def _rotation_acceleration(r: _Reader) -> Packet:
    sensor = r.u8()
    x, y, z, w = (r.s16() * _Q15 for _ in range(4))
    ax, ay, az = (r.s16() * _Q7 for _ in range(3))
    return Rotation(sensor, _quat(x, y, z, w), acc=(ax, ay, az))


def _ignored(ptype: int) -> Callable[[_Reader], Packet]:
    return lambda r: Ignored(ptype)


_DECODERS: dict[int, Callable[[_Reader], Packet]] = {
    Tx.HEARTBEAT: lambda r: Heartbeat(),
    Tx.ROTATION: _rotation_legacy(0),
    Tx.HANDSHAKE: _handshake,
    Tx.ACCELERATION: _acceleration,
    Tx.PING_PONG: lambda r: PingPong(r.u32()),
    Tx.BATTERY: _battery,
    Tx.ERROR: lambda r: TrackerError(r.u8(), r.u8()),
    Tx.SENSOR_INFO: lambda r: SensorInfo(r.u8(), r.u8(), r.u8() if r.remaining else 0),
    Tx.ROTATION_2: _rotation_legacy(1),
    Tx.ROTATION_DATA: _rotation_data,
    Tx.SIGNAL_STRENGTH: lambda r: SignalStrength(r.u8(), r.s8()),
    Tx.TEMPERATURE: _temperature,
    Tx.FEATURE_FLAGS: lambda r: FeatureFlags(r.take(r.remaining)),
    Tx.ROTATION_ACCELERATION: _rotation_acceleration,
    Tx.TAP: lambda r: Tap(r.u8(), r.u8()),
    Tx.USER_ACTION: lambda r: UserAction(r.u8()),
    **{t: _ignored(t) for t in (Tx.SERIAL, Tx.MAGNETOMETER_ACCURACY, Tx.ACK_CONFIG_CHANGE, Tx.FLEX_DATA,
                                Tx.POSITION, Tx.PROTOCOL_CHANGE)},
}  # fmt: skip


def _payload(ptype: int, r: _Reader) -> Packet:
    """One packet's payload (after type and number). Raises _ShortError or ValueError on bad content."""
    decoder = _DECODERS.get(ptype)
    if decoder is None:
        raise ValueError(f"unknown packet type {ptype}")
    return decoder(r)


def _bundle(ptype: int, r: _Reader) -> tuple[list[Packet], str | None]:
    """Inner packets of a bundle (100: u16 length + u32 type; 101: u8 length + u8 type)."""
    out: list[Packet] = []
    while r.remaining:
        n = r.u16() if ptype == Tx.BUNDLE else r.u8()
        if n == 0:
            continue
        if n > r.remaining:
            return out, f"bundle entry of {n} bytes, {r.remaining} left"
        inner = _Reader(r.take(n))
        try:
            itype = inner.u32() if ptype == Tx.BUNDLE else inner.u8()
        except _ShortError:
            return out, "bundled packet without a type"
        if itype in (Tx.BUNDLE, Tx.BUNDLE_COMPACT, Tx.HANDSHAKE):
            return out, f"packet type {itype} inside a bundle"
        try:
            out.append(_payload(itype, inner))
        except _ShortError:
            return out, f"bundled packet type {itype} truncated"
        except ValueError as exc:
            return out, f"bundled packet: {exc}"
    return out, None


def decode_datagram(data: bytes) -> Decoded:
    """Decode one tracker datagram (never raises: bad content gives ``error``, with what was read before it).

    ``packet_type`` is -1 and ``number`` 0 when the 12-byte header itself is missing.
    """
    if len(data) < _HEADER.size:
        return Decoded(-1, 0, (), f"datagram of {len(data)} bytes, shorter than the 12-byte header")
    ptype, number = _HEADER.unpack_from(data)
    r = _Reader(memoryview(data)[_HEADER.size :])
    if ptype in (Tx.BUNDLE, Tx.BUNDLE_COMPACT):
        try:
            packets, error = _bundle(ptype, r)
        except _ShortError:
            return Decoded(ptype, number, (), "bundle truncated")
        return Decoded(ptype, number, tuple(packets), error)
    try:
        return Decoded(ptype, number, (_payload(ptype, r),))
    except _ShortError:
        return Decoded(ptype, number, (), f"packet type {ptype} truncated ({len(data)} bytes)")
    except ValueError as exc:
        return Decoded(ptype, number, (), str(exc))


# ---------------------------------------------------------------------------------------------- server side
def encode_heartbeat() -> bytes:
    """The server's heartbeat (the tracker answers with its own)."""
    return _HEADER.pack(Rx.HEARTBEAT, 0)


def encode_ping(ping_id: int) -> bytes:
    """A ping the tracker echoes back unchanged."""
    return _HEADER.pack(Rx.PING_PONG, 0) + _U32.pack(ping_id & 0xFFFFFFFF)


def encode_sensor_info_ack(sensor: int, status: int) -> bytes:
    """Acknowledges a sensor info packet (the tracker stops repeating it): 6 bytes, no packet number."""
    return _U32.pack(Rx.SENSOR_INFO) + bytes([sensor & 0xFF, status & 0xFF])


def encode_feature_flags(features: ServerFeature) -> bytes:
    """The server's feature flags (the reply to the tracker's)."""
    return _HEADER.pack(Rx.FEATURE_FLAGS, 0) + bytes([int(features) & 0xFF])


# ---------------------------------------------------------------------------------------------- tracker side
def _handshake_bytes(p: Handshake) -> bytes:
    fw = p.firmware.encode("ascii")
    mac = bytes.fromhex(p.mac.replace(":", "")) if p.mac else bytes(6)
    return struct.pack(">7I", p.board, p.imu, p.mcu, 0, 0, 0, p.protocol_version) + bytes([len(fw)]) + fw + mac


def _rotation_bytes(p: Rotation) -> tuple[int, bytes]:
    w, x, y, z = p.quat
    if p.acc is None:
        return Tx.ROTATION_DATA, bytes([p.sensor, p.data_type]) + _F32x4.pack(x, y, z, w) + bytes([p.accuracy])
    q = [max(-32768, min(32767, round(v * (1 << 15)))) for v in (x, y, z, w)]
    a = [max(-32768, min(32767, round(v * (1 << 7)))) for v in p.acc]
    return Tx.ROTATION_ACCELERATION, bytes([p.sensor]) + struct.pack(">7h", *q, *a)


def _battery_bytes(p: Battery) -> bytes:
    return struct.pack(">f", p.level) if p.voltage is None else struct.pack(">2f", p.voltage, p.level)


def _payload_bytes(p: Packet) -> tuple[int, bytes]:
    """Packet type and payload bytes of a tracker packet (the inverse of :func:`_payload`)."""
    match p:
        case Rotation():
            return _rotation_bytes(p)
        case Handshake():
            body = (Tx.HANDSHAKE, _handshake_bytes(p))
        case Heartbeat():
            body = (Tx.HEARTBEAT, b"")
        case Acceleration():
            body = (Tx.ACCELERATION, _F32x3.pack(*p.acc) + bytes([p.sensor]))
        case PingPong():
            body = (Tx.PING_PONG, _U32.pack(p.ping_id))
        case Battery():
            body = (Tx.BATTERY, _battery_bytes(p))
        case SignalStrength():
            body = (Tx.SIGNAL_STRENGTH, bytes([p.sensor, p.rssi_dbm & 0xFF]))
        case SensorInfo():
            body = (Tx.SENSOR_INFO, bytes([p.sensor, p.status, p.imu_type]))
        case Temperature():
            body = (Tx.TEMPERATURE, bytes([p.sensor]) + struct.pack(">f", p.celsius))
        case TrackerError():
            body = (Tx.ERROR, bytes([p.sensor, p.code]))
        case FeatureFlags():
            body = (Tx.FEATURE_FLAGS, p.flags)
        case Tap():
            body = (Tx.TAP, bytes([p.sensor, p.flags]))
        case UserAction():
            body = (Tx.USER_ACTION, bytes([p.action]))
        case _:
            raise TypeError(f"cannot encode {type(p).__name__}")
    return body


def encode_packet(packet: Packet, number: int) -> bytes:
    """One tracker datagram as the firmware sends it (for simulators and tests)."""
    ptype, body = _payload_bytes(packet)
    return _HEADER.pack(ptype, 0 if ptype == Tx.HANDSHAKE else number) + body


def encode_bundle(packets: list[Packet], number: int, *, compact: bool = False) -> bytes:
    """Several tracker packets in one bundle datagram (100, or 101 with ``compact``)."""
    parts = [_HEADER.pack(Tx.BUNDLE_COMPACT if compact else Tx.BUNDLE, number)]
    for p in packets:
        ptype, body = _payload_bytes(p)
        inner = bytes([ptype]) + body if compact else _U32.pack(ptype) + body
        parts.append(bytes([len(inner)]) if compact else struct.pack(">H", len(inner)))
        parts.append(inner)
    return b"".join(parts)
