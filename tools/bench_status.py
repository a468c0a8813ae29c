"""Benchmark: does polling ``/status`` and ``/metrics`` move the output rate? Prints JSON.

Developer benchmark, not a ``mocapd bench`` verb (those are the benchmarks a user runs).

The daemon on the synthetic rig (the one assembly path, as ``mocapd demo --synthetic``) runs in this process in
``--rounds`` pairs of phases of ``--seconds`` each: idle, then a client process hammering ``/status`` and
``/metrics`` on loopback with ``--concurrency`` connections as fast as the server answers. Per phase: the output
rate (frames published / s), missed ticks, the daemon process's CPU seconds per second, requests answered, the
event loop's CPU time spent answering them (ms per second: what polling costs the tick's loop, measured as thread
CPU time so that other processes on a shared machine do not inflate it) and status snapshots taken (when the
server counts them); then the medians per kind of phase.
The client runs at ``nice 10`` so what is measured is the server side's cost on the tick loop, not the client's
own CPU (the machine is shared: compare the phases of one run with each other).

    .venv/bin/python tools/bench_status.py [--seconds 10] [--concurrency 8]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))


async def _hammer(port: int, seconds: float, concurrency: int) -> dict[str, int]:
    """GET /status (and every 4th request /metrics) on ``concurrency`` connections until ``seconds`` have passed."""
    end = time.monotonic() + seconds
    counts = {"ok": 0, "failed": 0, "bytes": 0}

    async def worker(k: int) -> None:
        i = 0
        while time.monotonic() < end:
            target = "/metrics" if (i + k) % 4 == 0 else "/status"
            i += 1
            try:
                reader, writer = await asyncio.open_connection("127.0.0.1", port)
                writer.write(f"GET {target} HTTP/1.1\r\nHost: localhost\r\n\r\n".encode())
                data = await reader.read()
                writer.close()
                ok = data.startswith(b"HTTP/1.1 200")
                counts["ok" if ok else "failed"] += 1
                counts["bytes"] += len(data)
            except OSError:
                counts["failed"] += 1

    await asyncio.gather(*(worker(k) for k in range(concurrency)))
    return counts


def hammer_main(port: int, seconds: float, concurrency: int) -> None:
    print(json.dumps(asyncio.run(_hammer(port, seconds, concurrency))), flush=True)


class Counter:
    """A pose sink counting published frames."""

    name = "bench-counter"

    def __init__(self) -> None:
        self.frames = 0

    async def start(self) -> None:
        return None

    def publish(self, frame: Any) -> None:
        self.frames += 1

    async def aclose(self) -> None:
        return None


def _median(xs: list[float]) -> float:
    return float(statistics.median(xs)) if xs else float("nan")


async def bench(seconds: float, concurrency: int, people: int, rounds: int, extra_kb: int) -> dict[str, Any]:
    from mocapd.service.assembly import RunOptions, assembled
    from mocapd.service.config import load_config
    from mocapd.service.demo.synthetic import synthetic_config
    from mocapd.service.http_status import Reply

    cfg = load_config()
    cfg = cfg.model_copy(
        update={
            "daemon": cfg.daemon.model_copy(update={"http_port": 0}),
            "synthetic": cfg.synthetic.model_copy(update={"people": people, "suits": min(1, people)}),
        }
    )
    counter = Counter()
    phases: list[dict[str, Any]] = []
    # A larger document, as a daemon with many sensors has (issue 18 D4: 113 KB after ~700 sensor ids).
    padding = {f"s{i:05d}": {"buffered": i, "counter_gaps": 0, "clock_skew_ppm": 1.5} for i in range(extra_kb * 14)}
    extras = {"padding": lambda: dict(padding)} if extra_kb else {}
    with assembled(synthetic_config(cfg), RunOptions(sinks=[counter], status_extras=extras)) as demo:
        d = demo.daemon
        # The event loop's CPU time spent answering requests (parsing + snapshot + rendering), thread CPU time so
        # that a neighbour's load on the shared machine does not count: the cost polling puts on the tick's loop.
        respond = d.http._respond
        spent = [0]

        def timed_respond(head: bytes, peer: str) -> Reply:
            t = time.thread_time_ns()
            try:
                return respond(head, peer)
            finally:
                spent[0] += time.thread_time_ns() - t

        d.http._respond = timed_respond  # type: ignore[method-assign]
        task = asyncio.create_task(d.run())
        await asyncio.wait_for(d.ready.wait(), 300)
        await asyncio.sleep(3.0)  # past the start-up transient

        async def phase(name: str, client: bool) -> None:
            f0, m0, r0 = counter.frames, d.plan.missed if d.plan else 0, d.http.requests
            cpu0, spent0 = time.process_time(), spent[0]
            renders0 = getattr(d.http, "renders", None)
            t0 = time.monotonic()
            result: dict[str, Any] = {}
            if client:
                cmd = ["nice", "-n", "10", sys.executable, __file__, "--hammer", str(d.http.port),
                       "--seconds", str(seconds), "--concurrency", str(concurrency)]  # fmt: skip
                proc = await asyncio.create_subprocess_exec(*cmd, stdout=subprocess.PIPE)
                out, _ = await proc.communicate()
                result = json.loads(out)
            else:
                await asyncio.sleep(seconds)
            dt = time.monotonic() - t0
            renders1 = getattr(d.http, "renders", None)
            phases.append({
                "phase": name,
                "seconds": round(dt, 2),
                "output_hz": round((counter.frames - f0) / dt, 2),
                "missed_ticks": (d.plan.missed if d.plan else 0) - m0,
                "daemon_cpu_s_per_s": round((time.process_time() - cpu0) / dt, 3),
                "requests_served": d.http.requests - r0,
                "respond_cpu_ms_per_s": round((spent[0] - spent0) / 1e6 / dt, 2),
                "renders": None if renders0 is None or renders1 is None else renders1 - renders0,
                **({"client": result} if client else {}),
            })  # fmt: skip

        for _ in range(rounds):  # alternate, so a neighbour's load on the shared machine hits both kinds alike
            await phase("idle", False)
            await phase("polling", True)
        status_bytes = len(json.dumps(d.status()))
        d.request_stop()
        await asyncio.wait_for(task, 10)
    return {
        "benchmark": "status_polling",
        "configured_hz": cfg.daemon.output_rate_hz,
        "people": people,
        "concurrency": concurrency,
        "extra_kb": extra_kb,
        "status_document_bytes": status_bytes,
        "median": {
            kind: {
                key: _median([p[key] for p in phases if p["phase"] == kind])
                for key in (
                    "output_hz",
                    "missed_ticks",
                    "daemon_cpu_s_per_s",
                    "requests_served",
                    "respond_cpu_ms_per_s",
                )
            }
            for kind in ("idle", "polling")
        },
        "phases": phases,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--concurrency", type=int, default=8)
    ap.add_argument("--people", type=int, default=2)
    ap.add_argument("--rounds", type=int, default=3, help="idle/polling pairs (default 3)")
    ap.add_argument("--extra-kb", type=int, default=0, help="grow /status by about this many KB (default 0)")
    ap.add_argument("--hammer", type=int, default=None, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.hammer is not None:
        hammer_main(a.hammer, a.seconds, a.concurrency)
        return
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    print(json.dumps(asyncio.run(bench(a.seconds, a.concurrency, a.people, a.rounds, a.extra_kb)), indent=1))


if __name__ == "__main__":
    main()
