#!/usr/bin/env python3
"""Xbus benchmark: parser throughput on one core and end-to-end latency from simulator write to ring buffer.

Developer benchmark, not a ``mocapd bench`` verb (those are the benchmarks a user runs).

Prints one JSON object:

- ``parser``: messages per second through :class:`XbusParser` alone (``framing``) and with MTData2
  decoding (``framing_decode``), on the real MTi captures (einride, 13–15 outputs per message) and on
  mocapd's own output configuration (counter, SampleTimeFine, quaternion, acceleration) as the simulator
  sends it; the median of ``--repeats`` runs, fed in 4 KiB chunks. ``baseline_slices_per_s`` is a plain
  Python loop that only slices the same stream message by message, measured in the same process, so that
  results from different machines can be compared as ratios. ``target`` is the issue's 20 000 messages/s.
- ``path_cost``: CPU time per sample of the in-process streaming path (Xbus session decode, clock map,
  ring-buffer push) without any I/O or scheduling: what one sample costs the reader.
- ``latency``: ``--sensors`` simulated devices (a separate process, ``mocapd/sim/xsens.py``) stream at
  ``--rate`` Hz through real ptys into mocapd's serial path (pyserial + asyncio), the bring-up session, the
  clock map and the ring buffers; the latency of a sample is the monotonic time after its ring-buffer push
  minus the simulator's monotonic time just before its ``write()``. Median, 95th percentile and max, ms.

Usage: ``python tools/bench_xbus.py [--sensors 13] [--rate 120] [--seconds 5]``
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from mocapd.io.xsens_serial import ImuSample, XsensPortConfig, XsensSerialDevice
from mocapd.pipeline.imu_ingest import ImuIngest
from mocapd.protocols import xbus
from mocapd.protocols.mtdata2 import decode_mtdata2

REPO = Path(__file__).resolve().parents[1]
CAPTURES = REPO / "tests" / "data" / "xbus_einride"
TARGET = 20_000


def _einride_stream() -> bytes:
    return b"".join((CAPTURES / str(i) / "output.bin").read_bytes() for i in range(1, 6))


def _mocapd_stream(n: int) -> bytes:
    if str(REPO) not in sys.path:  # run as a script: make the repository's tools package importable
        sys.path.insert(0, str(REPO))
    from mocapd.sim import xsens as xsens_sim

    device = xsens_sim.SimDevice(xsens_sim.synthetic_motion(n=n))
    device.settings = [
        xbus.OutputSetting(0x1020, xbus.RATE_MAX),
        xbus.OutputSetting(0x1060, xbus.RATE_MAX),
        xbus.OutputSetting(0x2010, 120),
        xbus.OutputSetting(0x4020, 120),
    ]
    due = device.due_ns(0)
    out = []
    for _ in range(n):
        assert due is not None
        out.append(device.next_message(due))
        due = device.due_ns(due)
    return b"".join(out)


def _rate(stream: bytes, copies: int, decode: bool, repeats: int) -> tuple[float, int]:
    data = stream * copies
    chunks = [data[i : i + 4096] for i in range(0, len(data), 4096)]
    rates = []
    n = 0
    for _ in range(repeats):
        parser = xbus.XbusParser()
        t0 = time.perf_counter()
        n = 0
        for chunk in chunks:
            parser.receive_data(chunk)
            msgs = parser.events_received()
            n += len(msgs)
            if decode:
                for m in msgs:
                    decode_mtdata2(m.payload)
        rates.append(n / (time.perf_counter() - t0))
    return statistics.median(rates), n


def _baseline(stream: bytes, copies: int, repeats: int) -> float:
    parser = xbus.XbusParser()
    parser.receive_data(stream)
    sizes = [len(xbus.encode(m.mid, m.payload)) for m in parser.events_received()] * copies
    data = stream * copies
    rates = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        pos = 0
        for size in sizes:
            _ = data[pos : pos + size]
            pos += size
        rates.append(len(sizes) / (time.perf_counter() - t0))
    return statistics.median(rates)


def parser_bench(repeats: int) -> dict[str, object]:
    einride = _einride_stream()
    own = _mocapd_stream(2000)
    fe, n_e = _rate(einride, 20, False, repeats)
    fde, _ = _rate(einride, 20, True, repeats)
    fo, n_o = _rate(own, 5, False, repeats)
    fdo, _ = _rate(own, 5, True, repeats)
    base = _baseline(einride, 20, repeats)
    return {
        "einride_mti": {
            "messages": n_e,
            "mean_message_bytes": round(len(einride) / 500, 1),
            "framing_msgs_per_s": round(fe),
            "framing_decode_msgs_per_s": round(fde),
        },
        "mocapd_outputs": {
            "messages": n_o,
            "mean_message_bytes": round(len(own) / 2000, 1),
            "framing_msgs_per_s": round(fo),
            "framing_decode_msgs_per_s": round(fdo),
        },
        "baseline_slices_per_s": round(base),
        "decode_vs_baseline_einride": round(fde / base, 4),
        "target_msgs_per_s": TARGET,
        "meets_target": min(fde, fdo) >= TARGET,
    }


async def _latency_run(links: list[Path], rate: int, seconds: float) -> list[tuple[str, int, int]]:
    ingest = ImuIngest()
    pushed: list[tuple[str, int, int]] = []

    def on_sample(s: ImuSample) -> None:
        ingest.add(
            s.sensor,
            s.host_ns,
            device_ticks=s.device_ticks,
            packet_counter=s.packet_counter,
            quat=s.quat,
            acc=s.acc,
        )
        if s.packet_counter is not None:
            pushed.append((s.sensor, s.packet_counter, time.monotonic_ns()))

    devices = [XsensSerialDevice(XsensPortConfig(str(link), rate_hz=rate), on_sample) for link in links]
    tasks = [asyncio.create_task(d.run()) for d in devices]
    deadline = time.monotonic() + 20
    while not all(d.streaming.is_set() for d in devices):
        if time.monotonic() > deadline:
            raise SystemExit(f"devices did not start: {[d.last_error for d in devices]}")
        await asyncio.sleep(0.05)
    pushed.clear()
    await asyncio.sleep(seconds)
    for d in devices:
        d.stop()
    await asyncio.gather(*tasks)
    return pushed


def latency_bench(sensors: int, rate: int, seconds: float) -> dict[str, object]:
    with tempfile.TemporaryDirectory() as tmp:
        links = [Path(tmp) / f"imu{k}" for k in range(sensors)]
        log = Path(tmp) / "writes.json"
        cmd = [sys.executable, str(REPO / "tools" / "xsens_sim.py"), "--write-log", str(log)]
        for link in links:
            cmd += ["--link", str(link)]
        sim = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True, env={**os.environ, "PYTHONPATH": str(REPO)})
        try:
            assert sim.stdout is not None
            for _ in links:
                sim.stdout.readline()  # one line per device once its pty exists
            pushed = asyncio.run(_latency_run(links, rate, seconds))
        finally:
            sim.send_signal(signal.SIGTERM)
            sim.wait(timeout=10)
        writes = {dev: {int(c): t for c, t in table.items()} for dev, table in json.loads(log.read_text()).items()}
    lat = sorted((t_push - writes[s][c]) / 1e6 for s, c, t_push in pushed if c in writes.get(s, {}))
    return {
        "sensors": sensors,
        "rate_hz": rate,
        "samples": len(lat),
        "expected_samples": int(sensors * rate * seconds),
        "median_ms": round(statistics.median(lat), 3),
        "p95_ms": round(lat[int(0.95 * (len(lat) - 1))], 3),
        "max_ms": round(lat[-1], 3),
        "path": "xsens_sim.py process -> pty -> pyserial fd + asyncio add_reader -> XbusParser -> "
        "MTData2 decode -> ClockSync -> RingBuffer.push",
    }


def path_cost_bench(repeats: int) -> dict[str, object]:
    """CPU cost per sample of the in-process path (session decode + clock map + ring buffer), no I/O."""
    from mocapd.protocols.xsens_session import Sample, State, XsensSession, output_settings

    stream = _mocapd_stream(2000)
    per_sample = []
    for _ in range(repeats):
        session = XsensSession(output_settings(120))
        session.state = State.MEASURING  # skip the bring-up handshake: only the streaming path is timed
        ingest = ImuIngest()
        host = 0
        t0 = time.perf_counter()
        for i in range(0, len(stream), 51):
            host += 8_333_333
            session.receive_data(stream[i : i + 51], host)
            for ev in session.events_received():
                if isinstance(ev, Sample):
                    d = ev.data
                    ingest.add(
                        "s",
                        host,
                        device_ticks=d.sample_time_fine,
                        packet_counter=d.packet_counter,
                        quat=d.quaternion,
                        acc=d.acceleration,
                    )
        per_sample.append((time.perf_counter() - t0) / 2000 * 1e6)
    return {"per_sample_us": round(statistics.median(per_sample), 2), "samples": 2000}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--sensors", type=int, default=13)
    ap.add_argument("--rate", type=int, default=120)
    ap.add_argument("--seconds", type=float, default=5.0)
    args = ap.parse_args(argv)
    load_before = os.getloadavg()[0]
    result = {
        "bench": "xbus",
        "python": sys.version.split()[0],
        "cpu_count": os.cpu_count(),
        "loadavg_1min_before": round(load_before, 2),
        "parser": parser_bench(args.repeats),
        "path_cost": path_cost_bench(args.repeats),
        "latency": latency_bench(args.sensors, args.rate, args.seconds),
    }
    result["loadavg_1min_after"] = round(os.getloadavg()[0], 2)  # the machine is shared: say how busy it was
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
