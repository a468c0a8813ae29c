"""Delayed vs predicted output at the moment of publishing, on the synthetic rig's recorded motion; prints JSON.

Developer benchmark, not a ``mocapd bench`` verb (those are the benchmarks a user runs).

Runs the daemon of ``mocapd demo --synthetic`` (4 cameras at 30 Hz with 50 ms detection delay, 2 people, one
wearing 13 simulated Xsens IMUs streaming Xbus on pseudo-terminals at 100 Hz; output at ``--rate`` Hz with
``--latency`` s fixed latency) in predicted output. Every published frame of the suit wearer carries both poses:
the delayed solve (``PersonPose.solved``, what ``output = "delayed"`` publishes) and the prediction carried to
the IMUs' newest instant, so both are measured on the same frames, under the same load. A sink records each
frame with the host time at which it is published; afterwards each pose is scored against the truth **at that
moment**:

- bone orientation error: mean angle over the 21 bones between the pose's global rotations and the truth's (and
  over the 13 bones that carry a sensor: the others are only as good as the solve makes them);
- joint position error: mean distance over the 21 joints (the pose on its own body-sized skeleton);
- IMU-sample -> publish latency: publish time minus the instant the pose is for (the solve instant when delayed;
  the newest IMU sample every live sensor of the suit has, as mapped to the host clock, when predicted).

With ``--heading-error DEG`` (and ``--heading-drift DEG_PER_MIN``) every simulated IMU reports its heading off by
a different offset spread over ±DEG, drifting, and the heading correction is measured end to end as well: the
residual per sensor (applied offset + injected error, which ``tests/test_heading.py`` checks against the truth's
bone orientations) over time.

    .venv/bin/python tools/bench_prediction.py [--seconds 60] [--latency 0.15] [--rate 60]
                                               [--heading-error 45 --heading-drift 10]
    .venv/bin/python tools/bench_prediction.py --lockstep [--seconds 60]

``--lockstep`` runs the same world and scheduler tick by tick without clocks or ptys (:mod:`mocapd.sim.lockstep`:
every detection and IMU sample delivered on time, each frame published at its tick): what the method gives,
independent of the machine's load; the default run adds what a real-time daemon on this machine adds.

The machine is shared: the JSON records the load average before and after; both modes are measured on the same
frames, so their ratio does not depend on it.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from mocapd.core.heading import wrap  # noqa: E402
from mocapd.core.kinematics import Kinematics  # noqa: E402
from mocapd.core.per_skeleton import PerSkeleton  # noqa: E402
from mocapd.core.rotations import quat_angle, quat_from_matrix  # noqa: E402
from mocapd.core.skeleton import Skeleton  # noqa: E402
from mocapd.io.prior import resolve_prior  # noqa: E402
from mocapd.pipeline.prediction import PredictionOptions  # noqa: E402
from mocapd.pipeline.scheduler import PoseFrame  # noqa: E402
from mocapd.service.assembly import Assembly, assembled  # noqa: E402
from mocapd.service.config import Config, load_config  # noqa: E402
from mocapd.service.demo.synthetic import synthetic_config  # noqa: E402
from mocapd.sim.lockstep import S, suit_lockstep  # noqa: E402
from mocapd.sim.world import SyntheticWorld  # noqa: E402
from mocapd.sim.xsens import HeadingFault  # noqa: E402


@dataclass(frozen=True)
class Published:
    """One published pose of the suit wearer, both ways, with the host time it was published at."""

    published_ns: int
    t_solve_ns: int
    t_pose_ns: int
    delayed: np.ndarray  # (66,)
    predicted: np.ndarray  # (66,)
    skeleton: Skeleton | None


class PublishLog:
    """A pose sink that keeps what it is given (scoring happens after the run, off the tick loop)."""

    def __init__(self, clock: Any, suit: str) -> None:
        self.clock = clock
        self.suit = suit
        self.frames: list[Published] = []
        self.recording = False

    def publish(self, frame: PoseFrame) -> None:
        now = self.clock()
        if not self.recording:
            return
        for p in frame.people:
            if p.suit == self.suit:
                solved = p.solved if p.solved is not None else p
                self.frames.append(Published(now, frame.t_solve_ns, frame.pose_time_ns(p), solved.theta.copy(),
                                             p.theta.copy(), p.skeleton))  # fmt: skip

    async def start(self) -> None:
        return None

    async def aclose(self) -> None:
        return None


def _summary(values: list[float], digits: int = 2) -> dict[str, float]:
    a = np.asarray(values, dtype=np.float64)
    return {"p50": round(float(np.median(a)), digits), "mean": round(float(a.mean()), digits),
            "p95": round(float(np.percentile(a, 95)), digits)}  # fmt: skip


def score(world: SyntheticWorld, person: int, epoch_ns: int, frames: list[Published]) -> dict[str, Any]:
    """Both modes against the truth at the moment of publishing, and at the instant each pose is for (what the
    solve and the prediction themselves get wrong, without the lag)."""
    models = PerSkeleton(world.kin, Kinematics)
    keys = (
        "orientation_deg",
        "sensor_bones_orientation_deg",
        "joint_mm",
        "own_instant_orientation_deg",
        "own_instant_joint_mm",
        "imu_to_publish_ms",
    )
    sensor_bones = [m.bone_index for m in world.suits[0].mounts]
    out: dict[str, dict[str, list[float]]] = {m: {k: [] for k in keys} for m in ("delayed", "predicted")}
    for f in frames:
        truth = world.kin.forward(world.theta_at(person, (f.published_ns - epoch_ns) / 1e9))
        for mode, theta, t_pose in (("delayed", f.delayed, f.t_solve_ns), ("predicted", f.predicted, f.t_pose_ns)):
            fk = models.get(f.skeleton).forward(theta)
            own = world.kin.forward(world.theta_at(person, (t_pose - epoch_ns) / 1e9))
            got = quat_from_matrix(fk.rotations)
            angles = np.degrees(quat_angle(got, quat_from_matrix(truth.rotations)))
            r = out[mode]
            r["orientation_deg"].append(float(angles.mean()))
            r["sensor_bones_orientation_deg"].append(float(angles[sensor_bones].mean()))
            r["joint_mm"].append(1e3 * float(np.linalg.norm(fk.positions - truth.positions, axis=1).mean()))
            r["own_instant_orientation_deg"].append(
                float(np.degrees(quat_angle(got, quat_from_matrix(own.rotations))).mean())
            )
            r["own_instant_joint_mm"].append(1e3 * float(np.linalg.norm(fk.positions - own.positions, axis=1).mean()))
            r["imu_to_publish_ms"].append((f.published_ns - t_pose) / 1e6)
    result: dict[str, Any] = {m: {k: _summary(v) for k, v in r.items()} for m, r in out.items()}
    d, p = result["delayed"], result["predicted"]
    result["predicted_over_delayed"] = {
        "orientation_p50": round(p["orientation_deg"]["p50"] / d["orientation_deg"]["p50"], 3),
        "orientation_mean": round(p["orientation_deg"]["mean"] / d["orientation_deg"]["mean"], 3),
        "sensor_bones_orientation_p50": round(
            p["sensor_bones_orientation_deg"]["p50"] / d["sensor_bones_orientation_deg"]["p50"], 3
        ),
        "joint_p50": round(p["joint_mm"]["p50"] / d["joint_mm"]["p50"], 3),
    }
    return result


def _config(args: argparse.Namespace) -> Config:
    cfg = load_config()
    if args.body_size_s is not None:
        cfg = cfg.model_copy(update={"daemon": cfg.daemon.model_copy(update={"body_size_s": args.body_size_s})})
    return cfg


def run_lockstep(args: argparse.Namespace) -> dict[str, Any]:
    """The scheduler in lockstep (2 people, one suit): each frame published at its tick, scored there."""
    cfg = _config(args)
    base = cfg.daemon.scheduler_options([f"cam{i}" for i in range(4)])
    options = replace(base, rate_hz=args.rate, latency_ns=round(args.latency * 1e9),
                      prediction=PredictionOptions(output="predicted"))  # fmt: skip
    ls = suit_lockstep(options, cost=cfg.solver.cost, lm=cfg.solver.lm.options(), prior=resolve_prior(cfg.solver.prior),
                       n_people=2)  # fmt: skip
    frames: list[Published] = []
    for _ in range(round((args.warm_up + args.seconds) * args.rate)):
        now = ls.now_ns
        frame = ls.tick()
        if now < S + round(args.warm_up * 1e9):
            continue
        for p in frame.people:
            if p.suit is not None:
                solved = p.solved if p.solved is not None else p
                frames.append(Published(now, frame.t_solve_ns, frame.pose_time_ns(p), solved.theta, p.theta,
                                        p.skeleton))  # fmt: skip
    return {
        "lockstep": True, "latency_s": args.latency, "rate_hz": args.rate, "warm_up_s": args.warm_up,
        "body_size_s": cfg.daemon.body_size_s,
        "seconds": args.seconds, "frames_scored": len(frames), **score(ls.world, 0, 0, frames),
    }  # fmt: skip


def heading_track(demo: Assembly, faults: dict[str, HeadingFault], t_s: float) -> dict[str, float]:
    """Per sensor: the heading error left (degrees) at world time ``t_s``: applied offset + injected error."""
    suit = demo.daemon.scheduler.suits["suit0"]
    offsets = demo.daemon.scheduler.heading.offsets(suit.sensors)
    return {s: round(float(np.degrees(wrap(o + faults[s].angle_rad(t_s)))), 2)
            for s, o in zip(suit.sensors, offsets, strict=True)}  # fmt: skip


def run(args: argparse.Namespace) -> dict[str, Any]:
    cfg = _config(args)
    cfg = cfg.model_copy(update={
        "daemon": cfg.daemon.model_copy(update={"http_port": 0, "latency_s": args.latency,
                                                "output_rate_hz": args.rate}),
        "websocket": cfg.websocket.model_copy(update={"enabled": False}),
    })  # fmt: skip
    cfg = synthetic_config(cfg)
    load0 = os.getloadavg()
    with assembled(cfg) as demo:
        d = demo.daemon
        assert demo.built.world is not None and demo.built.simulated is not None
        # The benchmark's own switch: predicted output (both poses on every frame), whatever config.toml says.
        d.scheduler.options = replace(d.scheduler.options, prediction=PredictionOptions(output="predicted"))
        log = PublishLog(d.clock, "suit0")
        d.sinks.append(log)
        world, epoch = demo.built.world, demo.built.epoch_ns
        faults: dict[str, HeadingFault] = {}
        if args.heading_error or args.heading_drift:
            faults = world.heading_faults(world.suits[0], args.heading_error, args.heading_drift, seed=1)
            for sim in demo.built.simulated.simulators:
                sim.device.heading = faults[f"{sim.device.motion.device_id:08X}"]
        track: list[dict[str, Any]] = []

        async def main() -> dict[str, Any]:
            task = asyncio.create_task(d.run())
            await d.ready.wait()
            t0 = time.monotonic()
            while time.monotonic() - t0 < args.warm_up + args.seconds:
                await asyncio.sleep(0.5)
                log.recording = time.monotonic() - t0 >= args.warm_up
                if faults and d.latest is not None:
                    t_s = (d.latest.t_solve_ns - epoch) / 1e9
                    track.append({"t_s": round(time.monotonic() - t0, 1), **heading_track(demo, faults, t_s)})
            st = d.status()
            d.request_stop()
            await task
            return st

        st = asyncio.run(main())
    result: dict[str, Any] = {
        "rig": {"cameras": 4, "people": 2, "suit_imus": 13, "imu_rate_hz": cfg.synthetic.imu_rate_hz,
                "motion": cfg.synthetic.motion},
        "latency_s": args.latency, "rate_hz": args.rate, "warm_up_s": args.warm_up, "seconds": args.seconds,
        "body_size_s": cfg.daemon.body_size_s, "frames_scored": len(log.frames),
        "output": {k: st["output"][k] for k in ("achieved_hz", "frames", "missed_ticks", "late_ticks")},
        "daemon_latency_ms": {k: st["latency_ms"][k] for k in ("end_to_end", "imu_to_publish", "solve", "publish")},
        **score(world, world.suits[0].person, epoch, log.frames),
        "load_average_before": [round(x, 2) for x in load0],
        "load_average_after": [round(x, 2) for x in os.getloadavg()],
    }  # fmt: skip
    if faults:
        result["heading"] = heading_report(track, faults, st["imu_heading"]["suit0"])
    return result


def heading_report(
    track: list[dict[str, Any]], faults: dict[str, HeadingFault], status: dict[str, Any]
) -> dict[str, Any]:
    """When every observable sensor got (and stayed) within 3°, and the last residuals."""
    observable = [s for s, v in status.items() if v["observable"]]
    outside = [row["t_s"] for row in track if max(abs(row[s]) for s in observable) > 3.0]
    last = track[-1] if track else {}
    return {
        "injected_deg": {s: [f.offset_deg, f.drift_deg_per_min] for s, f in faults.items()},
        "observable": observable,
        "unobservable": {s: status[s]["bone"] for s in status if s not in observable},
        "all_observable_within_3deg_from_s": (outside[-1] + 0.5) if outside else 0.0,
        "final_residual_deg": {s: last.get(s) for s in faults},
        "final_max_observable_deg": max(abs(last[s]) for s in observable) if last else None,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=60.0, help="measured seconds after the warm-up")
    ap.add_argument("--warm-up", type=float, default=15.0, help="seconds before measuring (enrolment, sizing)")
    ap.add_argument("--latency", type=float, default=0.15, help="fixed latency of the delayed solve, s")
    ap.add_argument("--rate", type=float, default=60.0, help="output rate, Hz")
    ap.add_argument(
        "--body-size-s",
        type=float,
        default=None,
        help="[daemon] body_size_s (default config.toml's; 0: everyone on the world's skeleton)",
    )
    ap.add_argument("--heading-error", type=float, default=0.0, help="per-sensor heading offsets over ±this, deg")
    ap.add_argument("--heading-drift", type=float, default=0.0, help="heading drift of every sensor, deg/min")
    ap.add_argument("--lockstep", action="store_true", help="the scheduler tick by tick, no clocks (see above)")
    args = ap.parse_args(argv)
    print(json.dumps(run_lockstep(args) if args.lockstep else run(args), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
