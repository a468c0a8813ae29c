"""``mocapd bench latency``: the synthetic rig run through the one assembly path for a while, measured from
inside by a monitor, as JSON.

Reports the end-to-end latency (solve instant -> frame published; it includes the configured latency),
per-stage latency and CPU, the output rate achieved against the configured one (missed ticks), the detector
delay, the process CPU, resident memory over the run (growth after the warm-up, when the motion loop and every
cache have been filled once) and the keypoint error (3D, 17 observed sites) against the synthetic truth.
"""

from __future__ import annotations

import asyncio
import os
import resource
import time
from typing import Any, Literal

from mocapd.service import assembly
from mocapd.service.assembly import RunOptions
from mocapd.service.bench.machine import machine
from mocapd.service.config import Config, load_config
from mocapd.service.daemon import Daemon
from mocapd.service.demo.synthetic import synthetic_config
from mocapd.sim.truth import RootRelativeError

WARM_UP_S = 15.0  # > one motion loop (12 s): the simulators' packet caches are full


def _rss_mb() -> float:
    with open("/proc/self/statm") as fh:
        pages = int(fh.read().split()[1])
    return pages * os.sysconf("SC_PAGE_SIZE") / 2**20


def _after_warm_up(warm: tuple[int, int, int] | None, st: dict[str, Any], wall_s: float) -> dict[str, Any]:
    """Output counters from the end of the warm-up on (None before a run that long)."""
    if warm is None or wall_s <= WARM_UP_S:
        return {"after_warm_up": None}
    missed, late, frames = warm
    n = st["output"]["frames"] - frames
    return {"after_warm_up": {"seconds": round(wall_s - WARM_UP_S, 1), "frames": n,
                              "achieved_hz": round(n / (wall_s - WARM_UP_S), 2),
                              "missed_ticks": st["output"]["missed_ticks"] - missed,
                              "late_ticks": st["output"]["late_ticks"] - late}}  # fmt: skip


def _bench_base(output: Literal["delayed", "predicted"] | None = None) -> Config:
    """The shipped config with the daemon's ports free (0) and, where given, this output mode."""
    base = load_config()
    daemon = base.daemon.model_copy(update={"http_port": 0, **({"output": output} if output else {})})
    return base.model_copy(update={"daemon": daemon, "websocket": base.websocket.model_copy(update={"port": 0})})


def run(seconds: float = 60.0, cameras: int = 4, people: int = 2) -> dict[str, Any]:
    """Run the synthetic rig (``mocapd demo --synthetic``'s generated config, through the one assembly path) for
    ``seconds`` after READY and report what it did."""
    base = _bench_base()
    base = base.model_copy(
        update={"synthetic": base.synthetic.model_copy(update={"people": people, "suits": min(1, people)})}
    )
    cfg = synthetic_config(base, cameras)
    syn = cfg.synthetic
    rig = {"cameras": cameras, "people": people, "suits": syn.suits, "imus": 13 * syn.suits,
           "camera_rate_hz": syn.camera_rate_hz, "detection_delay_ms": 1e3 * syn.detection_delay_s,
           "imu_rate_hz": syn.imu_rate_hz, "transport": "Xbus over pseudo-terminals (mocapd.sim.suits)"}  # fmt: skip
    return _measure(cfg, seconds, rig, RunOptions(), "median_keypoint_error_mm")


def run_imu(seconds: float = 60.0, output: Literal["delayed", "predicted"] | None = None) -> dict[str, Any]:
    """Run ``mocapd demo --imu-only``'s rig (one simulated 13-sensor Xsens suit on pseudo-terminals, no camera,
    through the one assembly path as ``mocapd run`` with a suit) for ``seconds`` after READY and report what it did;
    the error is the suit wearer's joints against the truth with both roots at the origin (nothing fixes the root's
    place in the room without cameras)."""
    from mocapd.service.demo.imu_only import IMU_RATE_HZ, simulated_suit
    from mocapd.sim.truth import RootRelativeError

    with simulated_suit(_bench_base(output)) as sim:
        truth = RootRelativeError(sim.world, sim.epoch_ns)
        rig = {"cameras": 0, "people": 1, "suits": 1, "imus": len(sim.suits.ports), "imu_rate_hz": IMU_RATE_HZ,
               "transport": "Xbus over pseudo-terminals (mocapd.sim.suits)"}  # fmt: skip
        return _measure(sim.config, seconds, rig, RunOptions(sinks=[truth]), "median_root_relative_error_mm", truth)


def _measure(cfg: Config, seconds: float, rig: dict[str, Any], options: RunOptions, error_key: str,
             truth: RootRelativeError | None = None) -> dict[str, Any]:  # fmt: skip
    """Run ``cfg`` through the assembly for ``seconds`` after READY, measured from inside; the JSON report."""
    load0 = os.getloadavg()
    rss: list[tuple[float, float]] = []
    run_stats: dict[str, Any] = {}

    async def measure(d: Daemon) -> None:
        t0 = time.monotonic()
        cpu0 = resource.getrusage(resource.RUSAGE_SELF)
        while time.monotonic() - t0 < seconds:
            await asyncio.sleep(1.0)
            rss.append((round(time.monotonic() - t0, 1), round(_rss_mb(), 1)))
            if "warm" not in run_stats and time.monotonic() - t0 >= WARM_UP_S and d.plan is not None:
                # Ticks missed while people enrol and their solvers are first built are start-up, not rate.
                run_stats["warm"] = (d.plan.missed, d.plan.late, d.scheduler.frame)
        cpu1 = resource.getrusage(resource.RUSAGE_SELF)
        wall = time.monotonic() - t0
        run_stats["process_cpu_fraction_of_one_core"] = round(
            (cpu1.ru_utime + cpu1.ru_stime - cpu0.ru_utime - cpu0.ru_stime) / wall, 3
        )
        run_stats["wall_s"] = round(wall, 1)
        run_stats["imu_streaming"] = sum(1 for x in d.imu.devices if x.streaming.is_set())
        run_stats["status"] = d.status()

    async def main() -> assembly.Assembly | None:
        holder: list[assembly.Assembly] = []
        await assembly.run(cfg, options, monitor=measure, on_ready=holder.append)
        return holder[0] if holder else None

    done = asyncio.run(main())
    st = run_stats["status"]
    frames = st["output"]["frames"]
    after = [m for t, m in rss if t >= WARM_UP_S]
    scorer = truth if truth is not None else (done.truth if done is not None else None)
    err = scorer.recent_mm(10**9) if scorer is not None else None
    return {
        "rig": rig,
        "duration_s": run_stats["wall_s"],
        "configured": {"output_rate_hz": cfg.daemon.output_rate_hz, "latency_ms": st["output"]["latency_s"] * 1e3,
                       "latency_mode": "auto" if cfg.daemon.latency_s == "auto" else "fixed",  # ms: at the end
                       "output": cfg.daemon.output},
        "output": {"frames": frames, "achieved_hz": round(frames / run_stats["wall_s"], 2),
                   "missed_ticks": st["output"]["missed_ticks"], "late_ticks": st["output"]["late_ticks"],
                   **_after_warm_up(run_stats.get("warm"), st, run_stats["wall_s"])},
        "end_to_end_ms": st["latency_ms"]["end_to_end"],
        "stage_latency_ms": {k: v for k, v in st["latency_ms"].items() if k != "end_to_end"},
        "stage_cpu_s": st["cpu_s"],
        "stage_cpu_ms_per_frame": {k: round(1e3 * v / max(frames, 1), 3) for k, v in st["cpu_s"].items()},
        # Per person and tick, by stage of the person job (flip search, LM solve, body sizing): CPU ms.
        "person_cpu_ms": st["person_cpu_ms"],
        "solve_threads": st["solve_threads"],
        "governor": st["governor"],
        "process_cpu_fraction_of_one_core": run_stats["process_cpu_fraction_of_one_core"],
        "memory_mb": {
            "rss_samples": rss[:: max(1, len(rss) // 12)],
            "after_warm_up_first": after[0] if after else None,
            "after_warm_up_last": after[-1] if after else None,
            "growth_after_warm_up": round(after[-1] - after[0], 1) if len(after) > 1 else None,
            "warm_up_s": WARM_UP_S,
        },
        error_key: None if err is None else round(err, 2),
        "imu_devices_streaming_at_end": run_stats["imu_streaming"],
        "imu_disconnects": sum(x["disconnects"] for x in st["imu"]["devices"]),
        "task_failures": {k: v["failures"] for k, v in st["tasks"].items()},
        "machine": {**machine(), "loadavg_at_start": [round(x, 2) for x in load0]},
    }  # fmt: skip
