"""MTData2 (Xbus MID 0x36) payload decoding and encoding.

An MTData2 payload is a sequence of packets, each::

    offset  size  field
    0       2     data identifier (uint16, big-endian)
    2       1     size of the data in bytes (0..255)
    3       size  data, big-endian

The data identifier packs ``group|type`` (mask 0xF8F0), the coordinate frame (mask 0x000C: 0x0 ENU,
0x4 NED, 0x8 NWU) and the precision (mask 0x0003: 0 float32, 1 fixed 12.20, 2 fixed 16.32, 3 float64) of the
floating-point outputs. Fixed 12.20 is an int32 scaled by 2^-20; fixed 16.32 is 6 bytes, the uint32 fraction
followed by the int16 integer part (value = int16 + uint32 / 2^32).

The snapshot group (0xC8xx) uses bit 0 as the retransmission flag instead of a precision: 0xC810 is an
Awinda snapshot, 0xC811 the same snapshot retransmitted. Its layout (46 bytes: device id, frame number,
3 int32 SDI delta-q increments, 3 int32 SDI delta-v increments, 3 int16 magnetic field, int32 pressure,
uint16 status, uint8 accelerometer / gyroscope clipping counters) is public; the scale factors that turn the
increments into physical units are not, see ``docs/imu.md``.

Packets with an identifier we do not know are skipped and counted (``MtData2.unknown``); packets whose size
does not match their identifier are skipped and counted (``MtData2.malformed``). Decoding never raises.
"""

from __future__ import annotations

import enum
import operator
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import NamedTuple

TYPE_MASK = 0xF8F0
FRAME_MASK = 0x000C
PRECISION_MASK = 0x0003
SNAPSHOT_GROUP = 0xC800
RETRANSMISSION_FLAG = 0x0001


class Precision(enum.IntEnum):
    """Precision bits of a floating-point data identifier."""

    FLOAT32 = 0
    FP1220 = 1
    FP1632 = 2
    FLOAT64 = 3


class CoordFrame(enum.IntEnum):
    """Coordinate-frame bits: the device's global frame for orientation, velocity and free acceleration."""

    ENU = 0x0
    NED = 0x4
    NWU = 0x8


class DataId(enum.IntEnum):
    """Data identifiers (group|type; OR in :class:`CoordFrame` and :class:`Precision` where they apply)."""

    TEMPERATURE = 0x0810
    UTC_TIME = 0x1010
    PACKET_COUNTER = 0x1020
    ITOW = 0x1030
    SAMPLE_TIME_FINE = 0x1060
    SAMPLE_TIME_COARSE = 0x1070
    FRAME_RANGE = 0x1080
    QUATERNION = 0x2010
    ROTATION_MATRIX = 0x2020
    EULER_ANGLES = 0x2030
    BARO_PRESSURE = 0x3010
    DELTA_V = 0x4010
    ACCELERATION = 0x4020
    FREE_ACCELERATION = 0x4030
    ACCELERATION_HR = 0x4040
    ALTITUDE_MSL = 0x5010
    ALTITUDE_ELLIPSOID = 0x5020
    POSITION_ECEF = 0x5030
    LAT_LON = 0x5040
    GNSS_PVT_DATA = 0x7010
    GNSS_SAT_INFO = 0x7020
    RATE_OF_TURN = 0x8020
    DELTA_Q = 0x8030
    RATE_OF_TURN_HR = 0x8040
    RAW_ACC_GYR_MAG_TEMP = 0xA010
    RAW_GYRO_TEMP = 0xA020
    ANALOG_IN_1 = 0xB010
    ANALOG_IN_2 = 0xB020
    MAGNETIC_FIELD = 0xC020
    MAGNETIC_FIELD_CORRECTED = 0xC030
    AWINDA_SNAPSHOT = 0xC810
    VELOCITY_XYZ = 0xD010
    STATUS_BYTE = 0xE010
    STATUS_WORD = 0xE020
    DEVICE_ID = 0xE080
    LOCATION_ID = 0xE090


# Number of float components of each precision-dependent output.
_FLOAT_COMPONENTS: dict[int, int] = {
    DataId.TEMPERATURE: 1,
    DataId.QUATERNION: 4,
    DataId.ROTATION_MATRIX: 9,
    DataId.EULER_ANGLES: 3,
    DataId.DELTA_V: 3,
    DataId.ACCELERATION: 3,
    DataId.FREE_ACCELERATION: 3,
    DataId.ACCELERATION_HR: 3,
    DataId.ALTITUDE_MSL: 1,
    DataId.ALTITUDE_ELLIPSOID: 1,
    DataId.POSITION_ECEF: 3,
    DataId.LAT_LON: 2,
    DataId.RATE_OF_TURN: 3,
    DataId.DELTA_Q: 4,
    DataId.RATE_OF_TURN_HR: 3,
    DataId.MAGNETIC_FIELD: 3,
    DataId.MAGNETIC_FIELD_CORRECTED: 3,
    DataId.VELOCITY_XYZ: 3,
}

# Integer outputs: one struct each; a single-field struct decodes to an int, others to a tuple of ints.
_INT_STRUCTS: dict[int, struct.Struct] = {
    DataId.PACKET_COUNTER: struct.Struct(">H"),
    DataId.ITOW: struct.Struct(">I"),
    DataId.SAMPLE_TIME_FINE: struct.Struct(">I"),
    DataId.SAMPLE_TIME_COARSE: struct.Struct(">I"),
    DataId.FRAME_RANGE: struct.Struct(">HH"),
    DataId.BARO_PRESSURE: struct.Struct(">I"),
    DataId.RAW_ACC_GYR_MAG_TEMP: struct.Struct(">HHHHHHHHHh"),
    DataId.RAW_GYRO_TEMP: struct.Struct(">hhh"),
    DataId.ANALOG_IN_1: struct.Struct(">H"),
    DataId.ANALOG_IN_2: struct.Struct(">H"),
    DataId.STATUS_BYTE: struct.Struct(">B"),
    DataId.STATUS_WORD: struct.Struct(">I"),
    DataId.DEVICE_ID: struct.Struct(">I"),
    DataId.LOCATION_ID: struct.Struct(">H"),
}

_PRECISION_SIZE = {Precision.FLOAT32: 4, Precision.FP1220: 4, Precision.FP1632: 6, Precision.FLOAT64: 8}
_FP1220_SCALE = 1.0 / (1 << 20)
_FP1632_SCALE = 1.0 / (1 << 32)


def _float_struct(precision: int, n: int) -> struct.Struct:
    code = {Precision.FLOAT32: "f", Precision.FP1220: "i", Precision.FP1632: "Ih", Precision.FLOAT64: "d"}
    return struct.Struct(">" + code[Precision(precision)] * n)


# (type, precision) -> struct, built once so that decoding does no format parsing.
_FLOAT_STRUCTS: dict[tuple[int, int], struct.Struct] = {
    (t, p): _float_struct(p, n) for t, n in _FLOAT_COMPONENTS.items() for p in Precision
}


class UtcTime(NamedTuple):
    """UtcTime output (0x1010). ``flags`` bit 2 set means the time is valid.

    A NamedTuple rather than a frozen dataclass: it is built for every message and costs a quarter as much.
    """

    nanosecond: int
    year: int
    month: int
    day: int
    hour: int
    minute: int
    second: int
    flags: int

    def isoformat(self) -> str:
        """RFC 3339 with the shortest fraction, e.g. ``2019-01-20T13:47:24.1219Z``."""
        frac = f"{self.nanosecond:09d}".rstrip("0")
        date = f"{self.year:04d}-{self.month:02d}-{self.day:02d}"
        base = f"{date}T{self.hour:02d}:{self.minute:02d}:{self.second:02d}"
        return f"{base}.{frac}Z" if frac else f"{base}Z"


_UTC = struct.Struct(">IHBBBBBB")

# fmt: off
GNSS_PVT_FIELDS = (
    "ITOW", "Year", "Month", "Day", "Hour", "Min", "Sec", "Valid", "TAcc", "Nano", "FixType", "Flags",
    "NumSV", "Reserved1", "Lon", "Lat", "Height", "HMSL", "HAcc", "VAcc", "VelN", "VelE", "VelD", "GSpeed",
    "HeadMot", "SAcc", "HeadAcc", "HeadVeh", "GDOP", "PDOP", "TDOP", "VDOP", "HDOP", "NDOP", "EDOP",
)
# fmt: on
_GNSS_PVT = struct.Struct(">IHBBBBBBIiBBBBiiiiIIiiiiiIIIHHHHHHH")
GNSS_SAT_INFO_FIELDS = ("ITOW", "NumSVS", "Res1", "Res2", "Res3")
_GNSS_SAT_HEADER = struct.Struct(">IBBBB")
_GNSS_SAT = struct.Struct(">BBBB")  # gnssId, svId, cno, flags


@dataclass(frozen=True, slots=True)
class GnssSatInfo:
    """GnssSatInfo output (0x7020): header fields plus one ``(gnss_id, sv_id, cno, flags)`` per satellite."""

    header: dict[str, int]
    satellites: tuple[tuple[int, int, int, int], ...]


@dataclass(frozen=True, slots=True)
class AwindaSnapshot:
    """Awinda snapshot record (0xC810, or 0xC811 when retransmitted), raw integers as sent.

    ``delta_q`` and ``delta_v`` are strapdown-integration (SDI) increments since the previous snapshot, in
    device units whose scale factors Xsens does not publish; see ``mocapd.io.awinda``.
    """

    device_id: int
    frame_number: int
    delta_q: tuple[int, int, int]
    delta_v: tuple[int, int, int]
    mag: tuple[int, int, int]
    baro: int
    status: int
    acc_clip_count: int
    gyr_clip_count: int
    retransmitted: bool


_SNAPSHOT = struct.Struct(">IIiiiiiihhhiHBB")

Value = tuple[float, ...] | int | tuple[int, ...] | UtcTime | dict[str, int] | GnssSatInfo | AwindaSnapshot


class DataItem(NamedTuple):
    """One decoded MTData2 packet.

    ``frame`` and ``precision`` are set for floating-point outputs only.
    """

    data_id: int
    value: Value
    frame: CoordFrame | None = None
    precision: Precision | None = None


# Plain ints of the outputs an IMU streams: IntEnum members' attribute look-ups cost on every sample.
_PACKET_COUNTER = int(DataId.PACKET_COUNTER)
_SAMPLE_TIME_FINE = int(DataId.SAMPLE_TIME_FINE)
_QUATERNION = int(DataId.QUATERNION)
_ACCELERATION = int(DataId.ACCELERATION)


@dataclass(slots=True)
class MtData2:
    """A decoded MTData2 message: items keyed by their :class:`DataId` (precision/frame bits masked off)."""

    items: dict[int, DataItem] = field(default_factory=dict)
    unknown: int = 0
    malformed: int = 0

    def floats(self, data_id: int) -> tuple[float, ...] | None:
        """Components of a floating-point output, or ``None`` if absent."""
        item = self.items.get(data_id)
        return item.value if item is not None and item.precision is not None else None  # type: ignore[return-value]

    def integer(self, data_id: int) -> int | None:
        """A single-integer output (counter, sample time, status), or ``None`` if absent."""
        item = self.items.get(data_id)
        return item.value if item is not None and isinstance(item.value, int) else None

    def imu_fields(
        self,
    ) -> tuple[int | None, int | None, tuple[float, ...] | None, tuple[float, ...] | None, CoordFrame | None]:
        """(:attr:`packet_counter`, :attr:`sample_time_fine`, :attr:`quaternion`, :attr:`acceleration`, the
        quaternion's frame) at once: what a streaming IMU's every sample is read for, with one dictionary look-up
        each rather than a property and a method call each (1300 samples a second for a suit)."""
        get = self.items.get
        c = get(_PACKET_COUNTER)
        t = get(_SAMPLE_TIME_FINE)
        q = get(_QUATERNION)
        a = get(_ACCELERATION)
        # A floating-point item's value is its components (as in :meth:`floats`).
        quat: tuple[float, ...] | None = q.value if q is not None and q.precision is not None else None  # type: ignore[assignment]
        acc: tuple[float, ...] | None = a.value if a is not None and a.precision is not None else None  # type: ignore[assignment]
        return (
            c.value if c is not None and isinstance(c.value, int) else None,
            t.value if t is not None and isinstance(t.value, int) else None,
            quat,
            acc,
            q.frame if q is not None else None,
        )

    @property
    def packet_counter(self) -> int | None:
        return self.integer(DataId.PACKET_COUNTER)

    @property
    def sample_time_fine(self) -> int | None:
        """Device time in 10 kHz ticks (wraps at 2^32)."""
        return self.integer(DataId.SAMPLE_TIME_FINE)

    @property
    def quaternion(self) -> tuple[float, ...] | None:
        """Orientation (w, x, y, z) of the sensor in the device's global frame (see the item's ``frame``)."""
        return self.floats(DataId.QUATERNION)

    @property
    def acceleration(self) -> tuple[float, ...] | None:
        """Calibrated acceleration in the sensor frame, m/s², gravity included."""
        return self.floats(DataId.ACCELERATION)


def _decode_utc(data: bytes | memoryview, data_id: int) -> Value | None:
    return UtcTime(*_UTC.unpack(data)) if len(data) == _UTC.size else None


def _decode_gnss_pvt(data: bytes | memoryview, data_id: int) -> Value | None:
    if len(data) != _GNSS_PVT.size:
        return None
    return dict(zip(GNSS_PVT_FIELDS, _GNSS_PVT.unpack(data), strict=True))


def _decode_gnss_sat_info(data: bytes | memoryview, data_id: int) -> Value | None:
    if len(data) < _GNSS_SAT_HEADER.size:
        return None
    header = dict(zip(GNSS_SAT_INFO_FIELDS, _GNSS_SAT_HEADER.unpack_from(data), strict=True))
    if len(data) != _GNSS_SAT_HEADER.size + _GNSS_SAT.size * header["NumSVS"]:
        return None
    return GnssSatInfo(header, tuple(_GNSS_SAT.iter_unpack(data[_GNSS_SAT_HEADER.size :])))


def _decode_snapshot(data: bytes | memoryview, data_id: int) -> Value | None:
    if len(data) != _SNAPSHOT.size:
        return None
    v = _SNAPSHOT.unpack(data)
    return AwindaSnapshot(
        v[0], v[1], v[2:5], v[5:8], v[8:11], v[11], v[12], v[13], v[14], bool(data_id & RETRANSMISSION_FLAG)
    )


_SPECIAL: dict[int, Callable[[bytes | memoryview, int], Value | None]] = {
    DataId.UTC_TIME: _decode_utc,
    DataId.GNSS_PVT_DATA: _decode_gnss_pvt,
    DataId.GNSS_SAT_INFO: _decode_gnss_sat_info,
    DataId.AWINDA_SNAPSHOT: _decode_snapshot,
}


# How a data identifier is decoded; built once per identifier seen (at most 65 536, in practice a dozen).
_RAW, _FIXED1220, _FIXED1632, _SCALAR, _TUPLE, _SPECIAL_KIND = range(6)


# (type id, kind, struct or None, size or -1, frame, precision): a plain tuple, unpacked in the hot loop.
_Spec = tuple[int, int, struct.Struct | None, int, CoordFrame | None, Precision | None]


def _type_of(data_id: int) -> int:
    if data_id & 0xFF00 == SNAPSHOT_GROUP:
        return data_id & ~RETRANSMISSION_FLAG & 0xFFFF
    return data_id & TYPE_MASK


def _build_spec(data_id: int) -> _Spec | None:
    type_id = _type_of(data_id)
    if type_id in _FLOAT_COMPONENTS:
        precision = Precision(data_id & PRECISION_MASK)
        frame_bits = data_id & FRAME_MASK
        frame = CoordFrame(frame_bits) if frame_bits != 0xC else None
        kind = {Precision.FP1220: _FIXED1220, Precision.FP1632: _FIXED1632}.get(precision, _RAW)
        st = _FLOAT_STRUCTS[(type_id, precision)]
        return (type_id, kind, st, st.size, frame, precision)
    if type_id in _SPECIAL:
        return (type_id, _SPECIAL_KIND, None, -1, None, None)
    int_st = _INT_STRUCTS.get(type_id)
    if int_st is None:
        return None
    return (type_id, _SCALAR if len(int_st.format) == 2 else _TUPLE, int_st, int_st.size, None, None)


_SPECS: dict[int, _Spec | None] = {}
_HEADER = struct.Struct(">HB")


class _Layout(NamedTuple):
    """A payload's packets when each is a known output of the right size (a device streams the same outputs in
    every message): their header bytes, one struct for the whole payload (headers and the special outputs' bytes
    skipped) and, per packet, how to make its item: from its run of the unpacked values, or (UTC time, GNSS, Awinda
    snapshot) its own decoder on its bytes."""

    header_at: Callable[[bytes | memoryview], tuple[int, ...]]  # the header bytes (id high, id low, size) of each
    header: tuple[int, ...]
    whole: struct.Struct
    packets: tuple[tuple[int, int, int, int, int, CoordFrame | None, Precision | None, int, int], ...]
    # (type id, data id, kind, first value, value count, frame, precision, data start, data end)


_LAYOUTS: dict[int, _Layout] = {}  # by payload length: the last layout decoded at that length
_MAX_LAYOUTS = 64  # a stream of ever new lengths (garbage) does not grow the cache without bound


def decode_mtdata2(payload: bytes | memoryview) -> MtData2:
    """Decode an MTData2 payload. Never raises; unknown or malformed packets are counted and skipped.

    A truncated trailing packet counts as malformed.

    A payload laid out as the last one of its length (every header byte the same: the packets' walk reads nothing
    else, so it finds the same packets) is unpacked with one struct call (:class:`_Layout`); each value is the one
    the packet's own struct gives (the same big-endian codes in one format), so the items are the same.
    """
    layout = _LAYOUTS.get(len(payload))
    if layout is not None and layout.header_at(payload) == layout.header:
        return _decode_laid_out(payload, layout)
    out = _decode_walk(payload)
    if not out.unknown and not out.malformed and (len(payload) in _LAYOUTS or len(_LAYOUTS) < _MAX_LAYOUTS):
        found = _layout_of(payload)
        if found is not None:
            _LAYOUTS[len(payload)] = found
    return out


def _decode_laid_out(payload: bytes | memoryview, layout: _Layout) -> MtData2:
    values = layout.whole.unpack_from(payload)
    out = MtData2()
    items = out.items
    new_item = tuple.__new__
    for type_id, data_id, kind, first, count, frame, precision, start, end in layout.packets:
        value: Value | None
        if kind == _SPECIAL_KIND:
            value = _SPECIAL[type_id](payload[start:end], data_id)
            if value is None:
                return _decode_walk(payload)  # malformed this time: the walk counts it
        elif kind == _SCALAR:
            value = values[first]
        else:
            raw = values[first : first + count]
            if kind == _FIXED1220:
                value = tuple(v * _FP1220_SCALE for v in raw)
            elif kind == _FIXED1632:
                value = tuple(raw[i + 1] + raw[i] * _FP1632_SCALE for i in range(0, len(raw), 2))
            else:
                value = raw
        items[type_id] = new_item(DataItem, (data_id, value, frame, precision))
    return out


def _layout_of(payload: bytes | memoryview) -> _Layout | None:
    """The layout of a payload that decoded without unknown or malformed packets (None for an empty one)."""
    n = len(payload)
    pos = 0
    header_pos: list[int] = []
    fmt = ">"
    packets = []
    first = 0
    while pos < n:
        data_id = (payload[pos] << 8) | payload[pos + 1]
        size = payload[pos + 2]
        spec = _SPECS.get(data_id)
        if spec is None:
            return None
        type_id, kind, st, _, frame, precision = spec
        header_pos += [pos, pos + 1, pos + 2]
        count = 0 if st is None else len(st.unpack_from(payload, pos + 3))
        fmt += f"3x{size}x" if st is None else "3x" + st.format.lstrip(">")
        packets.append((type_id, data_id, kind, first, count, frame, precision, pos + 3, pos + 3 + size))
        first += count
        pos += 3 + size
    if not packets:
        return None  # nothing to unpack (an empty payload)
    header_at = operator.itemgetter(*header_pos)  # three or more positions: a tuple of the bytes there
    return _Layout(header_at, header_at(payload), struct.Struct(fmt), tuple(packets))


def _decode_walk(payload: bytes | memoryview) -> MtData2:
    """Every packet in turn (the general case: any layout, unknown and malformed packets counted)."""
    out = MtData2()
    items = out.items
    n = len(payload)
    pos = 0
    specs = _SPECS
    new_item = tuple.__new__  # DataItem's generated __new__ is a Python function; this skips it (≈25 % faster)
    while pos < n:
        if n - pos < 3:
            out.malformed += 1
            break
        data_id = (payload[pos] << 8) | payload[pos + 1]
        size = payload[pos + 2]
        start = pos + 3
        pos = start + size
        if pos > n:
            out.malformed += 1
            break
        spec = specs.get(data_id, _SPEC_MISSING)
        if spec is _SPEC_MISSING:
            spec = specs[data_id] = _build_spec(data_id)
        if spec is None:
            out.unknown += 1
            continue
        type_id, kind, st, st_size, frame, precision = spec
        value: Value | None
        if st is None:
            value = _SPECIAL[type_id](payload[start:pos], data_id)
            if value is None:
                out.malformed += 1
                continue
        else:
            if size != st_size:
                out.malformed += 1
                continue
            raw = st.unpack_from(payload, start)
            if kind in (_RAW, _TUPLE):
                value = raw
            elif kind == _SCALAR:
                value = raw[0]
            elif kind == _FIXED1220:
                value = tuple(v * _FP1220_SCALE for v in raw)
            else:
                value = tuple(raw[i + 1] + raw[i] * _FP1632_SCALE for i in range(0, len(raw), 2))
        items[type_id] = new_item(DataItem, (data_id, value, frame, precision))
    return out


_SPEC_MISSING: _Spec = (-1, -1, None, -1, None, None)


# ---------------------------------------------------------------------------------------------- encoding


def _encode_floats(data_id: int, values: tuple[float, ...] | list[float]) -> bytes:
    type_id = data_id & TYPE_MASK
    precision = data_id & PRECISION_MASK
    st = _FLOAT_STRUCTS[(type_id, precision)]
    if precision == Precision.FP1220:
        return st.pack(*(round(v * (1 << 20)) for v in values))
    if precision == Precision.FP1632:
        flat: list[int] = []
        for v in values:
            fixed = round(v * (1 << 32))
            flat += [fixed & 0xFFFFFFFF, fixed >> 32]
        return st.pack(*flat)
    return st.pack(*values)


def encode_packet(data_id: int, value: Value | list[float]) -> bytes:
    """One MTData2 packet (identifier, size, data) for a value of the identifier's type.

    Supports every floating-point output (any precision), the integer outputs, UtcTime and the Awinda
    snapshot. Used by the device simulator and the tests.

    Raises
    ------
    ValueError
        If the identifier is unknown or the value does not fit it (a caller bug, not device data).
    """
    type_id = _type_of(data_id)
    if type_id in _FLOAT_COMPONENTS and isinstance(value, tuple | list):
        data = _encode_floats(data_id, [float(v) for v in value])
    elif isinstance(value, UtcTime):
        data = _UTC.pack(
            value.nanosecond,
            value.year,
            value.month,
            value.day,
            value.hour,
            value.minute,
            value.second,
            value.flags,
        )
    elif isinstance(value, AwindaSnapshot):
        data = _SNAPSHOT.pack(
            value.device_id,
            value.frame_number,
            *value.delta_q,
            *value.delta_v,
            *value.mag,
            value.baro,
            value.status,
            value.acc_clip_count,
            value.gyr_clip_count,
        )
    elif type_id in _INT_STRUCTS and isinstance(value, int | tuple):
        ints = (value,) if isinstance(value, int) else value
        data = _INT_STRUCTS[type_id].pack(*ints)
    else:
        raise ValueError(f"cannot encode {type(value).__name__} as MTData2 id 0x{data_id:04X}")
    return _HEADER.pack(data_id, len(data)) + data
