"""IMU bridge input format: msgpack records over UDP, for sensors that mocapd cannot talk to directly.

A site that runs the vendor SDK (e.g. Xsens MTw Awinda through the Xsens Device API) forwards each sensor's
samples with a short script (``tools/xsens_sdk_bridge.py``). Each UDP datagram is one msgpack value: a map
(one record) or an array of maps (several records). Version 1 record::

    key     type              meaning
    "v"     int               format version, 1
    "id"    str               sensor id, 8 hex digits as printed on the case (e.g. "00B421E6")
    "t"     float             device time in seconds (the sensor's own clock; any origin, must increase)
    "q"     [4 x float]       orientation (w, x, y, z) of the sensor frame in the device global frame
    "a"     [3 x float]       sensor-frame acceleration, m/s², gravity included
    "frame" str, optional     device global frame of "q": "ENU" (default), "NED" or "NWU"
    "pc"    int, optional     packet counter (0..65535), lets mocapd count dropped samples

Records that do not follow this are counted and skipped, never raised.
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


def _floats(value: object, n: int) -> tuple[float, ...] | None:
    if not isinstance(value, list | tuple) or len(value) != n:
        return None
    if not all(isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) for v in value):
        return None
    return tuple(float(v) for v in value)


def _record(item: object) -> BridgeRecord | None:
    if not isinstance(item, dict) or item.get("v") != VERSION:
        return None
    sensor, t = item.get("id"), item.get("t")
    if not isinstance(sensor, str) or not isinstance(t, int | float) or isinstance(t, bool) or not math.isfinite(t):
        return None
    q, a = _floats(item.get("q"), 4), _floats(item.get("a"), 3)
    frame = _FRAMES.get(str(item.get("frame", "ENU")))
    pc = item.get("pc")
    if q is None or a is None or frame is None or (pc is not None and not isinstance(pc, int)):
        return None
    norm = math.sqrt(sum(v * v for v in q))
    if not 0.9 < norm < 1.1:
        return None
    return BridgeRecord(
        sensor.upper(),
        float(t),
        (q[0] / norm, q[1] / norm, q[2] / norm, q[3] / norm),
        (a[0], a[1], a[2]),
        frame,
        pc,
    )


def decode_datagram(data: bytes) -> tuple[list[BridgeRecord], int]:
    """Records of one datagram and the number of rejected items (malformed msgpack counts as one)."""
    try:
        value = msgpack.unpackb(data, raw=False, strict_map_key=False)
    except (ValueError, msgpack.ExtraData, msgpack.FormatError, msgpack.StackError, TypeError):
        return [], 1
    items = value if isinstance(value, list) else [value]
    records = []
    rejected = 0
    for item in items:
        rec = _record(item)
        if rec is None:
            rejected += 1
        else:
            records.append(rec)
    return records, rejected
