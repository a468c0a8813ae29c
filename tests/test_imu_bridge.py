"""IMU bridge input: record format (pure) and the UDP listener on a real loopback socket."""

from __future__ import annotations

import asyncio
import socket

import msgpack
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mocapd.errors import ConfigError
from mocapd.io.imu_bridge import ImuBridgeListener
from mocapd.io.xsens_serial import ImuSample
from mocapd.protocols.imu_bridge import BridgeRecord, decode_datagram, encode_records
from mocapd.protocols.mtdata2 import CoordFrame

REC = BridgeRecord("00B421E6", 12.5, (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 9.81), CoordFrame.ENU, 7)


def test_round_trip_single_and_batch() -> None:
    assert decode_datagram(encode_records([REC])) == ([REC], 0)
    other = BridgeRecord("00B421ED", 12.51, (0.0, 1.0, 0.0, 0.0), (1.0, 2.0, 3.0), CoordFrame.NED, None)
    assert decode_datagram(encode_records([REC, other])) == ([REC, other], 0)


def test_bad_records_are_counted() -> None:
    good = {"v": 1, "id": "00b421e6", "t": 1.0, "q": [2.0, 0, 0, 0], "a": [0, 0, 9.8]}
    bad = [
        {"v": 2, "id": "x", "t": 1.0, "q": [1, 0, 0, 0], "a": [0, 0, 0]},  # version
        {"v": 1, "id": "x", "t": 1.0, "q": [1, 0, 0], "a": [0, 0, 0]},  # short quaternion
        {"v": 1, "id": "x", "t": float("nan"), "q": [1, 0, 0, 0], "a": [0, 0, 0]},
        {"v": 1, "id": "x", "t": 1.0, "q": [1, 0, 0, 0], "a": [0, 0, 0], "frame": "XYZ"},
        "not a map",
    ]
    records, rejected = decode_datagram(msgpack.packb([good, *bad]))
    assert rejected == 6  # the good one has |q| = 2: rejected as not a rotation
    assert records == []
    good["q"] = [1.02, 0, 0, 0]
    records, rejected = decode_datagram(msgpack.packb(good))
    assert rejected == 0 and records[0].sensor == "00B421E6" and records[0].quat == (1.0, 0.0, 0.0, 0.0)
    assert decode_datagram(b"\xc1") == ([], 1)


@settings(deadline=None)  # the machine is shared: no per-example wall-clock limit
@given(st.binary(max_size=200))
def test_arbitrary_datagrams_never_raise(data: bytes) -> None:
    records, rejected = decode_datagram(data)
    assert rejected >= 0 and all(isinstance(r, BridgeRecord) for r in records)


@pytest.mark.asyncio
async def test_listener_receives_from_a_forwarding_socket() -> None:
    got: list[ImuSample] = []
    listener = ImuBridgeListener(got.append, port=0)
    port = await listener.start()
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        for k in range(5):
            t = 10.0 + k / 60
            rec = BridgeRecord("00B421E6", t, (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 9.81), CoordFrame.ENU, k)
            sender.sendto(encode_records([rec]), ("127.0.0.1", port))
        sender.sendto(b"garbage", ("127.0.0.1", port))
        for _ in range(200):
            if len(got) == 5 and listener.stats.rejected == 1:
                break
            await asyncio.sleep(0.01)
    finally:
        sender.close()
        listener.close()
    assert [s.packet_counter for s in got] == [0, 1, 2, 3, 4]
    assert got[1].device_ticks == round((10.0 + 1 / 60) * 10_000)
    assert all(s.host_ns > 0 and s.frame is CoordFrame.ENU for s in got)
    assert listener.stats.datagrams == 6


def test_listener_refuses_non_loopback() -> None:
    with pytest.raises(ConfigError, match="loopback"):
        ImuBridgeListener(lambda s: None, host="0.0.0.0")
