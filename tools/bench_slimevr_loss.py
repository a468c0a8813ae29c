#!/usr/bin/env python3
"""SlimeVR datagram loss at real rates on a loaded machine: the daemon's receive thread against the event-loop reader.

Developer benchmark, not a ``mocapd bench`` verb (those are the benchmarks a user runs).

``--trackers`` emulated SlimeVR trackers (default 16, protocol 22, one sensor each, packet 23: rotation and
acceleration), each from a socket of its own, send ``--rate`` datagrams a second (default 100) for ``--seconds``
from a separate process, to the daemon's SlimeVR server on loopback. The first 13 follow the synthetic world's
suit sensors and form a calibrated suit, so the daemon's event loop solves that suit every tick (with
``--cameras N`` it also sorts and solves the synthetic rig's people: a busier loop). Meanwhile ``--load``
processes spin on the CPU (default 4) to put the machine at a load of 4 or more.

Each receive mode runs in turn, in this process, on the same machine: ``loop`` (the socket read on the event loop,
the reader before the receive thread) and ``thread`` (the receive thread, mocapd's reader). Both ask the kernel for
``--rcvbuf`` bytes of receive buffer (default 212992: the cap a stock kernel's ``net.core.rmem_max`` puts on it;
the daemon asks for 1 MiB, which a machine with a higher cap grants).

Loss per tracker = datagrams sent that the server never counted (``1 - received / sent``); the server's own count
of skipped packet numbers (``lost``, what /status shows as ``loss_percent``) and the kernel's drop counter of the
socket (``kernel_drops``, /proc/net/udp) are reported beside it. The load: /proc/loadavg at the start and end of
each mode and the median number of runnable tasks (/proc/stat ``procs_running``, sampled every second).

Usage: ``python tools/bench_slimevr_loss.py [--seconds 30] [--trackers 16] [--rate 100] [--load 4] [--cameras 0]``
Prints one JSON object.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import multiprocessing
import os
import platform
import socket
import statistics
import struct
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run as `python tools/bench_slimevr_loss.py` from a checkout
    sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

from mocapd.core.rotations import quat_conjugate, quat_rotate  # noqa: E402
from mocapd.io.slimevr import SlimeVrListener  # noqa: E402
from mocapd.protocols.slimevr import (  # noqa: E402
    HANDSHAKE_REPLY,
    Handshake,
    Rotation,
    SensorInfo,
    encode_packet,
)
from mocapd.service import assembly  # noqa: E402
from mocapd.service.assembly import RunOptions  # noqa: E402
from mocapd.service.config import load_config  # noqa: E402
from mocapd.service.config.cameras import parse_cameras  # noqa: E402
from mocapd.service.daemon import Daemon  # noqa: E402
from mocapd.sim.world import SyntheticWorld  # noqa: E402

STOCK_RMEM_MAX = 212992
GRAVITY = 9.81


def mac(k: int) -> str:
    return f"0A:00:00:00:00:{k:02X}"


# ---------------------------------------------------------------------------------------------- the trackers
def _trackers(port: int, n: int, rate_hz: float, seconds: float, results: Any, streaming: Any = None) -> None:
    """Child process: ``n`` trackers handshake with the server on ``port``, then send ``rate_hz`` rotations each."""
    world = SyntheticWorld(0, 1, 1, motion="recorded")
    quats, accs = world.imu_motion(world.suits[0], rate_hz)  # (13, m, 4) ENU, (13, m, 3) specific force
    up = np.array([0.0, 0.0, GRAVITY])
    socks = []
    for _ in range(n):
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.bind(("127.0.0.1", 0))
        s.settimeout(0.5)
        socks.append(s)
    server = ("127.0.0.1", port)
    for k, s in enumerate(socks):
        for _ in range(20):
            s.sendto(encode_packet(Handshake(2, 3, 2, 22, "0.6.3", mac(k)), 0), server)
            try:
                while s.recv(2048) != HANDSHAKE_REPLY:
                    pass
                break
            except TimeoutError:
                continue
        else:
            raise SystemExit(f"tracker {k}: no handshake reply")
        s.sendto(encode_packet(SensorInfo(0, 1, 3), 1), server)
        s.setblocking(False)
    # Every datagram's payload encoded once (the packet number is patched in): the sender stays light, so that a
    # loaded machine delays it as little as possible.
    payloads = []
    for k13 in range(min(n, 13)):
        row = []
        for j in range(quats.shape[1]):
            q = quats[k13, j]
            lin = accs[k13, j] - quat_rotate(quat_conjugate(q), up)
            w, x, y, z = (float(v) for v in q)
            a = (float(lin[0]), float(lin[1]), float(lin[2]))
            row.append(encode_packet(Rotation(0, (w, x, y, z), acc=a), 0)[12:])
        payloads.append(row)
    head = struct.Struct(">IQ")
    if streaming is not None:
        streaming.set()
    sent = [1] * n
    period = 1.0 / rate_hz
    t0 = time.monotonic()
    i = 0
    late = 0
    while True:
        due = t0 + i * period
        now = time.monotonic()
        if now - t0 >= seconds:
            break
        if due > now:
            time.sleep(due - now)
        elif now - due > 2 * period:  # this process was not scheduled in time: like a tracker's firmware, send
            skip = int((now - due) / period) - 1  # the current samples, not a backlog of old ones in one burst
            late += skip
            i += skip
        j = i % quats.shape[1]
        for k, s in enumerate(socks):
            try:
                s.sendto(head.pack(23, sent[k] + 1) + payloads[k % 13][j], server)
                sent[k] += 1
            except BlockingIOError:
                pass
        i += 1
        if i % 10 == 0:
            for s in socks:  # drop the server's heartbeats and pings (a real tracker reads them)
                while True:
                    try:
                        s.recv(2048)
                    except (BlockingIOError, ConnectionRefusedError):
                        break
    results.put({"sent": sent, "elapsed_s": time.monotonic() - t0, "ticks_late": late, "ticks": i})


def _spin(stop: Any) -> None:
    x = 0
    while not stop.is_set():
        for _ in range(100_000):
            x += 1


# ---------------------------------------------------------------------------------------------- the daemon
def _config(n: int, cameras: int, folder: Path) -> Any:
    """An IMU-only SlimeVR rig (or one beside ``cameras`` synthetic cameras) with the first 13 trackers a suit."""
    base = load_config()
    world = SyntheticWorld(0, 1, 1, motion="recorded")
    suit = world.suits[0]
    c = world.calibration(suit)
    rename = {f"{s:08X}": f"{mac(k)}/0" for k, s in enumerate(suit.sensor_ids)}
    bones = {rename[k]: v for k, v in c.bones.items()}
    c = replace(c, person="suit", bones=bones, q_ib={rename[k]: v for k, v in c.q_ib.items()},
                spread_deg=dict.fromkeys(bones, 0.0))  # fmt: skip
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "suit.imu.json").write_text(json.dumps(c.to_json_dict()), encoding="utf-8")
    slimevr = base.imu.slimevr.model_copy(update={"enabled": True, "port": 0, "assignment": dict(c.bones)})
    imu = base.imu.model_copy(update={"slimevr": slimevr, "calibration_dir": str(folder)})
    tables = [{"name": f"cam{i}", "source": "synthetic"} for i in range(cameras)]
    return base.model_copy(update={
        "imu": imu, "cameras": parse_cameras(tables),
        "synthetic": base.synthetic.model_copy(update={"people": 2, "suits": 0}),
        "daemon": base.daemon.model_copy(update={"http_port": 0}),
        "websocket": base.websocket.model_copy(update={"enabled": False}),
    })  # fmt: skip


def _runnable() -> int:
    with open("/proc/stat", encoding="ascii") as fh:
        for line in fh:
            if line.startswith("procs_running"):
                return int(line.split()[1])
    return 0


async def _mode(thread: bool, args: argparse.Namespace, folder: Path) -> dict[str, Any]:
    cfg = _config(args.trackers, args.cameras, folder)
    ctx = multiprocessing.get_context("spawn")
    out: dict[str, Any] = {}

    async def monitor(d: Daemon) -> None:
        old = d.imu.slimevr
        assert old is not None
        old.close()  # the daemon's own listener (its task runs on): replaced before any tracker talks to it
        listener = SlimeVrListener(d.imu.on_sample, host="127.0.0.1", port=0, receive_thread=thread,
                                   rcvbuf=args.rcvbuf)  # fmt: skip
        port = await listener.start()
        runner = asyncio.create_task(listener.run())
        d.imu.slimevr = listener
        results = ctx.Queue()
        streaming = ctx.Event()
        sender = ctx.Process(target=_trackers, args=(port, args.trackers, args.rate, args.seconds, results, streaming),
                             daemon=True)  # fmt: skip
        sender.start()
        loop = asyncio.get_running_loop()
        while not streaming.is_set() and sender.is_alive():  # the trackers' process starts and shakes hands
            await asyncio.sleep(0.05)
        load0 = os.getloadavg()
        status0 = d.status()
        running: list[int] = []
        end = loop.time() + args.seconds + 60
        solved = []
        while sender.is_alive() and loop.time() < end:
            running.append(_runnable())
            frame = d.latest
            solved.append(frame is not None and any(p.suit == "suit" for p in frame.people))
            await asyncio.sleep(1.0)
        sender.join(5)
        sent = results.get(timeout=5)
        await asyncio.sleep(1.0)  # what is queued reaches the server
        st = listener.status()
        status1 = d.status()
        listener.close()
        await asyncio.wait_for(runner, 2)
        by_mac = {t["id"]: t for t in st["trackers"]}
        per = []
        for k in range(args.trackers):
            t = by_mac.get(mac(k), {"packets": 0, "lost": 0, "loss_percent": None})
            per.append({"tracker": mac(k), "sent": sent["sent"][k], "received": t["packets"],
                        "loss_percent": round(100.0 * (1 - t["packets"] / sent["sent"][k]), 3),
                        "skipped_numbers": t["lost"], "server_loss_percent": t["loss_percent"]})  # fmt: skip
        total_sent = sum(p["sent"] for p in per)
        total_received = sum(p["received"] for p in per)
        out.update({
            "receive": "thread" if thread else "event loop",
            "datagrams_sent": total_sent, "datagrams_received": total_received,
            "loss_percent": round(100.0 * (1 - total_received / total_sent), 3),
            "worst_tracker_loss_percent": max(p["loss_percent"] for p in per),
            "kernel_drops": st["receiver"]["kernel_drops"], "receiver": st["receiver"],
            "sender": {"rate_hz_per_tracker": round((total_sent / args.trackers) / sent["elapsed_s"], 1),
                       "ticks_skipped_late": sent["ticks_late"], "ticks": sent["ticks"]},
            "loadavg_start": [round(v, 2) for v in load0], "loadavg_end": [round(v, 2) for v in os.getloadavg()],
            "runnable_tasks_median": statistics.median(running) if running else None,
            "daemon": {
                "output_frames": status1["output"]["frames"] - status0["output"]["frames"],
                "missed_ticks": status1["output"]["missed_ticks"] - status0["output"]["missed_ticks"],
                "solve_ms": status1["latency_ms"]["solve"], "end_to_end_ms": status1["latency_ms"]["end_to_end"],
                "suit_solved_fraction_of_seconds": round(sum(solved) / len(solved), 3) if solved else None,
            },
            "per_tracker": per,
        })  # fmt: skip

    await assembly.run(cfg, RunOptions(), monitor=monitor)
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=30.0, help="sending time per mode (default 30)")
    p.add_argument("--trackers", type=int, default=16)
    p.add_argument("--rate", type=float, default=100.0, help="datagrams per second per tracker (default 100)")
    p.add_argument("--load", type=int, default=4, help="busy processes spinning meanwhile (default 4)")
    p.add_argument("--warm-up", type=float, default=20.0, help="seconds of load before the first mode (default 20)")
    p.add_argument("--cameras", type=int, default=0, help="synthetic cameras beside the trackers (default 0)")
    p.add_argument(
        "--rcvbuf",
        type=int,
        default=STOCK_RMEM_MAX,
        help=f"receive buffer asked for, bytes (default {STOCK_RMEM_MAX}: a stock kernel's cap on it)",
    )
    p.add_argument("--modes", default="loop,thread", help="comma-separated: loop, thread (default both)")
    args = p.parse_args()
    ctx = multiprocessing.get_context("spawn")
    stop = ctx.Event()
    spinners = [ctx.Process(target=_spin, args=(stop,), daemon=True) for _ in range(args.load)]
    for s in spinners:
        s.start()
    result: dict[str, Any] = {
        "benchmark": "slimevr_loss", "trackers": args.trackers, "rate_hz": args.rate, "seconds": args.seconds,
        "busy_processes": args.load, "cameras": args.cameras, "rcvbuf_asked": args.rcvbuf,
        "rmem_max": int(Path("/proc/sys/net/core/rmem_max").read_text()),
        "cpus": os.cpu_count(), "machine": platform.machine(), "python": platform.python_version(),
        "switch_interval_s": sys.getswitchinterval(),
    }  # fmt: skip
    try:
        time.sleep(args.warm_up)
        with tempfile.TemporaryDirectory(prefix="mocapd-bench-slimevr-") as tmp:
            for mode in args.modes.split(","):
                result[mode] = asyncio.run(_mode(mode == "thread", args, Path(tmp) / mode))
    finally:
        stop.set()
        for s in spinners:
            s.join(5)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
