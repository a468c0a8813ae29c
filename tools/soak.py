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
- HTTP: /status and /metrics polling, and bad requests (garbage request lines, oversized headers, POST, unknown
  paths, half-sent requests that stall) to the status server; viewer file-server requests with path traversal;

while this process unplugs one simulated IMU (its pseudo-terminal goes away, as a USB cable pulled) every
``--unplug-every`` seconds and plugs it back 5 s later. Every minute one JSON line: the output rate the good
client saw, frames the daemon published, missed ticks, RSS, open fds, the rejection counters of every door, the
WebSocket close codes the churn clients got, and how many log records of level ERROR or above (and how many with
a traceback) the daemon wrote. The last line is the whole run's summary.

    .venv/bin/python tools/soak.py [--minutes 30] [--interval 60] [--seed 0] [--out soak.jsonl]
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
import socket
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

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


async def _attack(ports: dict[str, int], seconds: float, seed: int) -> None:
    import msgpack
    from websockets.asyncio.client import connect
    from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidStatus

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
            await asyncio.sleep(0.1)

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
        while time.monotonic() < end:
            await asyncio.sleep(1.0)
            print(json.dumps(dict(c)), flush=True)

    await asyncio.gather(
        good_client(),
        *(ws_churn() for _ in range(3)),
        udp("bridge", lambda n: _bridge_datagram(rng, n), 200.0),
        udp("slimevr", slimevr, 20.0),
        http_polling(),
        http_bad(),
        report(),
    )
    print(json.dumps(dict(c)), flush=True)


# --------------------------------------------------------------------------------------------- the daemon side


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


def _fds() -> int:
    return len(os.listdir("/proc/self/fd"))


async def soak(minutes: float, interval_s: float, seed: int, unplug_every_s: float, out: Any) -> dict[str, Any]:
    import psutil

    from mocapd.io.ws_server import WebSocketStreamServer
    from mocapd.service.assembly import assembled
    from mocapd.service.config import load_config
    from mocapd.service.demo.synthetic import synthetic_config

    cfg = load_config()
    imu = cfg.imu.model_copy(update={
        "bridge": cfg.imu.bridge.model_copy(update={"enabled": True, "port": _free_udp_port()}),
        "slimevr": cfg.imu.slimevr.model_copy(update={"enabled": True, "port": 0}),
    })  # fmt: skip
    cfg = cfg.model_copy(update={
        "daemon": cfg.daemon.model_copy(update={"http_port": 0}),
        "websocket": cfg.websocket.model_copy(update={"port": 0}),
        "imu": imu,
    })  # fmt: skip
    logs = _LogCounter()
    logging.getLogger().addHandler(logs)
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
        ports = {"http": d.http.port, "ws": int(ws.port), "bridge": d.imu.bridge.port, "slimevr": d.imu.slimevr.port}
        cmd = ["nice", "-n", "5", sys.executable, __file__, "--attack", json.dumps(ports),
               "--seconds", str(seconds), "--seed", str(seed)]  # fmt: skip
        attacker = await asyncio.create_subprocess_exec(*cmd, stdout=asyncio.subprocess.PIPE)
        latest: dict[str, int] = {}

        async def read_attacker() -> None:
            assert attacker.stdout is not None
            async for line in attacker.stdout:
                with contextlib.suppress(json.JSONDecodeError):
                    latest.update(json.loads(line))

        reader = asyncio.create_task(read_attacker())
        sims = demo.built.simulated.simulators if demo.built.simulated is not None else []
        unplugs = 0

        async def unplugger() -> None:
            nonlocal unplugs
            while sims:
                await asyncio.sleep(unplug_every_s)
                sim = rng.choice(sims)
                sim.unplug()
                unplugs += 1
                await asyncio.sleep(5.0)
                sim.replug()

        plugging = asyncio.create_task(unplugger())

        def counters() -> dict[str, Any]:
            st = d.status()
            ws_stats = ws.stats()
            bridge = st["imu"]["bridge"] or {}
            slime = st["imu"]["slimevr"] or {}
            return {
                "frames_published": st["output"]["frames"],
                "missed_ticks": st["output"]["missed_ticks"],
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
            }

        t_start = time.monotonic()
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
                "rss_mib": round(proc_info.memory_info().rss / 2**20, 1),
                "fds": _fds(),
                "rejected": cur["rejected"],
                "bridge_records": cur["bridge_records"],
                "sensors": cur["sensors"],
                "status_bytes": cur["status_bytes"],
                "imu_unplugs": unplugs,
                "imu_disconnects": cur["imu_disconnects"],
                "log_errors": logs.errors,
                "log_tracebacks": logs.tracebacks,
                "attacker": dict(latest),
            }
            lines.append(line)
            emit(line)
            prev, prev_t = cur, now
        plugging.cancel()
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
        "log_errors": logs.errors,
        "log_tracebacks": logs.tracebacks,
        "first_errors": logs.first,
    }
    emit(summary)
    return summary


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--minutes", type=float, default=30.0)
    ap.add_argument("--interval", type=float, default=60.0, help="seconds between report lines (default 60)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--unplug-every", type=float, default=20.0, help="seconds between IMU unplugs (default 20)")
    ap.add_argument("--out", type=Path, default=None, help="also append the JSON lines to this file")
    ap.add_argument("--attack", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--seconds", type=float, default=None, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.attack is not None:
        asyncio.run(_attack(json.loads(a.attack), a.seconds, a.seed))
        return
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr, format="%(levelname)s %(name)s: %(message)s")
    with contextlib.ExitStack() as stack:
        out = stack.enter_context(a.out.open("a")) if a.out is not None else None
        summary = asyncio.run(soak(a.minutes, a.interval, a.seed, a.unplug_every, out))
    sys.exit(0 if summary["daemon_alive_to_the_end"] and summary["exit_code"] == 0 else 1)


if __name__ == "__main__":
    main()
