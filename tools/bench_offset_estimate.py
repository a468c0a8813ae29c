"""The cameras' offset estimate against a 60 Hz tick: in a thread (as the status loop ran it) or in steps between
ticks (as the event loop runs it now, issue 45's hiccup near t = 10 s).

Developer benchmark, not a ``mocapd bench`` verb (those are the benchmarks a user runs).

The tick is the real solver (2 people, each seen by 4 cameras and wearing 13 IMUs: ``mocapd bench solver``'s synthetic
case) at 60 Hz on the main thread, late ticks skipped as the daemon's plan skips them. The estimate is
``estimate_camera_offsets`` on ``--seconds-kept`` of a synthetic 4-camera rig's 30 Hz detections (2 people), run in
alternating ``--window`` second windows (thread, none, steps, none, ...) three ways, so that a change of the machine's
load hits all alike:

* ``none``: no estimate;
* ``thread``: one estimate at the window's start, in a second thread (as the status loop ran it every 10 s);
* ``steps``: one estimate at the window's start as steps (:func:`mocapd.pipeline.scheduler.camera_offset_steps`)
  on the tick's own thread in the time between ticks, one after another until the next tick is due.

Prints JSON: per way, ticks solved and missed, the tick's wall time and its waiting (wall - its thread's CPU: the
interpreter lock held by the other thread, and the machine's other processes) as median and p90 in ms, the
estimates finished and how long each took (wall, median)::

    .venv/bin/python tools/bench_offset_estimate.py --seconds 96
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mocapd.core.imu import IMU_SET_13
from mocapd.core.sorting import Detections2D
from mocapd.pipeline.scheduler import camera_offset_steps, estimate_camera_offsets
from mocapd.service.bench.machine import machine
from mocapd.service.bench.solver import synthetic_case, synthetic_prior
from mocapd.sim.world import SyntheticWorld

PERIOD_S = 1 / 60
WAYS = ("none", "thread", "steps")
CYCLE = ("thread", "none", "steps", "none")  # an estimate that outlasts its window spills into a "none" one
Frames = list[tuple[list[int], list[Detections2D]]]


def recorded_frames(seconds: float, people: int = 2, seed: int = 3, noise_seed: int = 0) -> tuple[list[str], Frames]:
    """``seconds`` of a synthetic 4-camera rig's 30 Hz detections of ``people`` (the world's ``seed``, the
    detection noise's ``noise_seed``), per camera (times, frames); the cameras' names beside them."""
    world = SyntheticWorld(4, people, 0, seed=seed)
    rng = np.random.default_rng(noise_seed)
    period = round(1e9 / 30)
    frames: Frames = [([], []) for _ in range(4)]
    for k in range(round(seconds * 30)):
        for c in range(4):
            t = k * period + c * period // 4
            frames[c][0].append(t)
            frames[c][1].append(world.detections(c, t / 1e9, rng))
    return [c.name for c in world.cameras], frames


def _summary(rows: list[tuple[float, float] | None], took: list[float]) -> dict[str, Any]:
    real = np.array([r for r in rows if r is not None]) * 1e3
    wall, wait = real[:, 0], real[:, 0] - real[:, 1]
    return {"ticks": len(real), "missed": len(rows) - len(real),
            "missed_pct": round(100 * (len(rows) - len(real)) / max(len(rows), 1), 1),
            "wall_ms_p50": round(float(np.median(wall)), 2), "wall_ms_p90": round(float(np.percentile(wall, 90)), 2),
            "waiting_ms_p50": round(float(np.median(wait)), 2),
            "waiting_ms_p90": round(float(np.percentile(wait, 90)), 2),
            "tick_cpu_ms_p50": round(float(np.median(real[:, 1])), 2), "estimates_finished": len(took),
            "estimate_wall_s_p50": round(float(np.median(took)), 3) if took else None}  # fmt: skip


def run(seconds: float, window_s: float, kept_s: float) -> dict[str, Any]:
    names, frames = recorded_frames(kept_s)
    current = (0,) * len(names)
    case = synthetic_case(4, IMU_SET_13, 2, 2000, synthetic_prior(), 0)
    took: dict[str, list[float]] = {w: [] for w in WAYS}

    def in_thread() -> None:
        t0 = time.monotonic()
        estimate_camera_offsets(names, frames, current)
        took["thread"].append(time.monotonic() - t0)

    ticks: dict[str, list[tuple[float, float] | None]] = {w: [] for w in WAYS}
    with threadpool_limits(limits=1):
        for f in range(1, 30):  # the kernel loaded (or compiled) before timing
            for s, o in zip(case.solvers, case.observations, strict=True):
                s.solve(o[f])
        start = due = time.monotonic()
        f, window, steps, steps_t0 = 30, -1, None, 0.0
        while time.monotonic() - start < seconds:
            if int((time.monotonic() - start) // window_s) != window:  # a new window: its way's one estimate
                window = int((time.monotonic() - start) // window_s)
                way = CYCLE[window % len(CYCLE)]
                if way == "thread":
                    threading.Thread(target=in_thread, daemon=True).start()
                elif way == "steps":
                    steps, steps_t0 = camera_offset_steps(names, frames, current), time.monotonic()
            while steps is not None and time.monotonic() < due:  # the event loop's order: steps, then the tick
                try:
                    next(steps)
                except StopIteration:
                    steps = None
                    took["steps"].append(time.monotonic() - steps_t0)
            time.sleep(max(0.0, due - time.monotonic()))
            t0, c0 = time.monotonic(), time.thread_time()
            for s, o in zip(case.solvers, case.observations, strict=True):
                s.solve(o[f])
            ticks[way].append((time.monotonic() - t0, time.thread_time() - c0))
            f = f + 1 if f + 1 < 2000 else 30
            due += PERIOD_S
            behind = int((time.monotonic() - due) / PERIOD_S)
            if behind > 0:  # ticks that cannot be caught up are skipped (the daemon's TickPlan)
                ticks[way].extend([None] * behind)
                due += behind * PERIOD_S
    return {"ways": {w: _summary(ticks[w], took[w]) for w in WAYS}, "seconds": seconds, "window_s": window_s,
            "seconds_kept": kept_s, "frames_per_camera": len(frames[0][0]), "machine": machine()}  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=96.0, help="whole run, s")
    parser.add_argument("--window", type=float, default=4.0, help="length of each way's window, s")
    parser.add_argument("--seconds-kept", type=float, default=10.0,
                        help="keypoints the estimate reads, s (the status loop's first estimate: 10)")  # fmt: skip
    args = parser.parse_args(argv)
    print(json.dumps(run(args.seconds, args.window, args.seconds_kept), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
