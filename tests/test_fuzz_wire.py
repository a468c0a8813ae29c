"""Fuzzing the wire doors (issue 18): WebSocket client messages (msgpack and JSON), IMU bridge datagrams, SlimeVR
datagrams, and HTTP requests to the status server and the viewer's file server.

The property at every door: no traceback escapes (nothing raises; nothing is logged with a traceback at warning
level or above, which is where asyncio's "Exception in callback" and websockets' "connection handler failed" go),
the door keeps serving afterwards, per-message input creates no unbounded state, and every rejection is counted.

Hypothesis draws the inputs from a fixed seed (``derandomize``: the same examples on every run) with a bounded
budget: the volume runs through the sans-I/O protocol classes, and a few examples of batches go through the real
servers on 127.0.0.1 with real clients (websockets, UDP and TCP sockets).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import socket
import struct
from collections.abc import Iterator
from typing import Any, cast

import msgpack
import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from websockets.asyncio.client import connect

from mocapd.core.skeleton import Skeleton
from mocapd.io.slimevr import SlimeVrListener
from mocapd.io.ws_server import ServerSettings, WebSocketStreamServer, load_web_files
from mocapd.io.xsens_serial import ImuSample
from mocapd.pipeline.imu_ingest import MAX_OTHER_SENSORS, ImuIngest
from mocapd.protocols import ws_stream
from mocapd.protocols.imu_bridge import (
    MAX_ACC,
    MAX_ID_CHARS,
    MAX_PACKET_COUNTER,
    MAX_TIME_S,
    BridgeRecord,
    decode,
    encode_records,
)
from mocapd.protocols.mtdata2 import CoordFrame
from mocapd.protocols.slimevr import HANDSHAKE_REPLY, Handshake, SensorInfo, encode_packet
from mocapd.protocols.slimevr_server import SensorSample, ServerOptions, SlimeVrServer
from mocapd.protocols.ws_stream import (
    ENCODINGS,
    MAX_RATE_HZ,
    MAX_SUBJECTS_PER_REQUEST,
    MIN_RATE_HZ,
    STREAM_CONVENTIONS,
    ClientSession,
    FrameEncoder,
    StreamDescription,
    StreamOptions,
)
from mocapd.service.config.imu import BridgeConfig, ImuConfig
from mocapd.service.http_status import StatusServer
from mocapd.service.imu_inputs import ImuInputs
from tests.ws_support import random_frame

FUZZ = settings(
    derandomize=True,  # the fixed seed: the same examples every run
    database=None,
    deadline=None,  # the machine is shared: no per-example wall-clock limit
    print_blob=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much],
)
SKEL = Skeleton.from_height(1.75)
DESCRIPTION = StreamDescription(60.0, {"default": SKEL}, cameras=(("cam0", 640, 480),), camera_rate_hz=4.0)
FRAME = random_frame(np.random.default_rng(18), 12, ["suit:suit0", "track:1"], SKEL)
MAX_SUBJECT_CHARS = ws_stream.MAX_ID_CHARS
decode_message = ws_stream.decode
ERROR_CODES = {"bad_encoding", "bad_message", "unknown_type", "bad_field", "too_large"}


@contextlib.contextmanager
def tracebacks() -> Iterator[list[str]]:
    """Every log record with a traceback at warning level or above while inside (asyncio's "Exception in
    callback", "Task exception was never retrieved", websockets' "connection handler failed", ...)."""
    found: list[str] = []

    class Catch(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            if record.exc_info or record.exc_text:
                found.append(self.format(record))

    handler = Catch(logging.WARNING)
    handler.setFormatter(logging.Formatter("%(name)s: %(message)s"))
    root = logging.getLogger()
    root.addHandler(handler)
    try:
        yield found
    finally:
        root.removeHandler(handler)


# ---------------------------------------------------------------------------------------------- hostile values
EXTREME_INTS = [0, 1, -1, -5, 65535, 65536, 2**31, 2**32, 2**53 + 1, 2**63 - 1, 2**63, 2**64 - 1, -(2**63)]
EXTREME_FLOATS = [0.0, -0.0, 5e-324, 1e-300, 1e-20, 0.009, 0.01, 59.9, 1e6, 1.0000001e6, 1e9, 2.0**32, 1.7e308,
                  -1.7e308, math.inf, -math.inf, math.nan]  # fmt: skip


def numbers(*, wide: bool) -> st.SearchStrategy[Any]:
    """Ints and floats at and around every edge; ``wide``: ints beyond 64 bits too (JSON carries them)."""
    ints = st.integers(-(10**400), 10**400) if wide else st.integers(-(2**63), 2**64 - 1)
    extremes = EXTREME_INTS + ([10**400, -(10**30)] if wide else [])
    return st.one_of(st.sampled_from(extremes), st.sampled_from(EXTREME_FLOATS), ints, st.floats(), st.booleans())


def values(*, wide: bool) -> st.SearchStrategy[Any]:
    """Any value a decoder can produce: scalars, lists and maps of them (bytes only in msgpack)."""
    scalars = st.one_of(st.none(), numbers(wide=wide), st.text(max_size=12))
    if not wide:
        scalars = scalars | st.binary(max_size=12)
    return st.recursive(
        scalars, lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=3),
        max_leaves=8,
    )  # fmt: skip


def mostly(good: Any, *others: st.SearchStrategy[Any]) -> st.SearchStrategy[Any]:
    """``good`` five times out of six (so that one malformed part at a time gets past the others)."""
    return weighted((5, st.just(good)), (1, st.one_of(*others)))


def weighted(*choices: tuple[int, st.SearchStrategy[Any]]) -> st.SearchStrategy[Any]:
    """One of the strategies, each as often as its weight says (``one_of`` does not weigh its branches)."""
    picks = [k for k, (w, _) in enumerate(choices) for _ in range(w)]
    return st.sampled_from(picks).flatmap(lambda k: choices[k][1])


# ---------------------------------------------------------------------------------------------- WebSocket
def subscribe(*, wide: bool) -> st.SearchStrategy[dict[str, Any]]:
    """Subscribe requests: each field valid, at an edge, or any value; sometimes unknown keys or another type."""
    any_value = values(wide=wide)
    rate = weighted((3, st.floats(MIN_RATE_HZ, 200.0)), (1, st.none()), (2, numbers(wide=wide)), (1, any_value))
    fields = {
        "subjects": weighted(
            (2, st.lists(st.text(max_size=MAX_SUBJECT_CHARS + 20), max_size=MAX_SUBJECTS_PER_REQUEST + 5)),
            (1, st.none()), (1, any_value),
        ),
        "rate_hz": rate,
        "camera_rate_hz": rate,
        "convention": mostly("native", st.sampled_from(STREAM_CONVENTIONS), any_value),
        "encoding": weighted((4, st.sampled_from(ENCODINGS)), (1, any_value)),
        **{k: weighted((4, st.booleans()), (1, any_value)) for k in ("globals", "status", "cameras")},
    }  # fmt: skip
    kind = mostly("subscribe", any_value)
    return st.builds(
        lambda kind, known, extra: {"type": kind, **known, **extra},
        kind,
        st.fixed_dictionaries({}, optional=fields),
        weighted((5, st.just({})), (1, st.dictionaries(st.text(max_size=8), any_value, max_size=2))),
    )


def _msgpack(obj: Any) -> bytes:
    return bytes(msgpack.packb(obj, use_bin_type=True))


def _json(obj: Any) -> str:
    return json.dumps(obj, allow_nan=True)  # NaN and Infinity tokens: Python's json reads them back


def _flip(data: bytes, where: int, mask: int) -> bytes:
    if not data:
        return data
    b = bytearray(data)
    b[where % len(b)] ^= mask | 1
    return bytes(b)


def ws_messages() -> st.SearchStrategy[str | bytes]:
    """What a hostile WebSocket client sends: requests in msgpack (binary) or JSON (text), raw bytes and text,
    and valid requests with a flipped byte."""
    packed = subscribe(wide=False).map(_msgpack)
    return weighted(
        (4, packed),
        (4, subscribe(wide=True).map(_json)),
        (1, st.binary(max_size=200)),
        (1, st.text(max_size=200)),
        (1, st.builds(_flip, packed, st.integers(0, 1000), st.integers(0, 255))),
        (1, values(wide=False).map(_msgpack)),
        (1, values(wide=True).map(_json)),
        (1, st.binary(min_size=4000, max_size=4200)),  # around the server's 4096-byte limit
    )


def check_options(o: StreamOptions, description: StreamDescription) -> None:
    """Every option a client can set is a usable value (what the server does with it cannot overflow)."""
    assert o.encoding in ENCODINGS and o.convention in STREAM_CONVENTIONS
    assert isinstance(o.globals, bool) and isinstance(o.status, bool) and isinstance(o.cameras, bool)
    assert isinstance(o.decimation, int) and 1 <= o.decimation <= math.ceil(description.rate_hz / MIN_RATE_HZ)
    assert MIN_RATE_HZ <= o.camera_rate_hz <= description.camera_rate_hz <= MAX_RATE_HZ
    assert o.subjects is None or (
        len(o.subjects) <= MAX_SUBJECTS_PER_REQUEST and all(0 < len(s) <= MAX_SUBJECT_CHARS for s in o.subjects)
    )
    # What the server computes from them: the camera loop's next due time and sleep, the frame selection.
    assert round(0.9e9 / o.camera_rate_hz) > 0 and 1.0 / o.camera_rate_hz > 0
    assert isinstance(FRAME.frame % o.decimation, int)


@settings(FUZZ, max_examples=400)
@given(st.lists(ws_messages(), min_size=1, max_size=6))
def test_websocket_client_messages_sans_io(messages: list[str | bytes]) -> None:
    session = ClientSession(DESCRIPTION)
    errors = 0
    for m in messages:
        error = session.receive_message(m)
        (reply,) = session.messages_to_send()
        r = decode_message(reply)
        assert isinstance(reply, bytes if session.options.encoding == "msgpack" else str)  # the (new) encoding
        if r["type"] == "error":
            errors += 1
            assert error is not None and r["code"] == error.code and r["code"] in ERROR_CODES and r["message"]
        else:
            assert error is None and r["type"] == "hello" and r["decimation"] == session.options.decimation
        check_options(session.options, DESCRIPTION)
    assert session.errors == errors and session.requests == len(messages)
    # Whatever was accepted, every message for this client still encodes.
    FrameEncoder(FRAME, 1, DESCRIPTION).message(session.options)
    session.status({"uptime_s": 1.0}, 1, {"clients": 1, "sent": 0, "dropped": 0})
    session.hello()


def _size(message: str | bytes) -> int:
    return len(message) if isinstance(message, bytes) else len(message.encode("utf-8"))


async def _ws_round(messages: list[str | bytes]) -> None:
    limit = ServerSettings().max_message_bytes
    srv = WebSocketStreamServer(ServerSettings(port=0, status_hz=0), StreamDescription(60.0, {"default": SKEL}))
    await srv.start()
    try:
        errors = closed = 0
        async with connect(srv.url) as bystander:
            assert decode_message(await bystander.recv())["type"] == "hello"
            ws = await connect(srv.url, max_size=None)
            try:
                assert decode_message(await ws.recv())["type"] == "hello"
                for m in messages:
                    await ws.send(m)
                    if _size(m) > limit:  # closes this client only (1009), which comes back
                        async with asyncio.timeout(5):
                            await ws.wait_closed()
                        assert ws.close_code == 1009
                        closed += 1
                        ws = await connect(srv.url, max_size=None)
                        assert decode_message(await ws.recv())["type"] == "hello"
                        continue
                    async with asyncio.timeout(5):
                        reply = decode_message(await ws.recv())
                    assert reply["type"] in ("hello", "error"), reply
                    errors += reply["type"] == "error"
                await ws.send('{"type": "subscribe", "rate_hz": null, "subjects": null}')  # the session still works
                async with asyncio.timeout(5):
                    assert decode_message(await ws.recv())["type"] == "hello"
                    srv.publish(FRAME)
                    frame = decode_message(await ws.recv())
                    assert decode_message(await bystander.recv())["frame"] == FRAME.frame  # and the others' too
                assert frame["type"] == "frame" and frame["frame"] == FRAME.frame
                st_ = srv.status()
                assert sum(st_["rejected_requests"].values()) == errors and set(st_["rejected_requests"]) <= ERROR_CODES
                assert st_["clients"] == 2 and len(st_["per_client"]) == 2  # the closed ones are gone
            finally:
                await ws.close()
        async with asyncio.timeout(5):
            while srv.clients:
                await asyncio.sleep(0.01)
    finally:
        await srv.aclose()


@settings(FUZZ, max_examples=20)
@given(st.lists(ws_messages(), min_size=3, max_size=15))
def test_websocket_client_messages_to_the_real_server(messages: list[str | bytes]) -> None:
    """A real client on 127.0.0.1: every message is answered (hello or error), errors are counted by code, the
    connection stays open and frames still come."""
    with tracebacks() as found:
        asyncio.run(_ws_round(messages))
    assert found == []


# ---------------------------------------------------------------------------------------------- IMU bridge
def bridge_records() -> st.SearchStrategy[dict[str, Any]]:
    """Records with each field valid most of the time, at an edge, any value, or missing."""
    any_value = values(wide=False)
    unit = st.sampled_from([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0], [0.5, 0.5, 0.5, 0.5], [1.05, 0, 0, 0]])
    fields = {
        "v": mostly(1, any_value),
        "id": weighted((4, st.sampled_from(["00B421E6", "00b421e6", "00B421E7"])), (1, st.text(max_size=70)),
                       (1, any_value)),
        "t": weighted((4, st.floats(-1e5, 1e5)), (1, numbers(wide=False)), (1, any_value)),
        "q": weighted((4, unit), (1, st.lists(numbers(wide=False), min_size=4, max_size=4)), (1, any_value)),
        "a": weighted((4, st.lists(st.floats(-MAX_ACC, MAX_ACC), min_size=3, max_size=3)),
                      (1, st.lists(numbers(wide=False), min_size=3, max_size=3)), (1, any_value)),
        "frame": weighted((4, st.sampled_from(["ENU", "NED", "NWU"])), (1, any_value)),
        "pc": weighted((4, st.integers(0, MAX_PACKET_COUNTER)), (1, numbers(wide=False)), (1, any_value)),
    }  # fmt: skip
    missing: st.SearchStrategy[set[str]] = st.sets(st.sampled_from(sorted(fields)), max_size=2)
    return st.builds(lambda record, gone: {k: v for k, v in record.items() if k not in gone},
                     st.fixed_dictionaries(fields), weighted((3, st.just(set())), (1, missing)))  # fmt: skip


def bridge_datagrams() -> st.SearchStrategy[bytes]:
    one = bridge_records().map(_msgpack)
    return weighted(
        (4, one),
        (2, st.lists(bridge_records(), max_size=5).map(_msgpack)),
        (1, st.builds(_flip, one, st.integers(0, 1000), st.integers(0, 255))),
        (1, st.binary(max_size=120)),
        (1, values(wide=False).map(_msgpack)),
    )


def _items(data: bytes) -> int:
    """Items a datagram holds as the decoder counts them (undecodable: one)."""
    try:
        value = msgpack.unpackb(data, raw=False, strict_map_key=False)
    except (ValueError, TypeError):  # what the decoder catches (msgpack's errors are ValueErrors)
        return 1
    return len(value) if isinstance(value, list) else 1


@settings(FUZZ, max_examples=300)
@given(st.lists(bridge_datagrams(), min_size=1, max_size=8))
def test_imu_bridge_datagrams_sans_io(datagrams: list[bytes]) -> None:
    ingest = ImuIngest(capacity=16, max_other_sensors=8)
    ingest.keep(["00B421E6"])
    for n, data in enumerate(datagrams):
        d = decode(data)
        assert len(d.records) + len(d.rejected) == _items(data)
        for r in d.records:
            assert 0 < len(r.sensor) <= MAX_ID_CHARS and abs(r.device_time_s) <= MAX_TIME_S
            assert all(math.isfinite(v) and abs(v) <= MAX_ACC for v in r.acc)
            assert abs(math.hypot(*r.quat) - 1.0) < 1e-9
            assert r.packet_counter is None or 0 <= r.packet_counter <= MAX_PACKET_COUNTER
            ticks = round(r.device_time_s * 10_000) & 0xFFFFFFFF  # what the listener does with it
            ingest.add(r.sensor, (n + 1) * 1_000_000, device_ticks=ticks, packet_counter=r.packet_counter,
                       quat=r.quat, acc=r.acc)  # fmt: skip
    assert len(ingest.streams) <= 1 + 8


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


async def _bridge_round(datagrams: list[bytes]) -> None:
    """The daemon's IMU inputs with the bridge: datagrams over UDP into the buffers, then /status's IMU part."""
    inputs = ImuInputs(ImuConfig(bridge=BridgeConfig(enabled=True, port=_free_udp_port())))
    inputs.keep_sensors(["00B421E7"])  # a suit's sensor
    listener = inputs.bridge
    assert listener is not None
    port = await listener.start()
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    good = encode_records([BridgeRecord("00B421E6", 5.0, (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 9.8), CoordFrame.ENU, 1)])
    try:
        sent = 0
        for chunk in range(0, len(datagrams), 20):  # bursts the socket's receive buffer holds
            for data in datagrams[chunk : chunk + 20]:
                sender.sendto(data, ("127.0.0.1", port))
                sent += 1
            async with asyncio.timeout(5):
                while listener.stats.datagrams < sent:
                    await asyncio.sleep(0.005)
        sender.sendto(good, ("127.0.0.1", port))  # the door still takes a good record
        async with asyncio.timeout(5):
            while listener.stats.datagrams < sent + 1:
                await asyncio.sleep(0.005)
    finally:
        sender.close()
        listener.close()
    st_ = listener.stats
    assert st_.records + st_.rejected == sum(_items(d) for d in datagrams) + 1
    assert sum(st_.rejections.by_reason.values()) == st_.rejected
    status = inputs.status()
    json.dumps(status, allow_nan=False)  # /status stays valid JSON, whatever the device times and counters were
    sensors = cast(dict[str, Any], status["sensors"])
    assert len(sensors) <= MAX_OTHER_SENSORS + 1 and sensors["00B421E6"]["buffered"] >= 1


@settings(FUZZ, max_examples=15)
@given(st.lists(bridge_datagrams(), min_size=5, max_size=60))
def test_imu_bridge_datagrams_over_udp(datagrams: list[bytes]) -> None:
    with tracebacks() as found:
        asyncio.run(_bridge_round(datagrams))
    assert found == []


# ---------------------------------------------------------------------------------------------- SlimeVR
F32_EXTREMES = [0.0, 1.0, -1.0, 0.5, 3.4e38, -3.4e38, 1e-45, 2000.0, 2001.0, math.inf, -math.inf, math.nan]


def f32() -> st.SearchStrategy[bytes]:
    packed = st.one_of(st.sampled_from(F32_EXTREMES), st.floats(width=32)).map(lambda v: struct.pack(">f", v))
    return st.one_of(packed, st.binary(min_size=4, max_size=4))


def slimevr_packets() -> st.SearchStrategy[tuple[int, bytes]]:
    """(packet type, payload) of the packets that carry numbers, with every number at an edge or any bits."""
    u8 = st.integers(0, 255).map(lambda v: bytes([v]))
    s16 = st.integers(-(2**15), 2**15 - 1).map(lambda v: struct.pack(">h", v))
    mac = st.one_of(st.binary(min_size=6, max_size=6), st.sampled_from([b"\0" * 6, b"\xa1\xb2\xc3\xd4\xe5\xf6"]))
    handshake = st.builds(
        lambda ints, version, fw, m: ints + version + bytes([len(fw)]) + fw + m,
        st.binary(min_size=24, max_size=24), st.integers(0, 2**32 - 1).map(lambda v: struct.pack(">I", v)),
        st.binary(max_size=20), mac,
    )  # fmt: skip

    def join(*parts: st.SearchStrategy[bytes]) -> st.SearchStrategy[bytes]:
        return st.tuples(*parts).map(b"".join)

    return st.one_of(
        st.tuples(st.just(3), handshake),
        st.tuples(st.just(15), join(u8, u8, u8)),
        st.tuples(st.just(17), join(u8, st.sampled_from([b"\x01", b"\x02"]), f32(), f32(), f32(), f32(), u8)),
        st.tuples(st.just(1), join(f32(), f32(), f32(), f32())),
        st.tuples(st.just(4), join(f32(), f32(), f32(), u8)),
        st.tuples(st.just(23), join(u8, s16, s16, s16, s16, s16, s16, s16)),
        st.tuples(st.just(12), join(f32(), f32())),
        st.tuples(st.just(20), join(u8, f32())),
        st.tuples(st.just(10), st.binary(min_size=4, max_size=4)),
        st.tuples(st.integers(0, 300), st.binary(max_size=40)),
    )


def slimevr_datagrams() -> st.SearchStrategy[bytes]:
    number = st.one_of(st.integers(0, 50), st.sampled_from([2**64 - 1, 2**63]))
    single = st.builds(lambda p, n: struct.pack(">IQ", p[0], n) + p[1], slimevr_packets(), number)
    bundle = st.builds(
        lambda ps, n: struct.pack(">IQ", 100, n) + b"".join(struct.pack(">HI", len(p) + 4, t) + p for t, p in ps),
        st.lists(slimevr_packets().filter(lambda p: p[0] != 3), max_size=4), number,
    )  # fmt: skip
    return st.one_of(single, single, bundle, st.builds(_flip, single, st.integers(0, 100), st.integers(0, 255)),
                     st.binary(max_size=60))  # fmt: skip


@settings(FUZZ, max_examples=250)
@given(st.lists(st.tuples(st.integers(0, 90), st.integers(0, 400), slimevr_datagrams()), min_size=1, max_size=40))
def test_slimevr_datagrams_sans_io(steps: list[tuple[int, int, bytes]]) -> None:
    """Many source addresses (more than the table of trackers holds), time passing so that trackers time out."""
    s = SlimeVrServer(ServerOptions(max_trackers=16, timeout_ns=200_000_000, hold_after_ns=20_000_000))
    ingest = ImuIngest(capacity=16, max_other_sensors=8)
    now = 0
    for port, dt_ms, data in steps:
        now += dt_ms * 1_000_000
        s.receive_datagram(data, ("127.0.0.1", 40000 + port), now)
        s.tick(now)
        assert len(s.trackers) <= 16
        for e in s.events_received():
            if isinstance(e, SensorSample):
                assert all(math.isfinite(v) for v in (*e.quat, *e.acc)) and abs(math.hypot(*e.quat) - 1) < 1e-6
                assert max(map(abs, e.acc)) <= 2000.0 + 10.0  # linear acceleration bound + gravity
                ingest.add(e.sensor, e.host_ns, device_ticks=None, packet_counter=None, quat=e.quat, acc=e.acc)
        s.datagrams_to_send()
    status = s.status()
    json.dumps(status, allow_nan=False)  # /status must stay valid JSON
    assert status["datagrams"] == len(steps) and len(status["bad_reasons"]) <= 32
    assert len(ingest.streams) <= 8


async def _slimevr_round(datagrams: list[bytes]) -> None:
    got: list[ImuSample] = []
    listener = SlimeVrListener(got.append, port=0)
    port = await listener.start()
    runner = asyncio.create_task(listener.run())
    hostile = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tracker = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tracker.bind(("127.0.0.1", 0))
    tracker.setblocking(False)
    loop = asyncio.get_running_loop()
    try:
        for k, data in enumerate(datagrams):
            hostile.sendto(data, ("127.0.0.1", port))
            if k % 20 == 19:
                await asyncio.sleep(0.01)
        async with asyncio.timeout(5):
            while listener.server.counters.datagrams < len(datagrams):
                await asyncio.sleep(0.005)
        # A real tracker still gets its handshake answered and its sensor acknowledged.
        tracker.sendto(encode_packet(Handshake(2, 3, 2, 22, "0.6.3", "0A:0B:0C:0D:0E:0F"), 0), ("127.0.0.1", port))
        async with asyncio.timeout(5):
            while (await loop.sock_recv(tracker, 2048)) != HANDSHAKE_REPLY:
                pass
        tracker.sendto(encode_packet(SensorInfo(0, 1, 3), 1), ("127.0.0.1", port))
        async with asyncio.timeout(5):
            while (
                "0A:0B:0C:0D:0E:0F" not in listener.server.trackers
                or not listener.server.trackers["0A:0B:0C:0D:0E:0F"].sensors
            ):
                await asyncio.sleep(0.005)
        status = listener.status()
        json.dumps(status, allow_nan=False)
        c = listener.server.counters
        assert listener.rejections.total == c.bad_datagrams + c.unknown_source + c.unannounced_sensor
    finally:
        listener.close()
        await runner
        hostile.close()
        tracker.close()


@settings(FUZZ, max_examples=15)
@given(st.lists(slimevr_datagrams(), min_size=5, max_size=60))
def test_slimevr_datagrams_over_udp(datagrams: list[bytes]) -> None:
    with tracebacks() as found:
        asyncio.run(_slimevr_round(datagrams))
    assert found == []


# ---------------------------------------------------------------------------------------------- HTTP
TOKEN = "s3cret"
TARGETS = ["/", "/status", "/metrics", "/viewer.js", "/status?x=1", "/../../etc/passwd", "/%2e%2e/%2e%2e/etc/passwd",
           "//", "*", "http://127.0.0.1/status", f"/?token={TOKEN}", "/?token=wrong", "/?token=%ff%fe&token=",
           "/\u00e9", "/" + "a" * 9000, "/viewer.js?" + "&" * 3000]  # fmt: skip
HEADER_NAMES = ["Host", "Origin", "X-Mocapd-Request", "Upgrade", "Connection", "Authorization", "Sec-WebSocket-Key",
                "Sec-WebSocket-Version", "Content-Length", "Transfer-Encoding", "X-" + "y" * 200]  # fmt: skip
HEADER_VALUES = ["127.0.0.1", "evil.example", "http://evil.example", "null", "websocket", "Upgrade", f"Bearer {TOKEN}",
                 "Bearer \u00e9\u00ff", "Basic Zm9v", "dGhlIHNhbXBsZSBub25jZQ==", "13", "-1", "99999999999999999999",
                 "chunked", "", "v" * 9000]  # fmt: skip


def http_requests() -> st.SearchStrategy[bytes]:
    """Request lines and headers, well-formed, malformed or oversized, one part at a time; text in UTF-8
    (surrogates included) or Latin-1; sometimes without the blank line that ends a head; raw bytes."""
    method = mostly("GET", st.sampled_from(["POST", "HEAD", "get", "", "G ET", "GET\0"]), st.text(max_size=8))
    target = st.one_of(st.sampled_from(TARGETS), st.text(max_size=40).map(lambda t: "/" + t))
    version = mostly("HTTP/1.1", st.sampled_from(["HTTP/1.0", "HTTP/2", "", "http/1.1", "HTTP/1.1 x"]),
                     st.text(max_size=8))  # fmt: skip
    header = st.tuples(mostly("Host", st.sampled_from(HEADER_NAMES), st.text(max_size=10)),
                       mostly("127.0.0.1", st.sampled_from(HEADER_VALUES), st.text(max_size=20)))  # fmt: skip
    eol = mostly("\r\n", st.sampled_from(["\n", "\r"]))

    def build(m: str, t: str, v: str, hs: list[tuple[str, str]], nl: str, end: bool, latin: bool, body: bytes) -> bytes:
        text = f"{m} {t} {v}{nl}" + "".join(f"{k}: {x}{nl}" for k, x in hs) + (nl if end else "")
        raw = text.encode("latin-1", "replace") if latin else text.encode("utf-8", "surrogatepass")
        return raw + body

    structured = st.builds(build, method, target, version, st.lists(header, max_size=6), eol,
                           mostly(True, st.just(False)), st.booleans(),
                           mostly(b"", st.binary(max_size=30)))  # fmt: skip
    flood = st.integers(1, 6000).map(lambda n: b"GET / HTTP/1.1\r\n" * n)  # too many or too long header lines
    return weighted((12, structured), (2, st.binary(max_size=300)), (1, flood))


async def _exchange(port: int, request: bytes, *, websockets_server: bool = False) -> bytes:
    """Send a request and read the answer until the server closes (or the head of a 101).

    The sending side is ended at once, so that an incomplete request gets its answer without a time-out; but
    websockets drops a connection whose client ends its side before the answer, so for its server a complete
    head (a blank line) is left open and answered, and anything else is ended after 0.2 s (after an early answer
    to a malformed line, or to nothing: websockets would wait 10 s for the rest).
    """
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    data = b""

    async def read() -> None:
        nonlocal data
        with contextlib.suppress(ConnectionError):
            while chunk := await reader.read(65536):
                data += chunk
                if data.startswith(b"HTTP/1.1 101 ") and b"\r\n\r\n" in data:
                    break  # a WebSocket handshake succeeded: the rest is the stream

    try:
        with contextlib.suppress(ConnectionError):
            writer.write(request)
            await writer.drain()
            if not websockets_server:
                writer.write_eof()
        if websockets_server and b"\r\n\r\n" not in request:
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(0.2):
                    await read()
                return data
            with contextlib.suppress(ConnectionError, OSError):
                writer.write_eof()
        async with asyncio.timeout(10):
            await read()
    finally:
        writer.close()
        with contextlib.suppress(ConnectionError):
            await writer.wait_closed()
    return data


def _status_code(response: bytes) -> int | None:
    """The status code of a complete HTTP/1.1 response whose Content-Length matches its body (None: empty)."""
    if not response:
        return None
    head, sep, body = response.partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    assert sep and lines[0].startswith("HTTP/1.1 "), response[:200]
    headers = {k.lower(): v for k, _, v in (line.partition(": ") for line in lines[1:])}
    code = int(lines[0].split(" ")[1])
    if code != 101:
        assert int(headers["content-length"]) == len(body), response[:200]
    return code


async def _status_server_round(requests: list[bytes]) -> None:
    server = StatusServer(lambda: {"ready": True, "n": 1}, lambda _snapshot: b"mocapd_up 1\n", port=0)
    port = await server.start()
    try:
        codes = [_status_code(await _exchange(port, r)) for r in requests]
        assert set(codes) <= {200, 400, 403, 404, 405, 421, 431, None}, codes
        assert server.bad_requests == sum(1 for c in codes if c in (400, 431))  # every malformed one is counted
        assert server.requests == sum(1 for c in codes if c is not None)
        # every refusal is counted by reason: 421 a Host other than this machine's names, 403 a foreign Origin
        assert server.refused.total == sum(1 for c in codes if c in (403, 421))
        ok = await _exchange(port, b"GET /status HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        assert _status_code(ok) == 200 and json.loads(ok.partition(b"\r\n\r\n")[2]) == {"ready": True, "n": 1}
    finally:
        await server.close()


@settings(FUZZ, max_examples=25)
@given(st.lists(http_requests(), min_size=5, max_size=20))
def test_http_requests_to_the_status_server(requests: list[bytes]) -> None:
    with tracebacks() as found:
        asyncio.run(_status_server_round(requests))
    assert found == []


async def _viewer_round(requests: list[bytes], token: str) -> None:
    srv = WebSocketStreamServer(ServerSettings(port=0, status_hz=0, token=token, max_clients=4),
                                StreamDescription(60.0, {"default": SKEL}))  # fmt: skip
    await srv.start()
    try:
        # All at once: incomplete requests are ended after 0.2 s, and they wait together.
        answers = await asyncio.gather(*(_exchange(srv.port, r, websockets_server=True) for r in requests))
        codes = [_status_code(a) for a in answers]
        # None: websockets closed a request it could not parse (no HTTP answer); 500 would be a handler that failed
        assert set(codes) <= {101, 200, 400, 401, 403, 404, 405, 413, 414, 421, 426, 431, 503, 505, None}, codes
        assert srv.refused["host"] == codes.count(421) and srv.refused["origin"] == codes.count(403)
        assert srv.refused["unauthorised"] == codes.count(401) and srv.refused["not_found"] == codes.count(404)
        files = {body for _, body in load_web_files().values()}  # a 200 is one of the viewer's files, nothing else
        assert all(a.partition(b"\r\n\r\n")[2] in files for a, c in zip(answers, codes, strict=True) if c == 200)
        q = f"?token={token}" if token else ""
        page = await _exchange(
            srv.port, f"GET /{q} HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n".encode(), websockets_server=True
        )
        assert _status_code(page) == 200 and b"viewer.js" in page
        async with asyncio.timeout(5):
            while srv.clients:  # the handshakes that succeeded above have gone
                await asyncio.sleep(0.01)
        async with connect(f"{srv.url}{q}") as ws:
            assert decode_message(await ws.recv())["type"] == "hello"
    finally:
        await srv.aclose()


@settings(FUZZ, max_examples=15)
@given(st.lists(http_requests(), min_size=5, max_size=20), st.sampled_from([TOKEN, ""]))
def test_http_requests_to_the_viewer_file_server(requests: list[bytes], token: str) -> None:
    """The viewer's files on the stream's port (websockets' HTTP parser, mocapd's token rule and file table),
    with and without a token."""
    with tracebacks() as found:
        asyncio.run(_viewer_round(requests, token))
    assert found == []
