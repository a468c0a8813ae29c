"""The WebSocket stream server with real websockets clients on loopback: hello, frames, subsets, decimation,
conventions, JSON and msgpack, bad and oversized client messages, a stalled client, the token, client limits,
status messages and the viewer files on the same port."""

from __future__ import annotations

import asyncio
import json
import logging
import socket
from collections.abc import AsyncIterator
from dataclasses import replace
from typing import Any

import msgpack
import numpy as np
import pytest
import pytest_asyncio
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosedError, InvalidStatus

from mocapd.core.skeleton import Skeleton
from mocapd.errors import ConfigError
from mocapd.io.ws_server import ServerSettings, WebSocketStreamServer
from mocapd.protocols.conventions import convention
from mocapd.protocols.ws_stream import StreamDescription, StreamOptions, decode
from mocapd.service.config import parse_config
from mocapd.service.config.websocket import WebSocketConfig
from tests.ws_support import fk_from_message, random_frame
from tools.bench_stream import stalled_handshake

SKEL = Skeleton.from_height(1.75)
IDS = ["suit:suit0", "person:1", "person:2", "person:3"]


def health() -> dict[str, Any]:
    output = {"configured_hz": 60.0, "achieved_hz": 60, "frames": 10, "missed_ticks": 0, "latency_s": 0.15}
    return {
        "uptime_s": 3.0,
        "output": output,
        "latency_ms": {"end_to_end": {"p50": 160.0, "p95": 170.0, "p99": 175.0}},
        "cameras": [{"name": "cam0", "kind": "synthetic", "frames": 9}],
        "imu": {"devices": []},
        "tasks": {},
    }


@pytest_asyncio.fixture
async def server() -> AsyncIterator[WebSocketStreamServer]:
    srv = WebSocketStreamServer(ServerSettings(port=0, status_hz=0), StreamDescription(60.0, {"default": SKEL}))
    await srv.start()
    yield srv
    await srv.aclose()


async def recv(ws: ClientConnection, kind: str, timeout: float = 5.0) -> dict[str, Any]:
    """The next message of this type (others are skipped)."""
    async with asyncio.timeout(timeout):
        while True:
            m = decode(await ws.recv())
            if m["type"] == kind:
                return dict(m)


async def publish_until(srv: WebSocketStreamServer, ws: ClientConnection, frames: range, rng: Any) -> list[Any]:
    """Publish frames (one per loop turn) and collect the frame messages this client gets."""
    got: list[Any] = []
    for n in frames:
        srv.publish(random_frame(rng, n, IDS, SKEL))
        await asyncio.sleep(0.002)
    async with asyncio.timeout(5):
        while not got or got[-1]["frame"] < frames[-1] - frames.step + 1:
            m = decode(await ws.recv())
            if m["type"] == "frame":
                got.append(m)
    return got


@pytest.mark.asyncio
async def test_hello_then_frames_subset_and_decimation(server: WebSocketStreamServer) -> None:
    rng = np.random.default_rng(0)
    async with connect(server.url) as ws:
        hello = await recv(ws, "hello")
        assert (
            hello["v"] == 1 and hello["convention"] == "native" and len(hello["skeletons"]["default"]["offsets"]) == 63
        )
        got = await publish_until(server, ws, range(0, 6), rng)
        assert [m["frame"] for m in got] == list(range(6))
        assert [s["id"] for s in got[0]["subjects"]] == IDS and "joints" not in got[0]["subjects"][0]
        await ws.send(json.dumps({"type": "subscribe", "subjects": ["person:2"], "rate_hz": 20}))
        h2 = await recv(ws, "hello")
        assert h2["decimation"] == 3 and h2["subjects"][2] == {"id": "person:2", "skeleton": "default"}
        got = await publish_until(server, ws, range(6, 19), rng)
        assert [m["frame"] for m in got] == [6, 9, 12, 15, 18]
        assert all([s["id"] for s in m["subjects"]] == ["person:2"] for m in got)


@pytest.mark.asyncio
@pytest.mark.parametrize("encoding", ["json", "msgpack"])
@pytest.mark.parametrize("conv", ["native", "unity", "unreal"])
async def test_conventions_round_trip_over_the_wire(server: WebSocketStreamServer, conv: str, encoding: str) -> None:
    rng = np.random.default_rng(1)
    async with connect(server.url) as ws:
        await recv(ws, "hello")
        await ws.send(json.dumps({"type": "subscribe", "convention": conv, "encoding": encoding, "globals": True}))
        raw = await ws.recv()
        assert isinstance(raw, str if encoding == "json" else bytes)  # text vs binary WebSocket messages
        hello = decode(raw)
        frame = random_frame(rng, 7, IDS, SKEL)
        server.publish(frame)
        f = await recv(ws, "frame")
    c = convention(conv)
    offsets = hello["skeletons"]["default"]["offsets"]
    for sent, solved in zip(f["subjects"], frame.people, strict=True):
        expected = c.positions(solved.joints)
        np.testing.assert_allclose(fk_from_message(sent["root"], sent["rot"], offsets), expected, atol=1e-4 * c.scale)
        np.testing.assert_allclose(np.reshape(sent["joints"], (21, 3)), expected, atol=1e-4 * c.scale)


@pytest.mark.asyncio
async def test_bad_messages_get_errors_and_the_server_keeps_serving(server: WebSocketStreamServer) -> None:
    rng = np.random.default_rng(2)
    async with connect(server.url) as ws, connect(server.url) as other:
        await recv(ws, "hello")
        await recv(other, "hello")
        for bad in ("nonsense", '{"type": "subscribe", "convention": "blender"}', b"\xc1\x00"):
            await ws.send(bad)
            err = await recv(ws, "error")
            assert err["code"] in {"bad_encoding", "bad_field"} and err["message"]
        got = await publish_until(server, ws, range(3), rng)
        assert [m["frame"] for m in got] == [0, 1, 2]
        assert [m["frame"] for m in await publish_until(server, other, range(3, 5), rng)][-1] == 4
    async with asyncio.timeout(5):
        while server.clients:  # the server notices both closes
            await asyncio.sleep(0.01)


@pytest.mark.asyncio
async def test_extreme_rates_get_bad_field_over_the_wire_and_are_counted(
    server: WebSocketStreamServer, caplog: pytest.LogCaptureFixture
) -> None:
    """Issue 18 D1, D2 on a real connection: the client got 1011 (internal error) from an OverflowError; now a
    ``bad_field`` error, the connection stays open and the rejection is counted in the server's /status section."""
    rng = np.random.default_rng(4)
    async with connect(server.url) as ws:
        await recv(ws, "hello")
        for bad in (
            msgpack.packb({"type": "subscribe", "rate_hz": 1e-20}),
            '{"type": "subscribe", "rate_hz": 1e-20}',
            '{"type": "subscribe", "rate_hz": ' + "4" * 400 + "}",
        ):
            await ws.send(bad)
            err = await recv(ws, "error")
            assert err["code"] == "bad_field" and "rate_hz" in err["message"]
        got = await publish_until(server, ws, range(2), rng)
        assert [m["frame"] for m in got] == [0, 1]
        assert server.status()["rejected_requests"] == {"bad_field": 3}
        assert server.status()["per_client"][0]["errors"] == 3
    assert not [r for r in caplog.records if r.exc_info], "a traceback was logged"
    assert [r.getMessage() for r in caplog.records if "rejected" in r.getMessage()][:1] == [
        "websocket: rejected bad_field (client 1: rate_hz = 1e-20; allowed: a number from 0.01 to 1e+06 Hz, or nil "
        "for every frame); 1 rejected so far (counts per reason in /status)"
    ]


@pytest.mark.asyncio
async def test_an_oversized_message_closes_that_client_only(server: WebSocketStreamServer) -> None:
    rng = np.random.default_rng(3)
    async with connect(server.url) as ws, connect(server.url) as other:
        await recv(ws, "hello")
        await recv(other, "hello")
        await ws.send("x" * 5000)  # over max_message_bytes = 4096
        with pytest.raises(ConnectionClosedError) as info:
            await recv(ws, "frame")
        assert info.value.rcvd is not None and info.value.rcvd.code == 1009
        assert [m["frame"] for m in await publish_until(server, other, range(4), rng)] == [0, 1, 2, 3]
        assert len(server.clients) == 1


def stalled_client(port: int) -> socket.socket:
    """A real WebSocket client that completes the handshake and then never reads (tiny receive buffer)."""
    return stalled_handshake(port)


@pytest.mark.asyncio
async def test_a_stalled_client_loses_frames_while_others_get_every_one() -> None:
    rng = np.random.default_rng(4)
    settings = ServerSettings(port=0, status_hz=0, defaults=StreamOptions(encoding="json", globals=True))
    server = WebSocketStreamServer(settings, StreamDescription(60.0, {"default": SKEL}))
    await server.start()
    stalled = await asyncio.get_running_loop().run_in_executor(None, stalled_client, server.port)
    try:
        async with connect(server.url) as ws:
            await recv(ws, "hello")
            frames = [random_frame(rng, n, IDS, SKEL) for n in range(40)]
            got: list[int] = []

            async def read() -> None:
                while not got or got[-1] != 1499:
                    m = decode(await ws.recv())
                    if m["type"] == "frame":
                        got.append(m["frame"])

            reader = asyncio.create_task(read())
            for n in range(1500):  # ~12 kB per JSON frame: far more than the socket buffers hold
                server.publish(replace(frames[n % 40], frame=n))
                await asyncio.sleep(0)
            await asyncio.wait_for(reader, 10)
            stats = {c["client"]: c for c in server.stats()["per_client"]}
            slow = stats[min(stats)]
            assert slow["dropped"] > 1000 and slow["sent"] < 500  # the stalled one: stuck, dropping the oldest
            fast = stats[max(stats)]
            assert fast["dropped"] == 0 and got == list(range(1500))
    finally:
        stalled.close()
        await server.aclose()


@pytest.mark.asyncio
async def test_token_required_off_loopback_and_enforced_when_set() -> None:
    with pytest.raises(
        ConfigError, match=r"websocket\.host = '0\.0\.0\.0' is not loopback: websocket\.token = '' must then be set"
    ):
        websocket({"host": "0.0.0.0"})
    with pytest.raises(ConfigError, match="at least 16"):
        websocket({"host": "192.168.1.5", "token": "short"})
    cfg = websocket({"host": "0.0.0.0", "token": "a-long-enough-secret"})
    assert not cfg.loopback and websocket({"host": "127.0.0.2"}).loopback
    # The server enforces a configured token on any address (bound to loopback here: tests never leave it).
    srv = WebSocketStreamServer(ServerSettings(port=0, token=cfg.token), StreamDescription(60.0, {"d": SKEL}))
    await srv.start()
    try:
        base = f"ws://127.0.0.1:{srv.port}/"
        with pytest.raises(InvalidStatus) as info:
            await connect(base).__aenter__()
        assert info.value.response.status_code == 401
        with pytest.raises(InvalidStatus):
            await connect(base + "?token=wrong-secret-of-same-len").__aenter__()
        async with connect(base + "?token=a-long-enough-secret") as ws:
            assert (await recv(ws, "hello"))["type"] == "hello"
        async with connect(base, additional_headers={"Authorization": "Bearer a-long-enough-secret"}) as ws:
            assert (await recv(ws, "hello"))["type"] == "hello"
        assert (await http_get(srv.port, "/"))[0] == 401
        assert (await http_get(srv.port, "/?token=a-long-enough-secret"))[0] == 200
        # The page's own script is fetched by the browser without the page's query: it must load, or the viewer
        # of a token-guarded daemon is a blank page (it was refused with 401).
        assert (await http_get(srv.port, "/viewer.js"))[0] == 200
        assert srv.refused["unauthorised"] == 3
    finally:
        await srv.aclose()


async def http_get(port: int, target: str) -> tuple[int, dict[str, str], bytes]:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(f"GET {target} HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n".encode())
    await writer.drain()
    data = await reader.read()
    writer.close()
    head, _, body = data.partition(b"\r\n\r\n")
    lines = head.decode().split("\r\n")
    return int(lines[0].split(" ")[1]), dict(line.split(": ", 1) for line in lines[1:]), body


@pytest.mark.asyncio
async def test_viewer_files_client_limit_and_status_messages() -> None:
    settings = ServerSettings(port=0, max_clients=2, status_hz=20.0, defaults=StreamOptions(encoding="json"))
    srv = WebSocketStreamServer(settings, StreamDescription(60.0, {"default": SKEL}), status=health)
    await srv.start()
    try:
        code, headers, body = await http_get(srv.port, "/")
        assert code == 200 and headers["Content-Type"].startswith("text/html") and b"viewer.js" in body
        code, headers, body = await http_get(srv.port, "/viewer.js")
        assert code == 200 and headers["Content-Type"] == "text/javascript" and b"mocapdViewer" in body
        assert (await http_get(srv.port, "/secrets"))[0] == 404
        async with connect(srv.url) as a, connect(srv.url) as b:
            assert isinstance(await a.recv(), str)  # json by configured default
            with pytest.raises(InvalidStatus) as info:
                await connect(srv.url).__aenter__()
            assert info.value.response.status_code == 503 and srv.refused["full"] == 1
            st = await recv(b, "status")
            assert st["output"]["configured_hz"] == 60.0 and st["stream"]["clients"] == 2
            assert st["latency_ms"]["end_to_end"]["p95"] == 170.0
            await a.send(json.dumps({"type": "subscribe", "status": False}))
            await recv(a, "hello")
            srv.publish(random_frame(np.random.default_rng(5), 0, IDS, SKEL))
            assert (await recv(a, "frame"))["frame"] == 0
    finally:
        await srv.aclose()


@pytest.mark.asyncio
async def test_bytes_after_a_request_head_are_dropped_not_a_traceback(caplog: pytest.LogCaptureFixture) -> None:
    """Found by the wire fuzzing of issue 18: a GET followed by bytes that are not a WebSocket frame (a body,
    pipelined requests) made websockets fail its own assertion when it sent the answer: "unexpected internal
    error" with a traceback per request. Such a connection is now dropped unanswered, and counted."""
    srv = WebSocketStreamServer(ServerSettings(port=0, status_hz=0), StreamDescription(60.0, {"default": SKEL}))
    await srv.start()
    try:
        for tail in (b"\x00\x00", b"GET / HTTP/1.1\r\n\r\n", b"x"):
            reader, writer = await asyncio.open_connection("127.0.0.1", srv.port)
            writer.write(b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n" + tail)
            async with asyncio.timeout(5):
                answer = await reader.read()
            writer.close()
            assert answer.startswith(b"HTTP/1.1 200 ") == (tail == b"x"), answer[:40]  # one byte is no frame yet
        await asyncio.sleep(0.05)  # the handshakes end after the connections close
        assert not [r for r in caplog.records if r.exc_info and r.levelno >= logging.WARNING], "a traceback was logged"
        assert srv.refused["bad_request"] == 2
        code, _, body = await http_get(srv.port, "/")
        assert code == 200 and b"viewer.js" in body
    finally:
        await srv.aclose()


@pytest.mark.asyncio
async def test_a_port_in_use_is_a_clear_error(server: WebSocketStreamServer) -> None:
    other = WebSocketStreamServer(ServerSettings(port=server.port), StreamDescription(60.0, {"d": SKEL}))
    with pytest.raises(ConfigError, match=f"cannot listen on 127.0.0.1:{server.port}.*\\[websocket\\] port"):
        await other.start()


def test_config_defaults_and_errors() -> None:
    d = websocket({})
    assert d.enabled and d.host == "127.0.0.1" and d.port == 8766 and d.encoding == "msgpack"
    assert d.model_copy(update={"port": 1}).port == 1
    for bad, says in (({"port": 70000}, r"websocket.port = 70000; allowed: an integer in \[0, 65535\]"),
                      ({"encoding": "xml"}, "websocket.encoding = 'xml'; allowed: \"msgpack\" or \"json\""),
                      ({"colour": 1}, "unknown key websocket.colour"),
                      ({"status_hz": -1}, r"websocket.status_hz = -1; allowed: a number in \[0, 60\]"),
                      ({"globals": "yes"}, "websocket.globals = 'yes'; allowed: true or false"),
                      ({"convention": "maya"}, "websocket.convention = 'maya'; allowed: \"native\", \"unity\""),
                      ({"host": "example.com"}, "websocket.host = 'example.com': allowed: an IP address"),
                      ({"token": "a b"}, "websocket.token = 'a b': allowed: printable ASCII")):  # fmt: skip
        with pytest.raises(ConfigError, match=says):
            websocket(bad)


@pytest.mark.asyncio
async def test_a_persons_sized_skeleton_arrives_in_a_new_hello_before_its_frames(
    server: WebSocketStreamServer,
) -> None:
    """Body sizing gives a person their own skeleton mid-stream: clients get a hello naming it before the first
    frame that uses it, and that frame's joints follow from its offsets."""
    rng = np.random.default_rng(5)
    tall = Skeleton.from_height(1.95)
    async with connect(server.url) as ws:
        first = await recv(ws, "hello")
        assert set(first["skeletons"]) == {"default"}
        server.publish(random_frame(rng, 1, IDS[:1], SKEL))
        assert (await recv(ws, "frame"))["subjects"][0]["skeleton"] == "default"
        frame = random_frame(rng, 2, IDS[:1], SKEL)
        sized = replace(frame, people=[replace(frame.people[0], skeleton=tall)])
        server.publish(sized)
        kinds = []
        async with asyncio.timeout(5):
            while "frame" not in kinds:
                kinds.append(decode(msg := await ws.recv())["type"])
                if kinds[-1] == "hello":
                    hello = decode(msg)
                elif kinds[-1] == "frame":
                    got = decode(msg)
        assert kinds == ["hello", "frame"]
        key = got["subjects"][0]["skeleton"]
        assert key != "default" and key in hello["skeletons"]
        offsets = hello["skeletons"][key]["offsets"]
        np.testing.assert_allclose(np.reshape(offsets, (21, 3)), tall.offsets, atol=1e-5)
        server.publish(replace(sized, frame=3))  # the same skeleton again: no further hello
        assert decode(await ws.recv())["type"] == "frame"
        copy = Skeleton(offsets=tall.offsets.copy(), root_height=tall.root_height, height=tall.height)
        server.publish(replace(sized, frame=4, people=[replace(sized.people[0], skeleton=copy)]))  # a replayed copy
        again = decode(await ws.recv())
        assert again["type"] == "frame" and again["subjects"][0]["skeleton"] == key


def websocket(table: dict[str, Any]) -> WebSocketConfig:
    return parse_config({"websocket": table}).websocket


@pytest.mark.asyncio
async def test_the_hello_forgets_the_skeletons_of_people_gone_for_a_while(server: WebSocketStreamServer) -> None:
    """Every new client and accepted subscribe gets a hello with every skeleton it lists (the soak's churn clients:
    ~10 a second). The skeletons of tracks that had come and gone stayed in it until 64 piled up, so a long run's
    later hellos cost more (3 skeletons 0.2 ms to build, 64 3.4 ms, in JSON); a skeleton no frame has used for
    ``skeleton_keep_frames`` (10 s of frames) now leaves it when a new one joins. One used a frame ago stays: a frame
    still queued for a client may name it after the new hello."""
    rng = np.random.default_rng(7)
    server.skeleton_keep_frames = 3
    for n in range(40):  # a person a frame, each of their own size: tracks that come and go
        frame = random_frame(rng, n, [f"person:{n}"], SKEL)
        server.publish(replace(frame, people=[replace(frame.people[0], skeleton=Skeleton.from_height(1.5 + n / 100))]))
    async with connect(server.url) as ws:
        hello = await recv(ws, "hello")
    kept = set(hello["skeletons"]) - {"default"}
    # the last three people's skeletons (used within the last 3 frames), and no older one; 41 before
    assert kept == {"person:37#38", "person:38#39", "person:39#40"}
    assert len(server._key_of) == 3  # nor the identities of the people gone
