"""Where the soak's synthetic daemon spends its CPU: thread CPU per call of the loop's pieces, under the attackers.

Developer benchmark, not a ``mocapd bench`` verb.

The soak's output rate (``tools/soak.py``) says whether the event loop kept up, not what it spent its time on, and a
sampling profiler on a shared machine over-counts the system calls where a starved process is preempted. This
assembles the synthetic daemon as the soak does (the one assembly path, every door open on loopback), optionally
starts the soak's attacker process (``--attack``, the same attacks at the same rates), and wraps the pieces of the
daemon's own work (the tick's stages, a person's solve and its parts, the camera watch, the IMU path, the simulated
suit's thread, the synthetic cameras, the doors, the offset estimate's steps) with a thread-CPU counter. After
``--warm`` seconds it counts for ``--seconds`` and prints one JSON line (process and thread CPU a second, the output
rate, the scheduler's CPU per tick and stage, the person stages) and then per piece: calls a second, CPU per call
(µs) and CPU a second (ms). On a machine shared with other work the calls a second follow the share of the cores the
daemon got; the CPU per call is what each piece costs, and times the quiet machine's rates (60 ticks, 30 solves of
two people with the governor's half rate, 1300 IMU samples, 120 camera frames a second) it is the loop's budget. The
counters add a few microseconds per call.

    PYTHONPATH=$PWD nice -n 19 .venv/bin/python tools/bench_soak_loop.py [--seconds 40] [--warm 8] [--attack]
"""

from __future__ import annotations

import argparse
import asyncio
import functools
import json
import logging
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

#: label -> [CPU ns, calls]
COUNTS: dict[str, list[int]] = {}


def _wrap(owner: Any, name: str, label: str | None = None) -> None:
    """Count the thread CPU of every call of ``owner.name`` (a method or a module's function) under ``label``."""
    fn: Callable[..., Any] | None = getattr(owner, name, None)
    if fn is None:
        return  # a piece this revision does not have
    key = label or f"{owner.__name__}.{name}"
    COUNTS[key] = [0, 0]

    @functools.wraps(fn)
    def counted(*args: Any, **kwargs: Any) -> Any:
        c0 = time.thread_time_ns()
        try:
            return fn(*args, **kwargs)
        finally:
            acc = COUNTS[key]
            acc[0] += time.thread_time_ns() - c0
            acc[1] += 1

    setattr(owner, name, counted)


def install() -> None:
    """Wrap the pieces (before the daemon is assembled: modules that imported a function by name are patched too)."""
    from mocapd.core import camera_watch, lr_collapse, lr_flips
    from mocapd.core.people import PeopleTracker
    from mocapd.core.solver import PoseSolver
    from mocapd.io import imu_bridge, xsens_serial
    from mocapd.io.slimevr import SlimeVrListener
    from mocapd.io.ws_server import WebSocketStreamServer
    from mocapd.pipeline import scheduler
    from mocapd.pipeline.camera_watch import LiveCameraWatch
    from mocapd.service.daemon import Daemon
    from mocapd.service.http_status import StatusServer
    from mocapd.service.imu_inputs import ImuInputs
    from mocapd.sim.suits import _WorldClockedDevice
    from mocapd.sim.world import SyntheticWorld
    from mocapd.sim.xsens import XsensSimulator

    tick = ["sample", "_sample_cameras", "_sample_suit", "_look_up_suit", "_fill_tick", "_solve_tick", "_solve"]
    for name in [*tick, "_unflip", "_size_body", "_joints", "add_detections", "record_publish"]:
        _wrap(scheduler.FixedLatencyScheduler, name)
    for fn in ("collapsed_pairs", "choose_swaps"):
        module = lr_collapse if fn == "collapsed_pairs" else lr_flips
        _wrap(module, fn, fn)
        setattr(scheduler, fn, getattr(module, fn))
    _wrap(PeopleTracker, "update")
    _wrap(PoseSolver, "solve")
    _wrap(LiveCameraWatch, "observe")
    for name in ("_check", "_judge", "_at_once"):
        _wrap(camera_watch.CameraWatch, name)
    _wrap(camera_watch, "residuals_all_in", "camera_watch.residuals_all_in")
    _wrap(xsens_serial._SessionProtocol, "data_received")
    _wrap(xsens_serial.XsensSerialDevice, "_dispatch")
    _wrap(ImuInputs, "on_sample")
    _wrap(ImuInputs, "turn_headings")
    _wrap(imu_bridge._BridgeProtocol, "datagram_received")
    _wrap(SlimeVrListener, "_drain")
    _wrap(WebSocketStreamServer, "publish")
    _wrap(WebSocketStreamServer, "_process_request")
    _wrap(WebSocketStreamServer, "_command")
    _wrap(StatusServer, "_respond")
    _wrap(Daemon, "status")
    _wrap(Daemon, "reset_heading")
    _wrap(XsensSimulator, "emit_due")
    _wrap(_WorldClockedDevice, "next_message")
    _wrap(SyntheticWorld, "detections")
    _count_offset_estimate()


def _count_offset_estimate() -> None:
    """The offset estimate of the status loop (every 10 s, in steps between ticks): each step counted, and each
    whole estimate (its steps' CPU together) under its own label."""
    from mocapd.service import daemon as daemon_module

    step, whole = "offset estimate, a step", "offset estimate, cameras or IMUs, whole"
    COUNTS[step] = [0, 0]
    COUNTS[whole] = [0, 0]

    async def counted(steps: Any) -> Any:
        total = 0
        while True:
            c0 = time.thread_time_ns()
            try:
                next(steps)
            except StopIteration as done:
                COUNTS[whole][0] += total + time.thread_time_ns() - c0
                COUNTS[whole][1] += 1
                return done.value
            finally:
                ns = time.thread_time_ns() - c0
                COUNTS[step][0] += ns
                COUNTS[step][1] += 1
            total += ns
            await asyncio.sleep(0)

    daemon_module.run_in_steps = counted


def _thread_cpu_s() -> dict[str, float]:
    """CPU seconds of each of this process's threads, by thread id."""
    out = {}
    for tid in os.listdir("/proc/self/task"):
        try:
            stat = Path(f"/proc/self/task/{tid}/stat").read_text()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2 :].split()
        out[tid] = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    return out


async def measure(seconds: float, warm_s: float, attack: bool) -> None:
    from mocapd.io import log_throttle
    from mocapd.io.ws_server import WebSocketStreamServer
    from mocapd.service.assembly import assembled
    from mocapd.service.demo.synthetic import synthetic_config
    from tools.soak import soak_config

    log_throttle.install()
    logging.getLogger().setLevel(logging.ERROR)
    with assembled(synthetic_config(soak_config())) as demo:
        d = demo.daemon
        task = asyncio.create_task(d.run(), name="daemon")
        await asyncio.wait_for(d.ready.wait(), 900)
        attacker = None
        if attack:
            ws = next(s for s in d.sinks if isinstance(s, WebSocketStreamServer))
            assert d.imu.bridge is not None and d.imu.slimevr is not None
            ports = {"http": d.http.port, "ws": int(ws.port), "bridge": d.imu.bridge.port,
                     "slimevr": d.imu.slimevr.port}  # fmt: skip
            attacker = await asyncio.create_subprocess_exec(
                "nice", "-n", "5", sys.executable, str(ROOT / "tools" / "soak.py"), "--attack", json.dumps(ports),
                "--seconds", str(seconds + warm_s + 5), "--seed", "0", stdout=asyncio.subprocess.DEVNULL,
            )  # fmt: skip
        await asyncio.sleep(warm_s)
        s = d.scheduler
        for acc in COUNTS.values():
            acc[0] = acc[1] = 0
        t0, th0, cpu0, pub0, c0, p0 = time.monotonic(), _thread_cpu_s(), dict(s.cpu_ns), s.published, \
            dict(s.counters), time.process_time()  # fmt: skip
        await asyncio.sleep(seconds)
        dt = time.monotonic() - t0
        th1, cpu1, c1 = _thread_cpu_s(), dict(s.cpu_ns), dict(s.counters)
        ticks = c1["ticks"] - c0["ticks"]
        print(json.dumps({
            "seconds": round(dt, 1), "attack": attack, "loadavg": [round(x, 2) for x in os.getloadavg()],
            "process_cpu_s_per_s": round((time.process_time() - p0) / dt, 3),
            "published_hz": round((s.published - pub0) / dt, 2), "ticks": ticks,
            "ticks_solved": c1["ticks_solved"] - c0["ticks_solved"],
            "person_solves": c1["person_solves"] - c0["person_solves"],
            "threads_cpu_s_per_s": {k: round((v - th0.get(k, 0.0)) / dt, 3) for k, v in th1.items()
                                    if v - th0.get(k, 0.0) > 0},
            "stage_cpu_ms_per_tick": {k: round((cpu1[k] - cpu0[k]) / 1e6 / max(1, ticks), 3) for k in cpu1},
        }), flush=True)  # fmt: skip
        for key, (ns, n) in sorted(COUNTS.items(), key=lambda kv: -kv[1][0]):
            if n:
                print(f"{key:44s} calls/s {n / dt:8.1f}  us/call {ns / n / 1e3:9.1f}  ms/s {ns / dt / 1e6:7.1f}")
        if attacker is not None:
            attacker.kill()
            await attacker.wait()
        d.request_stop()
        await task


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=40.0, help="how long to count (default 40)")
    ap.add_argument("--warm", type=float, default=8.0, help="seconds after READY before counting (default 8)")
    ap.add_argument("--attack", action="store_true", help="run the soak's attacker process beside the daemon")
    args = ap.parse_args()
    install()
    asyncio.run(measure(args.seconds, args.warm, args.attack))


if __name__ == "__main__":
    main()
