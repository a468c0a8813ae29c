"""Soak test (a tool, not a timed test): the synthetic daemon under hostile input for N minutes, a JSON line a minute.

The daemon is built by the one assembly path (:func:`mocapd.service.assembly.assembled`, as ``mocapd demo
--synthetic``: four synthetic cameras, one suit of 13 simulated Xsens devices on pseudo-terminals) and runs in
this process with its WebSocket stream and viewer, the IMU bridge and the SlimeVR server listening on 127.0.0.1.
A second process (``nice 5``, so the attack's own CPU competes less with the daemon on a small machine) attacks
every door at once:

- a well-behaved WebSocket client that subscribes and counts the frames it receives (the output rate as a game
  engine sees it; it reconnects if dropped, and counts that);
- WebSocket churn: clients that connect, send one of valid subscribes, out-of-range numbers (``rate_hz`` 1e-20,
  a 400-digit integer, NaN), wrong types, unknown keys, bad msgpack/JSON, random bytes or an oversized message,
  read a little and disconnect; the close codes are counted (1011 = the server hit an internal error);
- IMU bridge datagrams: valid records, garbage bytes, out-of-range numbers (t = 1.7e308, NaN quaternions,
  ``pc`` = -5 or 2^63), wrong types, and records from fresh sensor ids;
- SlimeVR datagrams: random bytes and truncated or mangled packets;
- a SlimeVR swarm (issue 34): 64 trackers that each announce sensor ids 0..255 (again every 10 s, as firmware
  repeats unacknowledged sensor infos) and then send only heartbeats, every one of them now and then a datagram
  numbered 2⁶⁴−1; beside them one well-behaved tracker streaming sensor 0 at 100 Hz that also sends a 2⁶⁴−1
  every 10 s: its rotations per second (``slimevr_good_hz``) show whether it is locked out. The swarm fills the
  table (64 trackers, 128 sensors) before the good tracker is answered; since issue 45 a tracker that delivers no
  rotation for 5 s gives its place to a newcomer, so the good one gets in (``good_connected``: in the table and
  not timed out, false when refused or evicted; ``good_in_table``; ``evicted_trackers``);
- Zenoh (issue 34): the soak process receives one remote camera (``zcam`` of host ``hostZ``: the door's
  :class:`~mocapd.pipeline.remote_cameras.RemoteRig` and keypoint source on the daemon's event loop, counting what
  they deliver) over a real Zenoh session on loopback; the attacker process runs the real host (status, clock
  replies, 30 detections a second) and a rogue peer that answers the host's clock queries with 2^62 ns or another
  run id, publishes status for the host with its own run id (also on another host's key), and detections numbered
  2^63−1, stamped an hour ahead, of another run, or garbage: the real camera's delivered rate
  (``zenoh_delivered_hz``) and its clock offset (0 on one machine) show whether the rogue got through;
- HTTP: /status and /metrics polling, and bad requests (garbage request lines, oversized headers, POST, unknown
  paths, half-sent requests that stall) to the status server; viewer file-server requests with path traversal;
- the web surface (issue 45): pages of other sites opening the WebSocket (``Origin: null``, a foreign origin, a
  rebound ``Host: evil.example``), 5 a second, each of which must be refused (``web_ws_opened`` counts breaches);
  heading-reset floods, 10 POSTs a second: the simple requests a page can send (``text/plain``, a form, a foreign
  Origin: 403), a rebound Host (421), and POSTs with ``X-Mocapd-Request`` (200 within the rate limit, else 429);
  one WebSocket asking ``reset_heading`` 20 times a second (``rate_limited``); /status polled under a rebound Host
  (421); the daemon's heading resets a minute (``web.resets_per_min``) show the limit holding;
- every ``--cli-every`` seconds, hostile file commands in child processes (``nice 10``): ``mocapd import mtw`` of a
  FIFO, of a link to ``/dev/zero``, of an export of zero quaternions, with an absurd update rate, a backwards
  counter; ``mocapd import mvnx`` of a FIFO; ``mocapd export`` to ``/dev/full``, a directory, a missing folder, one
  file twice; ``mocapd calibrate convert X X``: each must end with one ``error:`` line and exit 2 within 60 s
  (``cli_refused`` / ``cli_bad``);

while this process unplugs one simulated IMU (its pseudo-terminal goes away, as a USB cable pulled) every
``--unplug-every`` seconds and plugs it back 5 s later. Every minute one JSON line: the output rate the good
client saw, frames the daemon published, missed ticks, RSS, open fds, the rejection counters of every door, the
WebSocket close codes the churn clients got, how many log records of level ERROR or above (and how many with
a traceback) the daemon wrote, and how many log lines of any level it wrote that minute (through the daemon's
repeat filter, :mod:`mocapd.io.log_throttle`, installed as ``mocapd run`` installs it) and the CPU seconds this
process used per second (``daemon_cpu_s_per_s``: the daemon and the simulated suit; on a shared machine the
output rate is the share of the cores the daemon got, this what it spent). The last JSON line is the whole run's
summary; then verdict lines say what was measured against what is needed: the output rate the client saw in
every interval against the configured rate (``--rate-tolerance``, 5 %), whether the well-behaved SlimeVR tracker
was connected, whether a web attack got through. What each attacker costs the daemon per operation:
``tools/bench_attack_cost.py``.

Beside the minute lines, a trace line every second (:mod:`tools.soak_trace`; ``--trace``, by default beside
``--out`` as its name + ``.trace.jsonl``): the daemon's missed and late ticks, the rate the client received, the CPU
of the daemon's process, the attacker process and the other processes, RSS, garbage collections and their pauses
per generation (``/status`` ``gc``), how late the event loop woke the tracer, the tick's CPU by stage, which attacks
ran, the CLI command running, IMU unplugs, SlimeVR evictions, offset estimates, governor changes, log lines by
logger. A minute below the needed rate gets its worst seconds and what co-occurred with them (in its JSON line,
``worst_seconds``, and in the per-minute table printed after the verdicts).

    .venv/bin/python tools/soak.py [--minutes 30] [--interval 60] [--seed 0] [--out soak.jsonl]
        [--rate-tolerance 0.05] [--trace soak.jsonl.trace.jsonl]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import logging
import math
import os
import random
import shutil
import socket
import sys
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from mocapd.service.config import Config

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

# --------------------------------------------------------------------------------------------- the attacker
#
# Runs in its own process; prints its cumulative counters as one JSON line a second.


def _ws_payloads(rng: random.Random) -> list[bytes | str]:
    """One churn client's messages: a mix of valid and hostile requests, msgpack and JSON."""
    import msgpack

    valid = [
        {"type": "subscribe", "encoding": "json"},
        {"type": "subscribe", "encoding": "msgpack", "convention": "unity", "rate_hz": 30},
        {"type": "subscribe", "convention": "unreal", "globals": True},
    ]
    hostile: list[Any] = [
        {"type": "subscribe", "rate_hz": 1e-20},
        {"type": "subscribe", "rate_hz": int("9" * 400)},
        {"type": "subscribe", "rate_hz": float("nan")},
        {"type": "subscribe", "rate_hz": -1},
        {"type": "subscribe", "encoding": 7},
        {"type": "subscribe", "convention": ["x"] * 50},
        {"type": "subscribe", "nope": 1},
        {"type": "unknown"},
        [1, 2, 3],
        "just a string",
        {"type": "subscribe", "subjects": ["a" * 100] * 30},
    ]
    out: list[bytes | str] = []
    for _ in range(rng.randint(1, 4)):
        kind = rng.random()
        if kind < 0.25:
            out.append(json.dumps(rng.choice(valid)))
        elif kind < 0.45:
            out.append(msgpack.packb(rng.choice(valid)))
        elif kind < 0.65:
            obj = rng.choice(hostile)
            try:
                out.append(msgpack.packb(obj))
            except (OverflowError, TypeError, ValueError):  # msgpack cannot carry a 400-digit int: send it as JSON
                out.append(json.dumps(obj))
        elif kind < 0.8:
            obj = rng.choice(hostile)
            out.append(json.dumps(obj, allow_nan=True))
        elif kind < 0.9:
            out.append(rng.randbytes(rng.randint(0, 300)))
        elif kind < 0.95:
            out.append("{" * rng.randint(1, 3000))
        else:
            out.append(b"\x80" * 10_000)  # larger than max_message_bytes: 1009
    return out


def _bridge_datagram(rng: random.Random, n: int) -> bytes:
    import msgpack

    def record(sensor: str) -> dict[str, Any]:
        return {"v": 1, "id": sensor, "t": n / 100.0, "q": [1.0, 0.0, 0.0, 0.0], "a": [0.0, 0.0, 9.81], "pc": n % 65536}

    kind = rng.random()
    if kind < 0.3:
        return bytes(msgpack.packb(record("00B40001")))
    if kind < 0.45:
        return rng.randbytes(rng.randint(0, 200))
    if kind < 0.6:  # out-of-range numbers
        r = record("00B40001")
        bad: list[tuple[str, Any]] = [("t", 1.7e308), ("t", float("nan")), ("t", -math.inf),
                                      ("q", [math.nan, 0, 0, 0]), ("q", [1e308, 1e308, 0, 0]), ("a", [math.inf, 0, 0]),
                                      ("pc", -5), ("pc", 2**63), ("v", 99), ("frame", "XYZ")]  # fmt: skip
        key, value = rng.choice(bad)
        r[key] = value
        return bytes(msgpack.packb(r))
    if kind < 0.7:  # wrong types
        r = record("00B40001")
        r[rng.choice(["t", "q", "a", "id", "pc"])] = rng.choice(["x", None, [], {"a": 1}, True])
        return bytes(msgpack.packb(r))
    if kind < 0.85:  # a fresh sensor id each time
        return bytes(msgpack.packb(record(f"{rng.getrandbits(32):08X}")))
    return bytes(msgpack.packb([record("00B40002")] * rng.randint(1, 50)))


def _http_bad_request(rng: random.Random) -> bytes:
    return rng.choice([
        b"GARBAGE\r\n\r\n",
        b"GET /status HTTP/9\r\n\r\n",
        b"POST /status HTTP/1.1\r\nContent-Length: 5\r\n\r\nhello",
        b"GET /" + b"a" * 10_000 + b" HTTP/1.1\r\n\r\n",
        b"GET /status HTTP/1.1\r\n" + b"X: y\r\n" * 2000 + b"\r\n",
        b"GET /nope HTTP/1.1\r\n\r\n",
        b"\x00\xff" * 100 + b"\r\n\r\n",
        b"GET /status HTTP/1.1\r\n",  # never finishes its headers: the server's read timeout ends it
    ])  # fmt: skip


def _viewer_request(rng: random.Random) -> bytes:
    path = rng.choice(
        ["/", "/../../../etc/passwd", "/%2e%2e/%2e%2e/etc/passwd", "/viewer.js", "/nope", "/" + "x" * 5000]
    )
    return f"GET {path} HTTP/1.1\r\nHost: localhost\r\n\r\n".encode()


#: the heading-reset requests of the web attackers: (label, extra header lines) with a body where a page sends one
_RESET_KINDS = {
    "reset_text": "Content-Type: text/plain\r\nContent-Length: 5\r\n\r\nreset",
    "reset_form": "Content-Type: application/x-www-form-urlencoded\r\nContent-Length: 6\r\n\r\nsuit=x",
    "reset_origin": "Origin: http://evil.example\r\nX-Mocapd-Request: 1\r\n\r\n",
    "reset_asked": "X-Mocapd-Request: soak\r\n\r\n",
}
#: attacker counters that mean a web attack got through (each must stay 0)
WEB_BREACHES = ("web_ws_opened", "reset_text_200", "reset_form_200", "reset_origin_200", "reset_rebound_200",
                "poll_rebound_200")  # fmt: skip


def _reset_request(rng: random.Random, port: int) -> tuple[str, bytes]:
    kind = rng.choice([*_RESET_KINDS, "reset_rebound", "reset_asked"])
    host = f"evil.example:{port}" if kind == "reset_rebound" else f"127.0.0.1:{port}"
    rest = _RESET_KINDS.get(kind, "X-Mocapd-Request: 1\r\n\r\n")
    return kind, f"POST /heading/reset HTTP/1.1\r\nHost: {host}\r\n{rest}".encode()


async def _attack(ports: dict[str, int], seconds: float, seed: int) -> None:
    import msgpack
    from websockets.asyncio.client import connect
    from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidStatus
    from websockets.typing import Origin

    from tools.soak_trace import REPORT_EVERY_S, REPORT_T

    rng = random.Random(seed)
    c: Counter[str] = Counter()
    end = time.monotonic() + seconds

    async def good_client() -> None:
        while time.monotonic() < end:
            try:
                async with connect(f"ws://127.0.0.1:{ports['ws']}/", max_size=None, open_timeout=10) as ws:
                    c["good_connects"] += 1
                    await ws.send(msgpack.packb({"type": "subscribe", "encoding": "msgpack"}))
                    async for msg in ws:
                        if isinstance(msg, bytes) and msgpack.unpackb(msg).get("type") == "frame":
                            c["good_frames"] += 1
                        if time.monotonic() > end:
                            return
            except (OSError, ConnectionClosed, InvalidHandshake, TimeoutError) as exc:
                c[f"good_dropped:{type(exc).__name__}"] += 1
                await asyncio.sleep(0.5)

    async def ws_churn() -> None:
        while time.monotonic() < end:
            try:
                async with connect(f"ws://127.0.0.1:{ports['ws']}/", max_size=None, open_timeout=10,
                                   close_timeout=2) as ws:  # fmt: skip
                    c["churn_connects"] += 1
                    for payload in _ws_payloads(rng):
                        await ws.send(payload)
                    with contextlib.suppress(TimeoutError):
                        async with asyncio.timeout(rng.uniform(0.05, 0.5)):
                            async for _ in ws:
                                c["churn_messages"] += 1
                c["churn_close_1000"] += 1
            except ConnectionClosed as exc:
                code = exc.rcvd.code if exc.rcvd is not None else "none"
                c[f"churn_close_{code}"] += 1
            except InvalidStatus as exc:
                c[f"churn_refused_{exc.response.status_code}"] += 1
            except (OSError, InvalidHandshake, TimeoutError) as exc:
                c[f"churn_error:{type(exc).__name__}"] += 1
            await asyncio.sleep(rng.uniform(0.02, 0.2))

    async def udp(port_key: str, make: Any, per_s: float) -> None:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setblocking(False)
        n = 0
        while time.monotonic() < end:
            n += 1
            with contextlib.suppress(OSError):  # ICMP port unreachable while the daemon is busy: keep going
                sock.sendto(make(n), ("127.0.0.1", ports[port_key]))
                c[f"{port_key}_datagrams"] += 1
            await asyncio.sleep(1 / per_s)
        sock.close()

    def slimevr(n: int) -> bytes:
        kind = rng.random()
        if kind < 0.5:
            return rng.randbytes(rng.randint(0, 128))
        # a plausible header (packet type, packet number) with a mangled or truncated body
        return rng.randint(0, 30).to_bytes(4, "big") + n.to_bytes(8, "big") + rng.randbytes(rng.randint(0, 64))

    async def tcp(port_key: str, request: bytes, label: str) -> None:
        try:
            reader, writer = await asyncio.wait_for(asyncio.open_connection("127.0.0.1", ports[port_key]), 5)
        except (OSError, TimeoutError):
            c[f"{label}_connect_failed"] += 1
            return
        try:
            writer.write(request)
            await writer.drain()
            data = await asyncio.wait_for(reader.read(1 << 20), 5)
            status = data.split(b" ", 2)[1].decode("latin-1") if data.startswith(b"HTTP/1.1 ") else "none"
            c[f"{label}_{status}"] += 1
        except (OSError, TimeoutError, IndexError):
            c[f"{label}_error"] += 1
        finally:
            writer.close()
            with contextlib.suppress(OSError):
                await writer.wait_closed()

    async def http_polling() -> None:
        while time.monotonic() < end:
            target = rng.choice(["/status", "/metrics"])
            await tcp("http", f"GET {target} HTTP/1.1\r\nHost: localhost\r\n\r\n".encode(), f"poll{target[1:]}")
            if rng.random() < 0.2:  # a rebound name reading the device paths: 421
                await tcp("http", f"GET /status HTTP/1.1\r\nHost: evil.example:{ports['http']}\r\n\r\n".encode(),
                          "poll_rebound")  # fmt: skip
            await asyncio.sleep(0.1)

    async def web_ws_foreign() -> None:
        """Other sites' pages opening the WebSocket, 5 a second: every handshake must be refused."""
        port = ports["ws"]
        while time.monotonic() < end:
            kind = rng.choice(["null", "foreign", "rebound"])
            uri = f"ws://evil.example:{port}/" if kind == "rebound" else f"ws://127.0.0.1:{port}/"
            origin = {"null": "null", "foreign": "http://evil.example", "rebound": f"http://evil.example:{port}"}[kind]
            try:
                async with connect(uri, host="127.0.0.1", port=port, origin=Origin(origin), open_timeout=5,
                                   close_timeout=1) as ws:  # fmt: skip
                    c["web_ws_opened"] += 1  # a breach: it would read poses and camera images
                    await ws.send(json.dumps({"type": "subscribe", "cameras": True}))
            except InvalidStatus as exc:
                c[f"web_ws_refused_{exc.response.status_code}"] += 1
            except (OSError, InvalidHandshake, TimeoutError, ConnectionClosed) as exc:
                c[f"web_ws_error:{type(exc).__name__}"] += 1
            await asyncio.sleep(0.2)

    async def reset_flood() -> None:
        """Heading-reset POSTs, 10 a second: a page's simple requests and a rebound Host (refused), and asked
        ones with the header (the rate limit's 200s and 429s)."""
        while time.monotonic() < end:
            label, request = _reset_request(rng, ports["http"])
            await tcp("http", request, label)
            await asyncio.sleep(0.1)

    async def ws_reset_flood() -> None:
        """One WebSocket asking for a heading reset 20 times a second (answered, or rate_limited)."""
        while time.monotonic() < end:
            try:
                async with connect(f"ws://127.0.0.1:{ports['ws']}/", max_size=None, open_timeout=10) as ws:
                    await ws.send(json.dumps({"type": "subscribe", "subjects": ["nobody"], "status": False}))
                    for _ in range(100):
                        await ws.send(json.dumps({"type": "reset_heading"}))
                        with contextlib.suppress(TimeoutError):
                            async with asyncio.timeout(0.05):
                                while True:
                                    m = msgpack.unpackb(await ws.recv())
                                    if m.get("type") == "heading_reset":
                                        c["ws_reset_done"] += 1
                                    elif m.get("type") == "error":
                                        c[f"ws_reset_{m.get('code')}"] += 1
            except (OSError, ConnectionClosed, InvalidHandshake, TimeoutError) as exc:
                c[f"ws_reset_error:{type(exc).__name__}"] += 1
                await asyncio.sleep(0.5)

    async def http_bad() -> None:
        tasks: set[asyncio.Task[None]] = set()
        while time.monotonic() < end:
            t = asyncio.create_task(tcp("http", _http_bad_request(rng), "http_bad"))
            tasks.add(t)
            t.add_done_callback(tasks.discard)
            t2 = asyncio.create_task(tcp("ws", _viewer_request(rng), "viewer"))
            tasks.add(t2)
            t2.add_done_callback(tasks.discard)
            await asyncio.sleep(0.2)
        await asyncio.gather(*tasks, return_exceptions=True)

    async def report() -> None:
        # Twice a second, with the time of the report (CLOCK_MONOTONIC is the machine's: the soak process reads it
        # too): the trace's per-second client rate is the frames between two reports over the time between them.
        while time.monotonic() < end:
            await asyncio.sleep(REPORT_EVERY_S)
            print(json.dumps({**c, REPORT_T: time.monotonic()}), flush=True)

    zenoh_side = _ZenohAttack(ports["zenoh"], rng, c) if "zenoh" in ports else None
    try:
        await asyncio.gather(
            good_client(),
            *(ws_churn() for _ in range(3)),
            udp("bridge", lambda n: _bridge_datagram(rng, n), 200.0),
            udp("slimevr", slimevr, 20.0),
            _slimevr_swarm(ports["slimevr"], end, c),
            _slimevr_good_tracker(ports["slimevr"], end, c),
            *([] if zenoh_side is None else [zenoh_side.run(end)]),
            http_polling(),
            http_bad(),
            web_ws_foreign(),
            reset_flood(),
            ws_reset_flood(),
            report(),
        )
    finally:
        if zenoh_side is not None:
            zenoh_side.close()
    print(json.dumps({**c, REPORT_T: time.monotonic()}), flush=True)


SWARM_TRACKERS = 64
"""Trackers of the SlimeVR swarm (the server's table holds 64)."""
GOOD_MAC = "0B:00:00:00:00:01"
"""The well-behaved SlimeVR tracker's MAC (its sensor 0 is ``0B:00:00:00:00:01/0``)."""


async def _slimevr_swarm(port: int, end: float, c: Counter[str]) -> None:
    """64 trackers announcing sensors 0..255 every 10 s, then heartbeats; each sends a 2^64-1 now and then."""
    from mocapd.protocols.slimevr import Handshake, Heartbeat, SensorInfo, encode_bundle, encode_packet

    socks = []
    for _ in range(SWARM_TRACKERS):
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.bind(("127.0.0.1", 0))
        sock.setblocking(False)
        socks.append(sock)
    numbers = [0] * SWARM_TRACKERS

    def send(k: int, data: bytes) -> None:
        with contextlib.suppress(OSError):
            socks[k].sendto(data, ("127.0.0.1", port))
            c["swarm_datagrams"] += 1

    def nxt(k: int) -> int:
        numbers[k] += 1
        return numbers[k]

    tick = 0
    try:
        while time.monotonic() < end:
            for k in range(SWARM_TRACKERS):
                if tick % 20 == 0:  # every 10 s: (re)introduce itself and announce 256 sensors
                    send(k, encode_packet(Handshake(2, 3, 2, 22, "swarm", f"0A:00:00:00:00:{k:02X}"), 0))
                    numbers[k] = 0
                    for first in range(0, 256, 128):
                        infos = [SensorInfo(i, 1, 3) for i in range(first, first + 128)]
                        send(k, encode_bundle(list(infos), nxt(k), compact=True))
                elif (tick + k) % 37 == 0:
                    send(k, encode_packet(Heartbeat(), 2**64 - 1))  # one absurd packet number
                    c["swarm_absurd_numbers"] += 1
                send(k, encode_packet(Heartbeat(), nxt(k)))
            tick += 1
            await asyncio.sleep(0.5)
    finally:
        for sock in socks:
            sock.close()


async def _slimevr_good_tracker(port: int, end: float, c: Counter[str]) -> None:
    """A tracker streaming sensor 0 at 100 Hz; every 10 s one of its datagrams is numbered 2^64-1. Like the
    firmware, it shakes hands again when it has heard nothing from the server for 3 s (a tracker that went quiet
    and was replaced in the server's table, or a daemon that restarted)."""
    from mocapd.protocols.slimevr import HANDSHAKE_REPLY, Handshake, Rotation, SensorInfo, encode_packet

    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.setblocking(False)
    loop = asyncio.get_running_loop()

    async def handshake() -> None:
        while time.monotonic() < end:  # until answered (the daemon may be busy)
            sock.sendto(encode_packet(Handshake(2, 3, 2, 22, "good", GOOD_MAC), 0), ("127.0.0.1", port))
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(1.0):
                    while await loop.sock_recv(sock, 2048) != HANDSHAKE_REPLY:
                        pass
                    return

    n = 0
    try:
        await handshake()
        heard = time.monotonic()
        k = 0
        while time.monotonic() < end:
            if time.monotonic() - heard > 3.0:
                c["good_tracker_reconnects"] += 1
                await handshake()
                heard, n, k = time.monotonic(), 0, 0
            if k % 100 == 0:
                n += 1
                sock.sendto(encode_packet(SensorInfo(0, 1, 3), n), ("127.0.0.1", port))
            if k % 1000 == 500:
                sock.sendto(encode_packet(Rotation(0, (1.0, 0.0, 0.0, 0.0)), 2**64 - 1), ("127.0.0.1", port))
                c["good_tracker_absurd_numbers"] += 1
            n += 1
            a = 0.001 * (k % 100)
            with contextlib.suppress(OSError):
                sock.sendto(encode_packet(Rotation(0, (math.cos(a), 0.0, 0.0, math.sin(a))), n), ("127.0.0.1", port))
                c["good_tracker_rotations_sent"] += 1
            with contextlib.suppress(OSError, BlockingIOError):
                while sock.recv(2048):  # the server's heartbeats and acks
                    heard = time.monotonic()
            k += 1
            await asyncio.sleep(0.01)
    finally:
        sock.close()


class _ZenohAttack:
    """The attacker's Zenoh side: the real camera host ``hostZ`` and a rogue peer (module docstring)."""

    def __init__(self, port: int, rng: random.Random, c: Counter[str]) -> None:
        import zenoh

        from mocapd.core.sorting import Detections2D
        from mocapd.io.zenoh_link import clock_key, detections_key, status_key
        from mocapd.protocols.remote import CameraState, encode_clock, encode_detections, encode_status

        self.c, self.rng = c, rng
        self.encode_detections, self.encode_status, self.CameraState = encode_detections, encode_status, CameraState
        self.dets = Detections2D.empty(17)
        self.run_id = rng.getrandbits(64)
        self.rogue_run = rng.getrandbits(64)
        self.frame = 0

        def session() -> Any:
            cfg = zenoh.Config()
            for key, value in (("mode", "peer"), ("listen/endpoints", []),
                               ("connect/endpoints", [f"tcp/127.0.0.1:{port}"]),
                               ("scouting/multicast/enabled", False), ("scouting/gossip/enabled", False)):  # fmt: skip
                cfg.insert_json5(key, json.dumps(value))
            return zenoh.open(cfg)

        self.host, self.rogue = session(), session()
        self.started = time.monotonic_ns()
        self.pub = self.host.declare_publisher(detections_key("soak", "zcam"))
        self.status = self.host.declare_publisher(status_key("soak", "hostZ"))
        self.rogue_pub = self.rogue.declare_publisher(detections_key("soak", "zcam"))
        self.rogue_status = self.rogue.declare_publisher(status_key("soak", "hostZ"))
        self.rogue_other = self.rogue.declare_publisher(status_key("soak", "hostY"))

        def real_clock(q: Any) -> None:
            q.reply(q.key_expr, encode_clock("hostZ", self.run_id, time.monotonic_ns()))

        def rogue_clock(q: Any) -> None:  # answers first if it can: 2^62 ns, or another run's clock
            c["zenoh_rogue_clock_replies"] += 1
            run = self.run_id if self.rng.random() < 0.5 else self.rogue_run
            q.reply(q.key_expr, encode_clock("hostZ", run, 2**62 if self.rng.random() < 0.5 else 1))

        self.queryables = [self.host.declare_queryable(clock_key("soak", "hostZ"), real_clock),
                           self.rogue.declare_queryable(clock_key("soak", "hostZ"), rogue_clock)]  # fmt: skip

    async def run(self, end: float) -> None:
        tick = 0
        while time.monotonic() < end:
            now = time.monotonic_ns()
            self.frame += 1
            self.pub.put(self.encode_detections("hostZ", "zcam", self.run_id, self.frame, now, now, 640, 480,
                                                self.dets))  # fmt: skip
            self.c["zenoh_real_frames"] += 1
            if tick % 15 == 0:
                uptime = (now - self.started) / 1e9
                self.status.put(self.encode_status("hostZ", self.run_id, now, uptime, [self.CameraState("zcam",
                                                   self.frame, True)]))  # fmt: skip
            if tick % 2 == 0:
                self._rogue(now)
            tick += 1
            await asyncio.sleep(1 / 30)

    def _rogue(self, now: int) -> None:
        kind = self.rng.randrange(6)
        hour = 3600 * 10**9
        if kind == 0:
            data = self.encode_detections("hostZ", "zcam", self.run_id, 2**63 - 1, now, now, 640, 480, self.dets)
        elif kind == 1:
            data = self.encode_detections("hostZ", "zcam", self.run_id, self.frame + 1, now + hour, now + hour, 640,
                                          480, self.dets)  # fmt: skip
        elif kind == 2:
            data = self.encode_detections("hostZ", "zcam", self.rogue_run, 1, now, now, 640, 480, self.dets)
        elif kind == 3:
            self.rogue_status.put(self.encode_status("hostZ", self.rogue_run, now, 0.5, []))
            self.c["zenoh_rogue_status"] += 1
            return
        elif kind == 4:
            self.rogue_other.put(self.encode_status("hostZ", self.rogue_run, now, 0.5, []))
            self.c["zenoh_rogue_status"] += 1
            return
        else:
            data = self.rng.randbytes(self.rng.randint(0, 200))
        self.rogue_pub.put(data)
        self.c["zenoh_rogue_messages"] += 1

    def close(self) -> None:
        for s in (self.host, self.rogue):
            with contextlib.suppress(Exception):
                s.close()


# --------------------------------------------------------------------------------------------- file doors


def _cli_attacks(folder: Path) -> list[tuple[str, list[str]]]:
    """Hostile ``mocapd`` file commands (module docstring), each expected to refuse with one line, exit 2."""
    src = REPO / "tests" / "data" / "opensense_mtw" / "MT_012005D6_009-001_00B421E6.txt"
    text = src.read_text(encoding="utf-8")
    fifo = folder / "MT_fifo_00B40001.txt"
    if not fifo.exists():
        os.mkfifo(fifo)
    zero = folder / "MT_zero_00B40002.txt"
    if not zero.is_symlink():
        zero.symlink_to("/dev/zero")
    quat = folder / "MT_quat_00B40003.txt"
    quat.write_text("// Update Rate: 100Hz\nPacketCounter\tQuat_q0\tQuat_q1\tQuat_q2\tQuat_q3\n"
                    + "".join(f"{i}\t0\t0\t0\t0\n" for i in range(200)), encoding="utf-8")  # fmt: skip
    rate = folder / "MT_rate_00B421E6.txt"
    rate.write_text(text.replace("// Update Rate: 100.0Hz", "// Update Rate: 1e6Hz"), encoding="utf-8")
    backwards = folder / "MT_back_00B421E6.txt"
    lines = text.splitlines()
    head = [ln for ln in lines if ln.startswith("//")]
    rows = lines[len(head) + 1 :]
    backwards.write_text("\n".join([*head, lines[len(head)], *reversed(rows)]) + "\n", encoding="utf-8")
    mvnx_fifo = folder / "take.mvnx"
    if not mvnx_fifo.exists():
        os.mkfifo(mvnx_fifo)
    session = folder / "session"
    calib = folder / "calib.toml"
    out = [(f"import mtw {p.name}", ["import", "mtw", str(p), "-o", str(folder / f"s-{p.stem}"), "--assign",
                                     f"{p.stem[-8:]}=Hips"]) for p in (fifo, zero, quat, rate, backwards)]  # fmt: skip
    out.append(("import mvnx FIFO", ["import", "mvnx", str(mvnx_fifo), "-o", str(folder / "s-mvnx")]))
    if session.exists():
        for name, target in (("export /dev/full", ["--bvh", "/dev/full"]), ("export dir", ["--csv", str(folder)]),
                             ("export missing folder", ["--bvh", str(folder / "no" / "x.bvh")]),
                             ("export twice", ["--bvh", str(folder / "F"), "--csv", str(folder / "F")])):  # fmt: skip
            out.append((name, ["export", str(session), "--resolved", *target]))
    if calib.exists():
        out.append(("calibrate convert X X", ["calibrate", "convert", str(calib), str(calib)]))
    return out


async def _cli_setup(folder: Path) -> None:
    """A resolved imported session and a calibration file for the export and convert attacks."""
    src = REPO / "tests" / "data" / "opensense_mtw" / "MT_012005D6_009-001_00B421E6.txt"
    for argv in (["import", "mtw", str(src), "-o", str(folder / "session"), "--assign", "00B421E6=Hips"],
                 ["resolve", str(folder / "session"), "--iterations", "2", "--no-smooth"]):  # fmt: skip
        proc = await asyncio.create_subprocess_exec("nice", "-n", "10", sys.executable, "-m", "mocapd", *argv,
                                                    stdout=asyncio.subprocess.DEVNULL,
                                                    stderr=asyncio.subprocess.DEVNULL, cwd=REPO)  # fmt: skip
        await proc.wait()
    from mocapd.sim.camera_hosts import write_ring_calibration

    write_ring_calibration(["cam0", "cam1"], folder / "calib.toml")


def _limit_memory() -> None:
    """A child's address space: 4 GiB (a regression reading /dev/zero whole fails with MemoryError instead of
    taking the shared machine's memory)."""
    import resource

    resource.setrlimit(resource.RLIMIT_AS, (4 << 30, 4 << 30))


async def _run_cli_attacks(
    folder: Path, counts: Counter[str], failures: list[str], now: dict[str, Any] | None = None
) -> None:
    """Run the hostile file commands one after the other; ``now`` (the trace's) says which is running
    (``running``, None between them) and how many were started (``started``)."""
    now = {} if now is None else now
    for name, argv in _cli_attacks(folder):
        now["running"] = name
        now["started"] = now.get("started", 0) + 1
        proc = await asyncio.create_subprocess_exec("nice", "-n", "10", sys.executable, "-m", "mocapd", *argv,
                                                    stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.PIPE,
                                                    cwd=REPO, preexec_fn=_limit_memory)  # fmt: skip
        try:
            _, err = await asyncio.wait_for(proc.communicate(), 60)
        except TimeoutError:
            counts["cli_bad"] += 1
            failures.append(f"{name}: no answer within 60 s")
            continue
        finally:
            now["running"] = None
            if proc.returncode is None:  # timed out, or the soak ended (cancelled) while it ran: never an orphan
                proc.kill()
                await asyncio.shield(proc.wait())
        lines = err.decode(errors="replace").strip().splitlines()
        if proc.returncode == 2 and len(lines) == 1 and lines[0].startswith("error: "):
            counts["cli_refused"] += 1
        else:
            counts["cli_bad"] += 1
            failures.append(f"{name}: exit {proc.returncode}: {(lines or [''])[-1][:200]}")


# --------------------------------------------------------------------------------------------- the daemon side


class _LineCounter(logging.Handler):
    """Counts the log lines the daemon writes (level WARNING and above, after the repeat filter), in all and by
    logger (the trace's ``log_lines``)."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.lines = 0
        self.by_logger: Counter[str] = Counter()

    def emit(self, record: logging.LogRecord) -> None:
        self.lines += 1
        self.by_logger[record.name.removeprefix("mocapd.")] += 1


class _LogCounter(logging.Handler):
    """Counts the daemon's log records of level ERROR and above, and those carrying a traceback."""

    def __init__(self) -> None:
        super().__init__(logging.ERROR)
        self.errors = 0
        self.tracebacks = 0
        self.first: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.errors += 1
        if record.exc_info:
            self.tracebacks += 1
        if len(self.first) < 5:
            self.first.append(f"{record.name}: {record.getMessage()[:200]}")


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def soak_config() -> Config:
    """The shipped config with every door the soak attacks open on free loopback ports: the IMU bridge, the SlimeVR
    server, the status server and the WebSocket stream (``synthetic_config`` of it is the daemon soaked)."""
    from mocapd.service.config import load_config

    cfg = load_config()
    imu = cfg.imu.model_copy(update={
        "bridge": cfg.imu.bridge.model_copy(update={"enabled": True, "port": _free_udp_port()}),
        "slimevr": cfg.imu.slimevr.model_copy(update={"enabled": True, "port": 0}),
    })  # fmt: skip
    return cfg.model_copy(update={
        "daemon": cfg.daemon.model_copy(update={"http_port": 0}),
        "websocket": cfg.websocket.model_copy(update={"port": 0}),
        "imu": imu,
    })  # fmt: skip


def _fds() -> int:
    return len(os.listdir("/proc/self/fd"))


def _free_tcp_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


async def soak(
    minutes: float,
    interval_s: float,
    seed: int,
    unplug_every_s: float,
    cli_every_s: float,
    out: Any,
    rate_tolerance: float = 0.05,
    trace_out: Any = None,
) -> dict[str, Any]:
    import psutil

    from mocapd.io import log_throttle
    from mocapd.io.ws_server import WebSocketStreamServer
    from mocapd.pipeline.remote_cameras import RemoteRig, ZenohKeypointSource
    from mocapd.service.assembly import assembled
    from mocapd.service.config import parse_config
    from mocapd.service.demo.synthetic import synthetic_config
    from tools.soak_trace import REPORT_T, Sample, machine_cpu_s, minute_findings, minute_table, trace_second

    cfg = soak_config()
    logs = _LogCounter()
    lines_out = _LineCounter()
    logging.getLogger().addHandler(logs)
    logging.getLogger().addHandler(lines_out)
    log_throttle.install()  # as `mocapd run` does: repeated lines are a few and a count
    zport = _free_tcp_port()
    zrig = RemoteRig(parse_config({"zenoh": {"rig": "soak", "listen": [f"tcp/127.0.0.1:{zport}"]}}).zenoh, ["hostZ"])
    zcam = ZenohKeypointSource(0, "zcam", "hostZ", zrig, (640, 480), 17, 300_000_000)
    cli_counts: Counter[str] = Counter()
    cli_failures: list[str] = []
    cli_now: dict[str, Any] = {}
    cli_folder = Path(tempfile.mkdtemp(prefix="mocapd-soak-"))
    proc_info = psutil.Process()
    rng = random.Random(seed)
    seconds = minutes * 60.0

    def emit(line: dict[str, Any]) -> None:
        text = json.dumps(line)
        print(text, flush=True)
        if out is not None:
            out.write(text + "\n")
            out.flush()

    with assembled(synthetic_config(cfg)) as demo:
        d = demo.daemon
        task = asyncio.create_task(d.run(), name="daemon")
        await asyncio.wait_for(d.ready.wait(), 600)
        ws = next(s for s in d.sinks if isinstance(s, WebSocketStreamServer))
        assert d.imu.bridge is not None and d.imu.slimevr is not None
        zenoh_task = asyncio.create_task(zcam.run(lambda *_: None))  # delivered frames counted by the source
        rate_hz = float(ws.description.rate_hz)  # the configured output rate the client should see
        need_hz = rate_hz * (1.0 - rate_tolerance)
        ports = {"http": d.http.port, "ws": int(ws.port), "bridge": d.imu.bridge.port, "slimevr": d.imu.slimevr.port,
                 "zenoh": zport}  # fmt: skip
        # The attackers run past the last interval (terminated after it): the intervals start only once the
        # well-behaved client has its first frame, seconds after the attacker process was started.
        cmd = ["nice", "-n", "5", sys.executable, __file__, "--attack", json.dumps(ports),
               "--seconds", str(seconds + 60.0), "--seed", str(seed)]  # fmt: skip
        attacker = await asyncio.create_subprocess_exec(*cmd, stdout=asyncio.subprocess.PIPE)
        latest: dict[str, float] = {}

        async def read_attacker() -> None:
            assert attacker.stdout is not None
            async for line in attacker.stdout:
                with contextlib.suppress(json.JSONDecodeError):
                    latest.update(json.loads(line))

        reader = asyncio.create_task(read_attacker())
        sims = demo.built.simulated.simulators if demo.built.simulated is not None else []
        unplugs = replugs = 0

        async def unplugger() -> None:
            nonlocal unplugs, replugs
            while sims:
                await asyncio.sleep(unplug_every_s)
                sim = rng.choice(sims)
                sim.unplug()
                unplugs += 1
                await asyncio.sleep(5.0)
                sim.replug()
                replugs += 1

        plugging = asyncio.create_task(unplugger())

        async def cli_attacker() -> None:
            await _cli_setup(cli_folder)
            while True:
                await _run_cli_attacks(cli_folder, cli_counts, cli_failures, cli_now)
                await asyncio.sleep(cli_every_s)

        cli = asyncio.create_task(cli_attacker())
        estimates = _count_offset_estimates(d)
        attacker_info = psutil.Process(attacker.pid)  # `nice` execs the interpreter: the same process

        def sample(loop_late_ms: float) -> Sample:
            """The trace's reading: the counters /status reports, read in-process (building the whole /status
            document once a second would be milliseconds of the loop's time a second)."""
            busy, steal = machine_cpu_s()
            try:
                attacker_cpu = sum(attacker_info.cpu_times()[:2])
            except psutil.Error:  # ended (the soak's end)
                attacker_cpu = 0.0
            gov, slime, frame = d.governor, d.imu.slimevr, d.latest
            return Sample(
                t=time.monotonic(), missed=d.plan.missed if d.plan else 0, late=d.plan.late if d.plan else 0,
                published=d.scheduler.published, good_frames=latest.get("good_frames", 0),
                report_t=latest.get(REPORT_T), daemon_cpu_s=sum(proc_info.cpu_times()[:2]), machine_busy_s=busy,
                machine_steal_s=steal, attacker_cpu_s=attacker_cpu, rss_mib=proc_info.memory_info().rss / 2**20,
                gc_collections=list(d.gc_watch.collections), gc_pause_ms=[p / 1e6 for p in d.gc_watch.pause_ns],
                attacker=dict(latest), log_lines=dict(lines_out.by_logger),
                evictions=slime.server.counters.evicted_trackers if slime is not None else 0,
                offset_estimates=int(estimates["count"]), offset_estimate_ms=estimates["ms"], unplugs=unplugs,
                replugs=replugs, cli_started=cli_now.get("started", 0), cli_running=cli_now.get("running"),
                governor_step=None if gov is None else gov.step_index, governor_changes=0 if gov is None else
                gov.changes, loop_late_ms=loop_late_ms,
                stage_cpu_ms={k: v / 1e6 for k, v in d.scheduler.cpu_ns.items()},
                people=0 if frame is None else len(frame.people),
                iterations=0 if frame is None else sum(p.iterations for p in frame.people),
                ws_clients=len(ws.clients), hello_skeletons=len(ws.description.skeletons),
                threads=threading.active_count(), fds=_fds(),
            )  # fmt: skip

        async def tracer() -> None:
            """A trace line a second (:mod:`tools.soak_trace`), on the daemon's event loop: how late it wakes is
            how long the loop was busy with something else."""
            prev = sample(0.0)
            due = prev.t + 1.0
            while True:
                await asyncio.sleep(max(0.0, due - time.monotonic()))
                woke = time.monotonic()
                cpu0 = time.thread_time()
                cur = sample((woke - due) * 1000.0)
                second = trace_second(prev, cur, t_start, interval_s)
                second["tracer_cpu_ms"] = round((time.thread_time() - cpu0) * 1000.0, 2)  # its own cost on the loop
                trace.append(second)
                if trace_out is not None:
                    trace_out.write(json.dumps(second) + "\n")
                    trace_out.flush()
                prev = cur
                due = due + 1.0 if woke - due < 1.0 else woke + 1.0  # a loop stalled > 1 s: on from now

        def counters() -> dict[str, Any]:
            st = d.status()
            ws_stats = ws.stats()
            bridge = st["imu"]["bridge"] or {}
            slime = st["imu"]["slimevr"] or {}
            good_t = d.imu.slimevr.server.trackers.get(GOOD_MAC) if d.imu.slimevr is not None else None
            zst = zcam.status()
            zhost = zrig.status().get("hostZ", {})
            return {
                "slimevr": {
                    "trackers": slime.get("trackers_total", len(slime.get("trackers", []))),
                    "sensors": slime.get("sensors_total", sum(len(t["sensors"]) for t in slime.get("trackers", []))),
                    "refused_sensors": slime.get("refused_sensors"),
                    "number_jumps": slime.get("number_jumps"),
                    "timeouts": slime.get("timeouts"),
                    # the well-behaved tracker, read from the server (/status lists only some trackers)
                    "good_rotations": sum(x.rotations for x in good_t.sensors.values()) if good_t else 0,
                    # in the table and not timed out (False, not null, when it is not in the table at all:
                    # refused or evicted; good_in_table says which)
                    "good_connected": good_t is not None and not good_t.timed_out,
                    "good_in_table": good_t is not None,
                    "good_reordered": None if good_t is None else good_t.reordered,
                    "good_lost": None if good_t is None else good_t.lost,
                    "refused_trackers": slime.get("refused_trackers"),
                    "evicted_trackers": slime.get("evicted_trackers"),
                    "replaced_trackers": slime.get("replaced_trackers"),
                },
                "zenoh": {
                    "received": zst["received"],
                    "delivered": zst["delivered"],
                    "dropped": zst["dropped"],
                    "decode_rejected": zst["decode_rejected"],
                    "host_rejected": zhost.get("rejected"),
                    "clock_offset_ms": zhost.get("clock_offset_ms"),
                    "restarts": zhost.get("restarts"),
                    "round_trips": zhost.get("round_trips"),
                },
                "log_lines": lines_out.lines,
                "cpu_s": sum(proc_info.cpu_times()[:2]),  # this process: the daemon (and the simulated suit)
                "cli": dict(cli_counts),
                "frames_published": st["output"]["frames"],
                "missed_ticks": st["output"]["missed_ticks"],
                "late_ticks": st["output"]["late_ticks"],
                "good_frames": latest.get("good_frames", 0),
                "rejected": {
                    "http_bad_requests": d.http.bad_requests,
                    "ws_refused": ws_stats["refused"],
                    "bridge_rejected": bridge.get("rejected", 0),
                    "slimevr_bad_datagrams": slime.get("bad_datagrams", 0),
                    "slimevr_unknown_source": slime.get("unknown_source", 0),
                },
                "bridge_records": bridge.get("records", 0),
                "sensors": len(st["imu"]["sensors"]),
                "status_bytes": len(d.http.snapshots.status_json()) if hasattr(d.http, "snapshots") else None,
                "imu_disconnects": sum(x["disconnects"] for x in st["imu"]["devices"]),
                "web": {
                    "http_refused": st["http_refused"],
                    "ws_refused": {k: ws_stats["refused"][k] for k in ("host", "origin")},
                    "resets": d.reset_limit.allowed,
                    "resets_refused": d.reset_limit.refused,
                },
            }

        # The first interval starts at the well-behaved client's first frame, not at `ready`: the attacker process
        # that hosts it takes ~2 s to start (an interpreter and its imports), and counting those seconds put 56.3 Hz
        # into a first minute in which the daemon published 58.3 Hz.
        await first_good_frame(latest, attacker, FIRST_FRAME_TIMEOUT_S)
        t_start = time.monotonic()
        trace: list[dict[str, Any]] = []
        tracing = asyncio.create_task(tracer(), name="soak trace")
        prev = counters()
        prev_t = t_start
        rss0 = proc_info.memory_info().rss
        lines: list[dict[str, Any]] = []
        minute = 0
        while time.monotonic() - t_start < seconds and not task.done():
            await asyncio.sleep(min(interval_s, seconds - (time.monotonic() - t_start)))
            now = time.monotonic()
            cur = counters()
            dt = now - prev_t
            minute += 1
            line = {
                "minute": minute,
                "t_s": round(now - t_start, 1),
                "output_hz_client": round((cur["good_frames"] - prev["good_frames"]) / dt, 2),
                "published_hz": round((cur["frames_published"] - prev["frames_published"]) / dt, 2),
                "missed_ticks": cur["missed_ticks"] - prev["missed_ticks"],
                "late_ticks": cur["late_ticks"] - prev["late_ticks"],
                "daemon_cpu_s_per_s": round((cur["cpu_s"] - prev["cpu_s"]) / dt, 3),
                "rss_mib": round(proc_info.memory_info().rss / 2**20, 1),
                "fds": _fds(),
                "rejected": cur["rejected"],
                "bridge_records": cur["bridge_records"],
                "sensors": cur["sensors"],
                "status_bytes": cur["status_bytes"],
                "imu_unplugs": unplugs,
                "imu_disconnects": cur["imu_disconnects"],
                "slimevr": cur["slimevr"],
                "slimevr_good_hz": round(  # (a tracker replaced in the table counts from 0 again)
                    max(0, cur["slimevr"]["good_rotations"] - prev["slimevr"]["good_rotations"]) / dt, 2
                ),
                "zenoh": cur["zenoh"],
                "zenoh_delivered_hz": round((cur["zenoh"]["delivered"] - prev["zenoh"]["delivered"]) / dt, 2),
                "log_lines_per_min": round((cur["log_lines"] - prev["log_lines"]) * 60.0 / dt, 1),
                "cli": cur["cli"],
                "web": {
                    **cur["web"],
                    "resets_per_min": round((cur["web"]["resets"] - prev["web"]["resets"]) * 60 / dt, 1),
                    "breaches": sum(latest.get(k, 0) for k in WEB_BREACHES),
                },
                "loadavg": os.getloadavg(),
                "log_errors": logs.errors,
                "log_tracebacks": logs.tracebacks,
                "attacker": dict(latest),
            }
            # a minute below the rate: its worst seconds from the trace, and what co-occurred with them
            in_it = [x for x in trace if prev_t - t_start < x["t_s"] <= now - t_start + 0.5]
            line.update(minute_findings(line, in_it, need_hz))
            lines.append(line)
            emit(line)
            prev, prev_t = cur, now
        tracing.cancel()
        plugging.cancel()
        cli.cancel()
        zenoh_task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await zenoh_task
        zrig.close()
        if attacker.returncode is None:
            attacker.terminate()
        await attacker.wait()
        reader.cancel()
        daemon_alive = not task.done()
        d.request_stop()
        code = await asyncio.wait_for(task, 30)
    summary = {
        "summary": True,
        "minutes": round((time.monotonic() - t_start) / 60, 2),
        "daemon_alive_to_the_end": daemon_alive,
        "exit_code": code,
        "output_hz_client_min": min((x["output_hz_client"] for x in lines), default=None),
        "output_hz_client_median": sorted(x["output_hz_client"] for x in lines)[len(lines) // 2] if lines else None,
        "missed_ticks_total": sum(x["missed_ticks"] for x in lines),
        "rss_mib_start": round(rss0 / 2**20, 1),
        "rss_mib_end": lines[-1]["rss_mib"] if lines else None,
        "fds_end": lines[-1]["fds"] if lines else None,
        "imu_unplugs": unplugs,
        "status_kb_max": max((round(x["status_bytes"] / 1024, 1) for x in lines if x["status_bytes"]), default=None),
        "log_lines_per_min_median": _median([x["log_lines_per_min"] for x in lines]),
        "log_lines_per_min_max": max((x["log_lines_per_min"] for x in lines), default=None),
        "slimevr_good_hz_min": min((x["slimevr_good_hz"] for x in lines), default=None),
        "slimevr_good_connected_end": lines[-1]["slimevr"]["good_connected"] if lines else None,
        "slimevr_good_in_table_end": lines[-1]["slimevr"]["good_in_table"] if lines else None,
        "slimevr_good_connected_minutes": sum(x["slimevr"]["good_connected"] for x in lines),
        "slimevr_evicted_trackers": lines[-1]["slimevr"]["evicted_trackers"] if lines else None,
        "output_rate_hz": rate_hz,
        "daemon_cpu_s_per_s_median": _median([x["daemon_cpu_s_per_s"] for x in lines]),
        "zenoh_delivered_hz_min": min((x["zenoh_delivered_hz"] for x in lines), default=None),
        "web_breaches": lines[-1]["web"]["breaches"] if lines else None,
        "web_resets_per_min_max": max((x["web"]["resets_per_min"] for x in lines), default=None),
        "web_refused_end": lines[-1]["web"] if lines else None,
        "cli": dict(cli_counts),
        "cli_failures": cli_failures[:10],
        "log_errors": logs.errors,
        "log_tracebacks": logs.tracebacks,
        "first_errors": logs.first,
        "trace_seconds": len(trace),
        "trace_missed_ticks": sum(x["missed"] for x in trace),
        "trace_gc2_collections": sum(x["gc_collections"][2] for x in trace),
        "trace_gc2_pause_ms_max": max((x["gc_pause_ms"][2] for x in trace), default=None),
        "trace_loop_late_ms_max": max((x["loop_late_ms"] for x in trace), default=None),
    }
    shutil.rmtree(cli_folder, ignore_errors=True)
    emit(summary)
    for verdict in verdicts(summary, rate_tolerance):
        print(verdict, flush=True)
    for row in minute_table(lines, need_hz):
        print(row, flush=True)
    return summary


#: how long the well-behaved client may take to get its first frame before the soak gives up
FIRST_FRAME_TIMEOUT_S = 60.0


def _count_offset_estimates(d: Any) -> dict[str, float]:
    """Count the daemon's offset estimates (every 10 s, on its event loop in steps) and their wall time: its
    ``estimate_offsets`` wrapped on this instance (the daemon keeps no count of them)."""
    done = {"count": 0.0, "ms": 0.0}
    estimate = d.estimate_offsets

    async def counted(names: list[str]) -> None:
        t0 = time.monotonic()
        try:
            await estimate(names)
        finally:
            done["count"] += 1
            done["ms"] += (time.monotonic() - t0) * 1000.0

    d.estimate_offsets = counted
    return done


async def first_good_frame(latest: Mapping[str, float], attacker: asyncio.subprocess.Process, timeout_s: float) -> None:
    """Return once the attacker process has reported a frame received by its well-behaved client (``latest``, its
    counters as the reader task updates them); raise :class:`RuntimeError` when the process ended first or no frame
    came within ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while latest.get("good_frames", 0) == 0:
        if attacker.returncode is not None:
            raise RuntimeError(f"the attacker process ended (exit {attacker.returncode}) before its client got a frame")
        if time.monotonic() > deadline:
            raise RuntimeError(f"the well-behaved client got no frame in {timeout_s:g} s")
        await asyncio.sleep(0.05)


def verdicts(summary: dict[str, Any], rate_tolerance: float) -> list[str]:
    """The run's verdict lines: what was measured against what is needed (the output rate first)."""
    rate = summary["output_rate_hz"]
    need = rate * (1.0 - rate_tolerance)
    low, median = summary["output_hz_client_min"], summary["output_hz_client_median"]
    held = low is not None and low >= need
    good_min, good_end = summary["slimevr_good_hz_min"], summary["slimevr_good_connected_end"]
    # Let in but timed out: its sender (the attacker process) fell silent for a second, as on a starved machine.
    good = "CONNECTED" if good_end else "TIMED OUT" if summary.get("slimevr_good_in_table_end") else "LOCKED OUT"
    breaches = summary["web_breaches"]
    return [
        f"verdict: output rate {'HELD' if held else 'NOT HELD'}: the well-behaved client received {median} Hz "
        f"(median of the report intervals), {low} Hz at the lowest, {summary['missed_ticks_total']} missed ticks; "
        f"needed >= {need:.1f} Hz in every interval ({rate:g} Hz configured, {rate_tolerance:.0%} tolerance); "
        f"the daemon's process used {summary['daemon_cpu_s_per_s_median']} CPU s per s (median)",
        f"verdict: SlimeVR tracker {good}: the well-behaved tracker was connected at the end: {good_end} (in the "
        f"table: {summary.get('slimevr_good_in_table_end')}), in {summary['slimevr_good_connected_minutes']} of the "
        "report intervals, "
        f"its rotations {good_min} Hz at the lowest (it sends 100); "
        f"{summary['slimevr_evicted_trackers']} idle swarm trackers evicted",
        f"verdict: web surface {'HELD' if breaches == 0 else 'BREACHED'}: {breaches} web attacks got through",
    ]


def trace_beside(out: Path) -> Path:
    """Where the per-second trace goes by default: beside the soak's ``--out`` file, its name + ``.trace.jsonl``."""
    return out.with_name(out.name + ".trace.jsonl")


def _median(values: list[float]) -> float | None:
    return sorted(values)[len(values) // 2] if values else None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--minutes", type=float, default=30.0)
    ap.add_argument("--interval", type=float, default=60.0, help="seconds between report lines (default 60)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--unplug-every", type=float, default=20.0, help="seconds between IMU unplugs (default 20)")
    ap.add_argument("--cli-every", type=float, default=300.0,
                    help="seconds between rounds of hostile file commands (default 300)")  # fmt: skip
    ap.add_argument("--out", type=Path, default=None, help="also append the JSON lines to this file")
    ap.add_argument("--trace", type=Path, default=None,
                    help="write the per-second trace (JSON lines, tools/soak_trace.py) to this file (default: beside "
                         "--out, its name + .trace.jsonl; none without --out)")  # fmt: skip
    ap.add_argument("--rate-tolerance", type=float, default=0.05,
                    help="the output rate is held when every interval's client rate is within this share of the "
                         "configured rate (default 0.05)")  # fmt: skip
    ap.add_argument("--attack", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--seconds", type=float, default=None, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.attack is not None:
        asyncio.run(_attack(json.loads(a.attack), a.seconds, a.seed))
        return
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr, format="%(levelname)s %(name)s: %(message)s")
    with contextlib.ExitStack() as stack:
        out = stack.enter_context(a.out.open("a")) if a.out is not None else None
        trace_path = a.trace if a.trace is not None else None if a.out is None else trace_beside(a.out)
        trace = stack.enter_context(trace_path.open("w")) if trace_path is not None else None
        summary = asyncio.run(soak(a.minutes, a.interval, a.seed, a.unplug_every, a.cli_every, out,
                                   a.rate_tolerance, trace))  # fmt: skip
    sys.exit(0 if summary["daemon_alive_to_the_end"] and summary["exit_code"] == 0 else 1)


if __name__ == "__main__":
    main()
