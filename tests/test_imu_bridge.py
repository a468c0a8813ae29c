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
from mocapd.protocols.imu_bridge import BridgeRecord, decode, decode_datagram, encode_records
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


GOOD: dict[str, object] = {"v": 1, "id": "00B421E6", "t": 1.0, "q": [1.0, 0.0, 0.0, 0.0], "a": [0.0, 0.0, 9.81]}


@pytest.mark.parametrize(
    ("change", "reason"),
    [
        ({"t": 1.7e308}, "bad time"),  # issue 18 D3: round(t * 10 kHz) overflowed in the listener
        ({"t": -1.7e308}, "bad time"),
        ({"t": 2.0**32 + 1}, "bad time"),
        ({"t": True}, "bad time"),
        ({"pc": -5}, "bad packet counter"),  # issue 18 D12: documented as 0..65535
        ({"pc": 2**63}, "bad packet counter"),
        ({"pc": 65536}, "bad packet counter"),
        ({"pc": True}, "bad packet counter"),
        ({"pc": 1.0}, "bad packet counter"),
        ({"a": [0.0, 0.0, 1e300]}, "bad acceleration"),
        ({"a": [0, 0, 2**64 - 1]}, "bad acceleration"),
        ({"q": [1.0, 0.0, 0.0, True]}, "bad quaternion"),
        ({"id": ""}, "bad id"),
        ({"id": "x" * 65}, "bad id"),
        ({"id": "00B4\n21E6"}, "bad id"),
        ({"frame": None}, "bad frame"),
        ({"v": True}, "bad version"),
    ],
)
def test_out_of_range_numbers_are_rejected_with_a_reason(change: dict[str, object], reason: str) -> None:
    """Issue 18 D3, D12: every number is checked for type, finiteness and range before use."""
    data = msgpack.packb({**GOOD, **change})
    assert decode_datagram(data) == ([], 1)
    d = decode(data)
    assert d.records == [] and d.rejected == [reason]


def test_the_edges_of_each_range_are_accepted() -> None:
    edges: list[dict[str, object]] = [
        {"pc": 0}, {"pc": 65535}, {"t": 2.0**32}, {"t": -(2.0**32)}, {"t": 1.7e9}, {"a": [-2000, 0, 2000.0]},
    ]  # fmt: skip
    for change in edges:
        d = decode(msgpack.packb({**GOOD, **change}))
        assert d.rejected == [] and len(d.records) == 1, change


@pytest.mark.asyncio
async def test_an_overflowing_time_is_rejected_and_counted_not_a_traceback(caplog: pytest.LogCaptureFixture) -> None:
    """Issue 18 D3 on a real socket: the record was counted as accepted and then raised ``OverflowError`` in the
    event loop, once per datagram; now it is counted as rejected, with its reason, and one warning is logged."""
    got: list[ImuSample] = []
    listener = ImuBridgeListener(got.append, port=0)
    port = await listener.start()
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        for change in ({"t": 1.7e308}, {"t": 1.7e308}, {"pc": -5}, {"pc": 2**63}, {"t": 2.0, "pc": 9}):
            sender.sendto(msgpack.packb({**GOOD, **change}), ("127.0.0.1", port))
        for _ in range(300):
            if listener.stats.datagrams == 5:
                break
            await asyncio.sleep(0.01)
    finally:
        sender.close()
        listener.close()
    st = listener.stats
    assert (st.datagrams, st.records, st.rejected) == (5, 1, 4)
    assert st.rejections.as_dict() == {"bad time": 2, "bad packet counter": 2}
    assert [s.packet_counter for s in got] == [9] and got[0].device_ticks == 20_000
    assert not [r for r in caplog.records if r.exc_info], "a traceback was logged"
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warnings) == 1 and warnings[0].startswith("imu bridge: rejected bad time (datagram of ")
