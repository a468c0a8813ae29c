"""What each attacker of the soak costs the daemon: CPU seconds per attack operation (a developer tool).

Developer benchmark, not a ``mocapd bench`` verb (those are the benchmarks a user runs).

The synthetic daemon is assembled in this process as ``tools/soak.py`` assembles it (the one assembly path, the
SlimeVR server on loopback), and its doors are started as the daemon starts them (the status server, the SlimeVR
server, the WebSocket stream) but not its tick: on a machine shared with other work the tick takes whatever share
of the cores it gets, and its elastic cost would hide the doors'. Then, for each attack kind, a quiet phase and an
attack phase of ``--phase`` seconds alternate ``--repeats`` times; in an attack phase a child process (``nice 5``,
set up once per kind) does that one kind of operation at a fixed rate. The cost of one operation, per pair of
phases, is the CPU time of the event loop's thread and the SlimeVR receive thread in the attack phase less the
quiet phase's rate times its length, divided by the operations done; the median of the pairs is reported beside
each pair's value (their spread is the measurement's noise). CPU time, not the output rate: on a shared machine
the output rate says what share of the cores the daemon got, the CPU time what it spent. /status comes from this
daemon, which has not ticked (a document of the same shape; a running daemon's is larger).

Kinds (each one operation as the soak's attacker does it):

- ``ws_foreign``: a WebSocket handshake from another site's page (``Origin: http://evil.example``): refused (403);
- ``ws_churn``: a WebSocket client that connects, subscribes, reads for 0.1 s and leaves;
- ``reset_http``: a ``POST /heading/reset``, alternately a page's simple request (403) and one with
  ``X-Mocapd-Request`` (200 within the rate limit, else 429);
- ``ws_reset``: ``reset_heading`` on one open WebSocket (answered, or ``rate_limited``);
- ``status_poll``: ``GET /status``;
- ``slimevr_bundle``: a bundle of 128 sensor infos from one of 64 trackers that shook hands (the soak's swarm:
  all of them refused, the budget being full);
- ``slimevr_unknown``: the same bundle from an address that never shook hands (a forgotten swarm tracker);
- ``slimevr_heartbeat``: a heartbeat from one of the 64;
- ``bridge_mix``: an IMU bridge datagram of the soak's mix (valid records, garbage, out-of-range numbers, wrong
  types, fresh sensor ids, 1-50 records at once).

    nice -n 19 .venv/bin/python tools/bench_attack_cost.py [--kinds ws_foreign,status_poll] [--phase 6]
        [--repeats 2] [--out cost.json]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import random
import socket
import sys
import threading
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

#: operations a second each kind is driven at (low enough that a loaded machine keeps up, high enough to measure)
RATES = {
    "ws_foreign": 40.0,
    "ws_churn": 10.0,
    "reset_http": 40.0,
    "ws_reset": 40.0,
    "status_poll": 40.0,
    "slimevr_bundle": 40.0,
    "slimevr_unknown": 40.0,
    "slimevr_heartbeat": 400.0,
    "bridge_mix": 200.0,
}
SWARM = 64


# --------------------------------------------------------------------------------------------- the attacker
async def _tcp(port: int, request: bytes) -> bytes:
    reader, writer = await asyncio.wait_for(asyncio.open_connection("127.0.0.1", port), 5)
    try:
        writer.write(request)
        await writer.drain()
        return await asyncio.wait_for(reader.read(1 << 20), 5)
    finally:
        writer.close()
        with contextlib.suppress(OSError):
            await writer.wait_closed()


def _swarm_sockets(port: int) -> list[socket.socket]:
    """64 trackers that shook hands (and announced sensors, so the budget is full) before the phase."""
    from mocapd.protocols.slimevr import Handshake, SensorInfo, encode_bundle, encode_packet

    socks = []
    for k in range(SWARM):
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.bind(("127.0.0.1", 0))
        sock.setblocking(False)
        sock.sendto(encode_packet(Handshake(2, 3, 2, 22, "swarm", f"0A:00:00:00:00:{k:02X}"), 0), ("127.0.0.1", port))
        sock.sendto(encode_bundle([SensorInfo(i, 1, 3) for i in range(16)], 1, compact=True), ("127.0.0.1", port))
        socks.append(sock)
    return socks


async def _attack(kind: str, ports: dict[str, int], seconds: float, rate: float) -> None:
    """Print "start" once set up (imports, the swarm's handshakes); then for every line on stdin do ``kind`` at
    ``rate`` a second for ``seconds`` and print the operations done."""
    import msgpack
    from websockets.asyncio.client import connect

    from mocapd.protocols.slimevr import Heartbeat, SensorInfo, encode_bundle, encode_packet
    from tools.soak import _bridge_datagram

    http, ws_port, slime = ports["http"], ports["ws"], ("127.0.0.1", ports["slimevr"])
    key = "dGhlIHNhbXBsZSBub25jZQ=="
    foreign = (f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{ws_port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
               f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
               "Origin: http://evil.example\r\n\r\n").encode()  # fmt: skip
    resets = [
        f"POST /heading/reset HTTP/1.1\r\nHost: 127.0.0.1:{http}\r\nContent-Type: text/plain\r\n"
        "Content-Length: 5\r\n\r\nreset".encode(),
        f"POST /heading/reset HTTP/1.1\r\nHost: 127.0.0.1:{http}\r\nX-Mocapd-Request: bench\r\n\r\n".encode(),
    ]
    poll = f"GET /status HTTP/1.1\r\nHost: localhost:{http}\r\n\r\n".encode()
    socks = _swarm_sockets(ports["slimevr"]) if kind in ("slimevr_bundle", "slimevr_heartbeat") else []
    stranger = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    stranger.bind(("127.0.0.1", 0))
    bundle = [SensorInfo(i, 1, 3) for i in range(128)]
    rng = random.Random(0)
    await asyncio.sleep(0.5)  # the swarm's handshakes are in before the first phase
    ws = await connect(f"ws://127.0.0.1:{ws_port}/", max_size=None) if kind == "ws_reset" else None
    if ws is not None:
        await ws.send(json.dumps({"type": "subscribe", "subjects": ["nobody"], "status": False}))
    number = 1
    done = 0
    inflight: set[asyncio.Task[None]] = set()

    async def one(i: int) -> None:
        """One operation of a connection-per-operation kind (several run at once: a refused handshake's
        connection takes the server a while to close, and the rate must not wait for it)."""
        nonlocal done
        with contextlib.suppress(OSError, TimeoutError, ConnectionError):
            if kind == "ws_foreign":
                await _tcp(ws_port, foreign)
            elif kind == "reset_http":
                await _tcp(http, resets[i % 2])
            elif kind == "status_poll":
                await _tcp(http, poll)
            else:  # ws_churn
                async with connect(f"ws://127.0.0.1:{ws_port}/", max_size=None, close_timeout=2) as c:
                    await c.send(msgpack.packb({"type": "subscribe", "encoding": "msgpack"}))
                    with contextlib.suppress(TimeoutError):
                        async with asyncio.timeout(0.1):
                            async for _ in c:
                                pass
            done += 1

    async def phase() -> None:
        nonlocal number, done
        start = time.monotonic()
        ops = 0
        while time.monotonic() < start + seconds:
            number += 1
            if kind in ("ws_foreign", "reset_http", "status_poll", "ws_churn"):
                if len(inflight) < 64:
                    t = asyncio.create_task(one(ops))
                    inflight.add(t)
                    t.add_done_callback(inflight.discard)
            elif kind == "ws_reset":
                assert ws is not None
                await ws.send(json.dumps({"type": "reset_heading"}))
                await ws.recv()
                done += 1
            elif kind == "slimevr_bundle":
                socks[ops % SWARM].sendto(encode_bundle(list(bundle), number, compact=True), slime)
                done += 1
            elif kind == "slimevr_unknown":
                stranger.sendto(encode_bundle(list(bundle), number, compact=True), slime)
                done += 1
            elif kind == "slimevr_heartbeat":
                socks[ops % SWARM].sendto(encode_packet(Heartbeat(), number), slime)
                done += 1
            elif kind == "bridge_mix":
                stranger.sendto(_bridge_datagram(rng, number), ("127.0.0.1", ports["bridge"]))
                done += 1
            else:
                raise SystemExit(f"unknown kind {kind}")
            ops += 1
            await asyncio.sleep(max(0.0, start + ops / rate - time.monotonic()))
        await asyncio.gather(*inflight, return_exceptions=True)

    loop = asyncio.get_running_loop()
    print("start", flush=True)
    try:
        while await loop.run_in_executor(None, sys.stdin.readline):
            done = 0
            await phase()
            print(json.dumps({"ops": done}), flush=True)
    finally:
        if ws is not None:
            await ws.close()
        for sock in [*socks, stranger]:
            sock.close()


# --------------------------------------------------------------------------------------------- the daemon side
async def bench(kinds: list[str], phase_s: float, repeats: int) -> dict[str, Any]:
    from mocapd.io.ws_server import WebSocketStreamServer
    from mocapd.service.assembly import assembled
    from mocapd.service.demo.synthetic import synthetic_config
    from tools.soak import soak_config

    cfg = soak_config()
    results: dict[str, Any] = {}
    with assembled(synthetic_config(cfg)) as demo:
        d = demo.daemon
        # The doors alone, as the daemon starts them, without its tick (whose cost on a loaded machine is the share
        # of the cores it gets, and would hide what the doors cost).
        ws = next(s for s in d.sinks if isinstance(s, WebSocketStreamServer))
        slimevr = d.imu.slimevr
        assert slimevr is not None
        assert d.imu.bridge is not None
        await d.http.start()
        await d.imu.bridge.start()
        await slimevr.start()
        await ws.start()
        ticking = asyncio.create_task(slimevr.run())
        ports = {"http": d.http.port, "ws": int(ws.port), "slimevr": slimevr.port, "bridge": d.imu.bridge.port}
        rx = next(t for t in threading.enumerate() if t.name == "mocapd-slimevr-rx")

        def cpu() -> float:
            """CPU seconds of the event loop's thread and the SlimeVR receive thread."""
            return time.thread_time() + _thread_cpu(rx.native_id)

        for kind in kinds:
            cmd = ["nice", "-n", "5", sys.executable, __file__, "--attack", kind, "--ports", json.dumps(ports),
                   "--seconds", str(phase_s)]  # fmt: skip
            proc = await asyncio.create_subprocess_exec(*cmd, stdin=asyncio.subprocess.PIPE,
                                                        stdout=asyncio.subprocess.PIPE)  # fmt: skip
            assert proc.stdin is not None and proc.stdout is not None
            await proc.stdout.readline()  # "start": set up
            per_op: list[float] = []
            ops_total = 0
            quiet_rates, attack_rates = [], []
            for _ in range(repeats):
                cpu0, t0 = cpu(), time.monotonic()
                await asyncio.sleep(phase_s)
                quiet = (cpu() - cpu0) / (time.monotonic() - t0)
                cpu0, t0 = cpu(), time.monotonic()
                proc.stdin.write(b"go\n")
                ops = int(json.loads(await proc.stdout.readline())["ops"])
                used, wall = cpu() - cpu0, time.monotonic() - t0
                quiet_rates.append(quiet)
                attack_rates.append(used / wall)
                ops_total += ops
                if ops:
                    per_op.append(1000 * (used - quiet * wall) / ops)
            proc.stdin.close()
            await proc.wait()
            per_op.sort()
            results[kind] = {
                "ops": ops_total,
                "ops_per_s": round(ops_total / (repeats * phase_s), 1),
                "quiet_cpu_s_per_s": [round(x, 3) for x in quiet_rates],
                "attack_cpu_s_per_s": [round(x, 3) for x in attack_rates],
                "cpu_ms_per_op_median": round(per_op[len(per_op) // 2], 3) if per_op else None,
                "cpu_ms_per_op_pairs": [round(x, 3) for x in per_op],
            }
            print(json.dumps({"kind": kind, **results[kind]}), flush=True)
        slimevr.stop()
        await ticking
        slimevr.close()
        await ws.aclose()
        d.imu.bridge.close()
        await d.http.close()
    return results


def _thread_cpu(tid: int | None) -> float:
    """CPU seconds of one thread of this process (utime + stime of /proc/self/task/TID/stat)."""
    if tid is None:
        return 0.0
    try:
        fields = Path(f"/proc/self/task/{tid}/stat").read_text().rpartition(")")[2].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--kinds", default=",".join(RATES), help="comma-separated kinds (default: all)")
    ap.add_argument("--phase", type=float, default=6.0, help="seconds of each quiet and attack phase (default 6)")
    ap.add_argument("--repeats", type=int, default=2, help="quiet/attack pairs per kind (default 2)")
    ap.add_argument("--out", type=Path, default=None, help="write the results as JSON here")
    ap.add_argument("--attack", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--ports", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--seconds", type=float, default=None, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.attack is not None:
        asyncio.run(_attack(a.attack, json.loads(a.ports), a.seconds, RATES[a.attack]))
        return
    kinds = [k for k in a.kinds.split(",") if k]
    unknown = [k for k in kinds if k not in RATES]
    if unknown:
        raise SystemExit(f"error: unknown kinds {unknown}; known: {', '.join(RATES)}")
    import logging

    from mocapd.io import log_throttle

    logging.basicConfig(level=logging.WARNING, stream=sys.stderr, format="%(levelname)s %(name)s: %(message)s")
    log_throttle.install()  # as `mocapd run` does: a flood's repeated lines are a few and a count
    results = asyncio.run(bench(kinds, a.phase, a.repeats))
    if a.out is not None:
        a.out.write_text(json.dumps(results, indent=1) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
