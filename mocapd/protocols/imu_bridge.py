"""IMU bridge input format: msgpack records over UDP, for sensors that mocapd cannot talk to directly.

A site that runs the vendor SDK (e.g. Xsens MTw Awinda through the Xsens Device API) forwards each sensor's
samples with a short script (``tools/xsens_sdk_bridge.py``). Each UDP datagram is one msgpack value: a map
(one record) or an array of maps (several records). Version 1 record::

    key     type              meaning
    "v"     int               format version, 1
    "id"    str               sensor id, 8 hex digits as printed on the case (e.g. "00B421E6"); any printable
                              text of 1..64 characters is taken (upper-cased)
    "t"     float             device time in seconds (the sensor's own clock; any origin, must increase),
                              |t| <= 2^32 s
    "q"     [4 x float]       orientation (w, x, y, z) of the sensor frame in the device global frame, norm
                              0.9..1.1 (normalised here)
    "a"     [3 x float]       sensor-frame acceleration, m/s², gravity included, each |a_i| <= 2000
    "frame" str, optional     device global frame of "q": "ENU" (default), "NED" or "NWU"
    "pc"    int, optional     packet counter (0..65535), lets mocapd count dropped samples

Every number is checked for type (int or float; never bool), finiteness and range before it is used. Records
that do not follow this are counted (with the reason) and skipped, never raised.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import msgpack

from mocapd.protocols.mtdata2 import CoordFrame

VERSION = 1
_FRAMES = {"ENU": CoordFrame.ENU, "NED": CoordFrame.NED, "NWU": CoordFrame.NWU}


@dataclass(frozen=True, slots=True)
class BridgeRecord:
    """One decoded bridge record."""

    sensor: str
    device_time_s: float
    quat: tuple[float, float, float, float]
    acc: tuple[float, float, float]
    frame: CoordFrame
    packet_counter: int | None


def encode_records(records: list[BridgeRecord]) -> bytes:
    """One datagram carrying ``records`` (what the forwarding script sends)."""
    items = []
    for r in records:
        item: dict[str, object] = {
            "v": VERSION,
            "id": r.sensor,
            "t": r.device_time_s,
            "q": list(r.quat),
            "a": list(r.acc),
            "frame": r.frame.name,
        }
        if r.packet_counter is not None:
            item["pc"] = r.packet_counter
        items.append(item)
    return bytes(msgpack.packb(items[0] if len(items) == 1 else items))


MAX_ID_CHARS = 64
MAX_TIME_S = 2.0**32
"""Largest |t|: 136 years of seconds, where a float64 still resolves the bridge's 0.1 ms ticks."""
MAX_ACC = 2000.0
"""Largest |a_i| in m/s² (about 200 g; the MTw measures up to 160 m/s²)."""
MAX_PACKET_COUNTER = 0xFFFF


def _number(value: object, bound: float) -> float | None:
    """``value`` as a float when it is an int or a float (not a bool) with ``|value| <= bound``, else None.

    Compared before conversion: an int too large for a float fails the bound instead of overflowing, NaN fails
    every comparison.
    """
    if isinstance(value, bool) or not isinstance(value, int | float) or not -bound <= value <= bound:
        return None
    return float(value)


def _floats(value: object, n: int, bound: float) -> tuple[float, ...] | None:
    if not isinstance(value, list | tuple) or len(value) != n:
        return None
    out = tuple(_number(v, bound) for v in value)
    return None if None in out else out  # type: ignore[return-value]


def _record(item: object) -> BridgeRecord | str:
    """The record of one item, or why it is rejected (a short fixed phrase: it becomes a counter's key)."""
    if not isinstance(item, dict):
        return "not a map"
    version, sensor, pc = item.get("v"), item.get("id"), item.get("pc")
    t = _number(item.get("t"), MAX_TIME_S)
    q, a = _floats(item.get("q"), 4, 2.0), _floats(item.get("a"), 3, MAX_ACC)
    norm = math.sqrt(sum(v * v for v in q)) if q is not None else 0.0
    frame = _FRAMES.get(item["frame"]) if isinstance(item.get("frame"), str) else None
    if "frame" not in item:
        frame = CoordFrame.ENU
    problems = (
        (version != VERSION or isinstance(version, bool), "bad version"),
        (not isinstance(sensor, str) or not 0 < len(sensor) <= MAX_ID_CHARS or not sensor.isprintable(), "bad id"),
        (t is None, "bad time"),
        (q is None or not 0.9 < norm < 1.1, "bad quaternion"),
        (a is None, "bad acceleration"),
        (frame is None, "bad frame"),
        (pc is not None and (isinstance(pc, bool) or not isinstance(pc, int) or not 0 <= pc <= MAX_PACKET_COUNTER),
         "bad packet counter"),
    )  # fmt: skip
    reason = next((why for bad, why in problems if bad), None)
    if reason is not None:
        return reason
    assert isinstance(sensor, str) and t is not None and q is not None and a is not None and frame is not None
    return BridgeRecord(
        sensor.upper(),
        t,
        (q[0] / norm, q[1] / norm, q[2] / norm, q[3] / norm),
        (a[0], a[1], a[2]),
        frame,
        pc,
    )


@dataclass(frozen=True, slots=True)
class Decoded:
    """What one datagram held: its valid records and a reason per rejected item."""

    records: list[BridgeRecord]
    rejected: list[str]


def decode(data: bytes) -> Decoded:
    """Records of one datagram and why each other item was rejected (malformed msgpack is one rejection)."""
    try:
        value = msgpack.unpackb(data, raw=False, strict_map_key=False)
    except (ValueError, msgpack.ExtraData, msgpack.FormatError, msgpack.StackError, TypeError):
        return Decoded([], ["not msgpack"])
    items = value if isinstance(value, list) else [value]
    records: list[BridgeRecord] = []
    rejected: list[str] = []
    for item in items:
        rec = _record(item)
        if isinstance(rec, str):
            rejected.append(rec)
        else:
            records.append(rec)
    return Decoded(records, rejected)


def decode_datagram(data: bytes) -> tuple[list[BridgeRecord], int]:
    """Records of one datagram and the number of rejected items (malformed msgpack counts as one)."""
    d = decode(data)
    return d.records, len(d.rejected)
