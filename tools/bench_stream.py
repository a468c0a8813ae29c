"""Benchmark of the WebSocket pose stream; prints JSON.

Developer benchmark, not a ``mocapd bench`` verb (those are the benchmarks a user runs).

1. **Serialisation**: 4 subjects (real poses through forward kinematics), each encoding (msgpack, JSON) and
   convention, with and without global joints: the cost of turning one published frame into one message
   (conversion + encoding, as the first client with those options pays it; every further client with the same
   options reuses the bytes) and its size. Medians over many frames.
2. **Fan-out under the real tick loop**: the daemon on the synthetic rig (4 people by default) with its WebSocket
   server, run in phases in one process: a baseline with no clients, then 50 clients on loopback (one of them
   stalled: it completes the handshake and never reads) in a separate process, then a second baseline. Reports
   missed solver ticks per phase (streaming's share = streaming phase minus baseline), the cost of the sink's
   ``publish`` inside the tick, per-client delivery latency (daemon publish → client receive, both on the host's
   CLOCK_MONOTONIC) p50/p95 and what the stalled client lost. The client process runs at ``nice 10`` by default,
   so what is measured is the server side's effect on the tick loop rather than the clients' own CPU competing
   for the 2 cores (a game engine on the same laptop would compete too: ``--client-nice 0`` measures that).

    .venv/bin/python tools/bench_stream.py [--seconds 30] [--people 4] [--clients 50]

The machine is shared: quote the medians, and compare phases of one run with each other.
"""

from __future__ import annotations

import argparse
import asyncio
import base64
import json
import os
import resource
import socket
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from mocapd.core.kinematics import Kinematics  # noqa: E402
from mocapd.core.rotations import random_rotvec  # noqa: E402
from mocapd.core.skeleton import N_BONES, Skeleton  # noqa: E402
from mocapd.pipeline.scheduler import PersonPose, PoseFrame  # noqa: E402
from mocapd.protocols.ws_stream import STREAM_CONVENTIONS, FrameEncoder, StreamDescription, StreamOptions  # noqa: E402


# ---------------------------------------------------------------------------------------------- serialisation
def _frames(n: int, people: int, rng: np.random.Generator) -> list[PoseFrame]:
    skel = Skeleton.from_height(1.75)
    kin = Kinematics(skel)
    out = []
    for k in range(n):
        persons = []
        for p in range(people):
            theta = np.concatenate([rng.uniform(-2, 2, 3), random_rotvec(rng, (N_BONES,), 1.0).ravel()])
            persons.append(PersonPose(f"person:{p}", p, None, theta, kin.forward(theta).positions, 0.9, 4, 13,
                                      5, True))  # fmt: skip
        out.append(PoseFrame(k, 10**12 + k * 16_666_667, 0, persons, 0))
    return out


def serialisation(people: int, n: int = 600) -> dict[str, Any]:
    """Per option set: thread CPU time (robust on a shared machine) and wall time to convert + encode a frame."""
    desc = StreamDescription(60.0, {"default": Skeleton.from_height(1.75)})
    frames = _frames(n, people, np.random.default_rng(0))
    result: dict[str, Any] = {}
    for f in frames[:100]:  # warm-up: first calls into numpy and msgpack
        FrameEncoder(f, 0, desc).message(StreamOptions())
    for encoding in ("msgpack", "json"):
        for conv in STREAM_CONVENTIONS:
            for globals_ in (False, True):
                opts = StreamOptions(encoding=encoding, convention=conv, globals=globals_)
                cpu, wall, size = [], [], 0
                for f in frames:
                    c0, t0 = time.thread_time_ns(), time.perf_counter_ns()
                    msg = FrameEncoder(f, 0, desc).message(opts)
                    wall.append(time.perf_counter_ns() - t0)
                    cpu.append(time.thread_time_ns() - c0)
                    size = len(msg)
                cached = FrameEncoder(frames[0], 0, desc)
                cached.message(opts)
                t0 = time.perf_counter_ns()
                for _ in range(1000):
                    cached.message(opts)
                key = f"{encoding}/{conv}/{'globals' if globals_ else 'no_globals'}"
                result[key] = {
                    "cpu_us_median": round(float(np.median(cpu)) / 1e3, 1),
                    "wall_us_median": round(float(np.median(wall)) / 1e3, 1),
                    "wall_us_p95": round(float(np.percentile(wall, 95)) / 1e3, 1),
                    "bytes": size,
                    "us_same_options_again": round((time.perf_counter_ns() - t0) / 1000 / 1e3, 3),
                }
    return result


# ---------------------------------------------------------------------------------------------- client process
def stalled_handshake(port: int) -> socket.socket:
    """A real WebSocket client that completes the handshake and then never reads (tiny receive buffer)."""
    s = socket.socket()
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    s.connect(("127.0.0.1", port))
    key = base64.b64encode(os.urandom(16)).decode()
    s.sendall(f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
              f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n".encode())  # fmt: skip
    head = b""
    while b"\r\n\r\n" not in head:
        head += s.recv(1)  # byte by byte: leave every WebSocket frame unread
    if not head.startswith(b"HTTP/1.1 101"):
        raise ConnectionError(f"websocket handshake refused: {head[:40]!r}")
    return s


def _stalled(port: int) -> socket.socket:
    """Handshake, ask for the largest frames (JSON with global joints), then never read."""
    s = stalled_handshake(port)
    payload = json.dumps({"type": "subscribe", "encoding": "json", "globals": True}).encode()
    mask = os.urandom(4)
    masked = bytes(b ^ mask[i % 4] for i, b in enumerate(payload))
    s.sendall(bytes([0x81, 0x80 | len(payload)]) + mask + masked)  # one masked text frame (RFC 6455 5.2)
    return s


async def _clients(port: int, n: int, seconds: float) -> dict[str, Any]:
    import msgpack
    from websockets.asyncio.client import connect

    stalled = _stalled(port)  # first, so the server numbers it first in this phase
    latencies: list[list[int]] = [[] for _ in range(n - 1)]
    hellos = [0] * (n - 1)

    async def one(i: int, stop_at: float) -> None:
        async with connect(f"ws://127.0.0.1:{port}/", max_size=1 << 22, compression=None) as ws:
            while time.monotonic() < stop_at:
                try:
                    raw = await asyncio.wait_for(ws.recv(), max(0.01, stop_at - time.monotonic()))
                except TimeoutError:
                    break
                now = time.monotonic_ns()
                m = msgpack.unpackb(raw)
                if m["type"] == "frame":
                    latencies[i].append(now - m["t_publish_ns"])
                elif m["type"] == "hello":
                    hellos[i] += 1

    stop_at = time.monotonic() + seconds
    await asyncio.gather(*(one(i, stop_at) for i in range(n - 1)))
    stalled.close()
    per = [np.asarray(x, dtype=np.float64) / 1e6 for x in latencies]
    p50 = [float(np.percentile(x, 50)) for x in per if x.size]
    p95 = [float(np.percentile(x, 95)) for x in per if x.size]
    return {
        "reading_clients": n - 1,
        "frames_per_client_median": int(np.median([x.size for x in per])),
        "frames_per_client_min": int(min(x.size for x in per)),
        "latency_ms_p50_median_over_clients": round(float(np.median(p50)), 3),
        "latency_ms_p95_median_over_clients": round(float(np.median(p95)), 3),
        "latency_ms_p95_worst_client": round(max(p95), 3),
        "latency_ms_p50_all_messages": round(float(np.percentile(np.concatenate(per), 50)), 3),
        "latency_ms_p95_all_messages": round(float(np.percentile(np.concatenate(per), 95)), 3),
    }


async def _child(port: int, n: int, seconds: float) -> None:
    """The client process: one streaming phase per "go" line on stdin, one JSON line per phase on stdout."""
    loop = asyncio.get_running_loop()
    print("ready", flush=True)
    while (await loop.run_in_executor(None, sys.stdin.readline)).strip() == "go":
        print(json.dumps(await _clients(port, n, seconds)), flush=True)


# ---------------------------------------------------------------------------------------------- daemon side
class TimedSink:
    """Wraps the WebSocket sink: times its ``publish`` inside the tick and how late each tick publishes."""

    def __init__(self, inner: Any) -> None:
        self.inner = inner
        self.cost_ns: list[int] = []
        self.late_ns: list[int] = []

    async def start(self) -> None:
        await self.inner.start()

    def publish(self, frame: PoseFrame) -> None:
        t0 = time.perf_counter_ns()
        self.late_ns.append(time.monotonic_ns() - frame.tick_ns)  # scheduled tick -> the frame reaches the sink
        self.inner.publish(frame)
        self.cost_ns.append(time.perf_counter_ns() - t0)

    async def aclose(self) -> None:
        await self.inner.aclose()


def _pct(values: list[int], q: float, scale: float) -> float | None:
    return round(float(np.percentile(np.asarray(values, dtype=np.float64), q)) / scale, 3) if values else None


def fan_out(
    seconds: float, people: int, clients: int, warm_up_s: float, repeats: int, client_nice: int
) -> dict[str, Any]:
    from mocapd.service.assembly import assembled
    from mocapd.service.config import load_config
    from mocapd.service.demo.synthetic import synthetic_config
    from mocapd.service.outputs.websocket import build_websocket_sinks

    cfg = load_config()
    syn = cfg.synthetic.model_copy(update={"people": people, "suits": 0})
    cfg = cfg.model_copy(update={
        "daemon": cfg.daemon.model_copy(update={"http_port": 0}), "synthetic": syn,
        "websocket": cfg.websocket.model_copy(update={"port": 0, "max_clients": max(64, clients + 4)}),
    })  # fmt: skip
    runs: list[dict[str, Any]] = []
    # The daemon without its own stream server: the benchmark adds one wrapped in a timer, so that its publish()
    # is measured on the real tick loop.
    quiet = cfg.model_copy(update={"websocket": cfg.websocket.model_copy(update={"enabled": False})})
    with assembled(synthetic_config(quiet)) as demo:
        d = demo.daemon
        (ws,) = build_websocket_sinks(cfg, d)
        timed = TimedSink(ws)
        d.sinks.append(timed)

        async def phase(kind: str, proc: asyncio.subprocess.Process | None) -> None:
            assert d.plan is not None
            m0, f0, n0 = d.plan.missed, d.scheduler.frame, len(timed.cost_ns)
            r0 = resource.getrusage(resource.RUSAGE_SELF)
            t0 = time.monotonic()
            row: dict[str, Any] = {"phase": kind}
            if proc is not None:
                assert proc.stdin is not None and proc.stdout is not None
                first = min((c.number for c in ws.clients), default=0)
                proc.stdin.write(b"go\n")
                await proc.stdin.drain()
                stalled: dict[str, Any] = {}
                others_dropped = 0
                reply = asyncio.create_task(proc.stdout.readline())
                while not reply.done():  # the stalled client is the first one this phase connects
                    await asyncio.wait({reply}, timeout=0.25)
                    mine = [c for c in ws.stats()["per_client"] if c["client"] > first]
                    if mine:
                        stalled = {k: mine[0][k] for k in ("sent", "dropped", "queued")}
                        others_dropped = max([others_dropped, *(c["dropped"] for c in mine[1:])])
                row["clients"] = json.loads(reply.result())
                row["stalled_client"] = stalled
                row["reading_clients_max_dropped"] = others_dropped
            else:
                await asyncio.sleep(seconds)
            wall = time.monotonic() - t0
            r1 = resource.getrusage(resource.RUSAGE_SELF)
            cpu = r1.ru_utime + r1.ru_stime - r0.ru_utime - r0.ru_stime
            cost, late = timed.cost_ns[n0:], timed.late_ns[n0:]
            frames, missed = d.scheduler.frame - f0, d.plan.missed - m0
            row.update({
                "wall_s": round(wall, 1), "frames": frames, "missed_ticks": missed,
                "missed_fraction": round(missed / max(1, frames + missed), 4),
                "missed_per_s": round(missed / wall, 2),
                "daemon_cpu_fraction_of_one_core": round(cpu / wall, 3),
                "tick_to_publish_ms_p50": _pct(late, 50, 1e6), "tick_to_publish_ms_p95": _pct(late, 95, 1e6),
                "sink_publish_us_p50": _pct(cost, 50, 1e3), "sink_publish_us_p99": _pct(cost, 99, 1e3),
            })  # fmt: skip
            runs.append(row)

        async def main() -> None:
            task = asyncio.create_task(d.run())
            await asyncio.wait_for(d.ready.wait(), 300)
            proc = await asyncio.create_subprocess_exec(
                "nice", "-n", str(client_nice), sys.executable, __file__, "--child", str(ws.port), str(clients),
                str(seconds),
                stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE,
            )  # fmt: skip
            assert proc.stdout is not None and proc.stdin is not None
            assert (await proc.stdout.readline()).strip() == b"ready"  # imports done before any phase
            await asyncio.sleep(warm_up_s)
            for _ in range(repeats):
                await phase("baseline", None)
                await phase("streaming", proc)
                await asyncio.sleep(1.0)  # the phase's connections close
            await phase("baseline", None)
            proc.stdin.write(b"stop\n")
            await proc.stdin.drain()
            await proc.wait()
            d.request_stop()
            await task

        asyncio.run(main())

    def med(kind: str, key: str) -> float:
        return float(np.median([r[key] for r in runs if r["phase"] == kind]))

    streaming = [r for r in runs if r["phase"] == "streaming"]
    return {
        "rig": {"people": people, "cameras": len(cfg.cameras), "suits": 0, "output_rate_hz": cfg.daemon.output_rate_hz},
        "clients": clients,
        "client_process_nice": client_nice,
        "phase_s": seconds,
        "summary": {
            "missed_ticks_per_s_median": {"baseline": round(med("baseline", "missed_per_s"), 2),
                                          "streaming": round(med("streaming", "missed_per_s"), 2)},
            "missed_fraction_median": {"baseline": med("baseline", "missed_fraction"),
                                       "streaming": med("streaming", "missed_fraction")},
            "tick_to_publish_ms_p50_median": {"baseline": med("baseline", "tick_to_publish_ms_p50"),
                                              "streaming": med("streaming", "tick_to_publish_ms_p50")},
            "sink_publish_us_p50_median": {"baseline": med("baseline", "sink_publish_us_p50"),
                                           "streaming": med("streaming", "sink_publish_us_p50")},
            "delivery_latency_ms_p50_median": float(np.median(
                [r["clients"]["latency_ms_p50_median_over_clients"] for r in streaming])),
            "delivery_latency_ms_p95_median": float(np.median(
                [r["clients"]["latency_ms_p95_median_over_clients"] for r in streaming])),
            "stalled_client_dropped": [r["stalled_client"].get("dropped") for r in streaming],
            "reading_clients_max_dropped": max(r["reading_clients_max_dropped"] for r in streaming),
        },
        "phases": runs,
    }  # fmt: skip


def main() -> int:
    p = argparse.ArgumentParser(description="WebSocket stream benchmark (JSON on stdout)")
    p.add_argument("--seconds", type=float, default=10.0, help="length of each phase (default 10)")
    p.add_argument("--repeats", type=int, default=3, help="baseline/streaming pairs (default 3: 30 s streaming)")
    p.add_argument("--people", type=int, default=4)
    p.add_argument("--clients", type=int, default=50, help="including the stalled one")
    p.add_argument("--warm-up", type=float, default=10.0)
    p.add_argument(
        "--client-nice",
        type=int,
        default=10,
        help="niceness of the client process, so its own CPU does not starve the daemon (0: none)",
    )
    p.add_argument("--child", nargs=3, metavar=("PORT", "N", "SECONDS"), help=argparse.SUPPRESS)
    a = p.parse_args()
    if a.child:
        asyncio.run(_child(int(a.child[0]), int(a.child[1]), float(a.child[2])))
        return 0
    out = {
        "machine": {"cpus": os.cpu_count(), "load_avg_at_start": [round(x, 2) for x in os.getloadavg()]},
        "serialisation_per_frame": {"subjects": a.people, **serialisation(a.people)},
        "fan_out": fan_out(a.seconds, a.people, a.clients, a.warm_up, a.repeats, a.client_nice),
    }
    out["machine"]["load_avg_at_end"] = [round(x, 2) for x in os.getloadavg()]
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
