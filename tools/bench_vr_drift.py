#!/usr/bin/env python3
"""Yaw drift of a SlimeVR suit on the synthetic rig, with whatever heading handling the config has.

Developer benchmark, not a ``mocapd bench`` verb (those are the benchmarks a user runs).

One person walks (procedural motion) in a ring of ``--cameras`` synthetic cameras wearing 13 emulated SlimeVR
sensors (``tools/slimevr_rig.py``: the PyPI ``slimevr-tracker-emulator``, in a process of its own, talking to the
daemon's SlimeVR server over loopback UDP).
Each sensor's heading reference drifts at its own rate, drawn once from ``--drift`` degrees per minute with a
random sign (seeded), as gyroscope bias makes 6-axis trackers drift. Every 6th published frame (10 Hz) the
heading error of each of the 13 suit bones is measured against the truth at the frame's solve time:

- ``imu``: the bone orientation the suit gives (``R_ig R_i R_ib⁻¹`` from the ring buffers, before any heading
  correction), the heading part of ``R · R_trueᵀ`` (its twist about world up), in degrees; measured whether or not
  the suit is bound to the person this frame;
- ``imu_corrected``: the same after the scheduler's camera-based heading correction (``R_y(offset) · R``, the
  offsets in use at that moment: what the solver is told; equal to ``imu`` when the correction is off);
- ``solved``: the same for the solved skeleton's bone, in frames where the suit is bound (``suit_bound_fraction``).

Prints one JSON object: per-minute medians over bones and samples of ``|heading error|``, the last 30 s, the injected
drift at the end, the load average, and the daemon's latency summary. Run it twice, once with a config that
leaves heading correction off and once with it on (``--config``), to fill both columns of docs/vr.md.

Usage: ``python tools/bench_vr_drift.py [--seconds 300] [--cameras 2] [--config FILE] [--drift 1 3]``
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import io
import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run as `python tools/bench_vr_drift.py` from a checkout
    sys.path.insert(0, str(REPO))

from mocapd.core.heading import yaw_quat  # noqa: E402
from mocapd.core.kinematics import Kinematics  # noqa: E402
from mocapd.core.per_skeleton import PerSkeleton  # noqa: E402
from mocapd.core.rotations import quat_conjugate, quat_from_matrix, quat_multiply  # noqa: E402
from mocapd.core.skeleton import BONE_INDEX  # noqa: E402
from mocapd.pipeline.ringbuffer import LookupStatus  # noqa: E402
from mocapd.pipeline.scheduler import PoseFrame  # noqa: E402
from mocapd.service.config import load_config  # noqa: E402
from tools.slimevr_rig import SlimeVrRig, build_slimevr_daemon, emulator_process  # noqa: E402


def heading_deg(q_est: np.ndarray, q_true: np.ndarray) -> np.ndarray:
    """Twist about world +Y of ``q_est · q_true⁻¹`` (degrees, (-180, 180]); shapes (..., 4)."""
    d = quat_multiply(q_est, quat_conjugate(q_true))
    out: np.ndarray = np.degrees(2.0 * np.arctan2(d[..., 2], d[..., 0]))
    return (out + 180.0) % 360.0 - 180.0


class DriftProbe:
    """A pose sink measuring the suit's heading errors every ``every``-th frame."""

    def __init__(self, every: int = 6) -> None:
        self.every = every
        self.rig: SlimeVrRig | None = None
        # (t_s, median |imu| error, median |solved| error, median |corrected imu| error)
        self.samples: list[tuple[float, float, float, float]] = []
        self.frames = 0
        self._kin: PerSkeleton[Kinematics] | None = None

    def publish(self, frame: PoseFrame) -> None:
        self.frames += 1
        rig = self.rig
        if rig is None or self.frames % self.every:
            return
        world = rig.world
        suit = rig.daemon.rig.suits[0]
        t = (frame.t_solve_ns - rig.epoch_ns) / 1e9
        bones = np.array([BONE_INDEX[suit.calibration.bones[s]] for s in suit.sensors])
        q_true = quat_from_matrix(world.kin.forward(world.theta_at(0, t)).rotations[bones])
        # What the suit tells the solver, bound or not: the buffered orientations through the calibration.
        by_sensor = {b.sensor: b for b in rig.daemon.imu.bone_orientations(frame.t_solve_ns, suit.calibration)}
        q_imu = np.array([
            by_sensor[s].quat if by_sensor[s].status is LookupStatus.OK else [np.nan] * 4 for s in suit.sensors
        ])  # fmt: skip
        e_imu = float(np.nanmedian(np.abs(heading_deg(q_imu, q_true)))) if np.isfinite(q_imu).any() else np.nan
        q_corr = quat_multiply(yaw_quat(rig.daemon.scheduler.heading.offsets(suit.sensors)), q_imu)
        e_corr = float(np.nanmedian(np.abs(heading_deg(q_corr, q_true)))) if np.isfinite(q_corr).any() else np.nan
        person = next((p for p in frame.people if p.suit == "suit0"), None)
        e_solved = np.nan
        if person is not None:
            if self._kin is None:
                self._kin = PerSkeleton(Kinematics(world.skeleton), Kinematics)
            q_solved = quat_from_matrix(self._kin.get(person.skeleton).forward(person.theta).rotations[bones])
            e_solved = float(np.median(np.abs(heading_deg(q_solved, q_true))))
        self.samples.append((t, e_imu, e_solved, e_corr))

    async def start(self) -> None:
        return None

    async def aclose(self) -> None:
        return None


def _median(x: np.ndarray) -> float | None:
    x = x[np.isfinite(x)]
    return round(float(np.median(x)), 2) if len(x) else None


def _window(sel: np.ndarray) -> dict[str, Any]:
    return {
        "samples": len(sel),
        "suit_bound_fraction": round(float(np.isfinite(sel[:, 2]).mean()), 3) if len(sel) else None,
        "imu_heading_error_deg_median": _median(sel[:, 1]),
        "imu_corrected_heading_error_deg_median": _median(sel[:, 3]),
        "solved_heading_error_deg_median": _median(sel[:, 2]),
    }


def summarise(samples: list[tuple[float, float, float, float]], seconds: float) -> dict[str, Any]:
    a = np.array(samples) if samples else np.zeros((0, 4))
    per_minute = [
        {"minute": m + 1, **_window(a[(a[:, 0] >= 60 * m) & (a[:, 0] < 60 * (m + 1))])}
        for m in range(int(np.ceil(seconds / 60.0)))
    ]
    last = a[a[:, 0] >= a[-1, 0] - 30.0] if len(a) else a
    return {"per_minute": per_minute, "last_30s": _window(last)}


async def run(args: argparse.Namespace) -> dict[str, Any]:
    cfg = load_config(args.config)
    cfg = cfg.model_copy(update={"daemon": cfg.daemon.model_copy(update={"http_port": 0}),
                                 "websocket": cfg.websocket.model_copy(update={"enabled": False})})  # fmt: skip
    rng = np.random.default_rng(args.seed)
    lo, hi = args.drift
    drift = rng.uniform(lo, hi, 13) * rng.choice([-1.0, 1.0], 13)
    probe = DriftProbe()
    rig = build_slimevr_daemon(cfg, cameras=args.cameras, drift_deg_per_min=drift, sinks=[probe], seed=args.seed)
    probe.rig = rig
    d = rig.daemon
    try:
        task = asyncio.create_task(d.run())
        await asyncio.wait_for(d.ready.wait(), 300)
        while d.imu.slimevr is None or d.imu.slimevr.port == 0:
            await asyncio.sleep(0.05)
        t_start = time.monotonic()
        proc = emulator_process(rig, d.imu.slimevr.port, args.seconds + 5, cameras=args.cameras, motion="procedural",
                                seed=args.seed, pace=args.emulator_pace)  # fmt: skip
        await asyncio.sleep(args.seconds)
        status = d.status()
        proc.terminate()
        proc.join(5)
        d.request_stop()
        await asyncio.wait_for(task, 10)
        elapsed = time.monotonic() - t_start
    finally:
        rig.close()
    (tracker,) = status["imu"]["slimevr"]["trackers"]
    return {
        "benchmark": "vr_drift",
        "config": str(args.config or "shipped config.toml"),
        "heading_correction": cfg.daemon.heading_correction,
        "seconds": args.seconds,
        "elapsed_s": round(elapsed, 1),
        "cameras": args.cameras,
        "emulator_pace": args.emulator_pace,
        "drift_deg_per_min": [round(float(v), 2) for v in drift],
        "injected_heading_offset_at_end_deg_median_abs": round(float(np.median(np.abs(drift))) * args.seconds / 60, 1),
        **summarise(probe.samples, args.seconds),
        "latency_ms_end_to_end": status["latency_ms"]["end_to_end"],
        "output": {k: status["output"][k] for k in ("configured_hz", "achieved_hz", "frames", "missed_ticks")},
        "slimevr": {k: tracker[k] for k in ("packets", "lost", "reordered", "rtt_ms")},
        "loadavg": [round(v, 2) for v in os.getloadavg()],
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=300.0)
    p.add_argument("--cameras", type=int, default=2)
    p.add_argument("--config", type=Path, default=None, help="config file (default: the shipped one)")
    p.add_argument("--drift", type=float, nargs=2, default=(1.0, 3.0), metavar=("MIN", "MAX"),
                   help="per-sensor drift magnitude range, degrees per minute")  # fmt: skip
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--emulator-pace", type=float, default=0.1,
                   help="scale of the emulator's own sleeps (1: as published, ~10 updates/s per sensor; 0.1: ~50-100, "
                   "a real tracker's rate)")  # fmt: skip
    args = p.parse_args()
    chatter = io.StringIO()  # the emulator prints every packet it does not expect
    with contextlib.redirect_stdout(chatter):
        result = asyncio.run(run(args))
    print(json.dumps(result))


if __name__ == "__main__":
    main()
