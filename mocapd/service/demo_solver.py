"""``mocapd demo`` (until the daemon lands): the solver running live on a synthetic rig at the output rate.

Two people walk in an 8-camera, 13-IMU rig; each tick at 60 Hz the solver fuses their noisy synthetic
measurements, paced by the wall clock as the live scheduler will be. Once a second it prints the output rate,
the solve time and the joint error against the known truth.
"""

from __future__ import annotations

import time

import numpy as np

from mocapd.core.imu import IMU_SET_13
from mocapd.core.kinematics import Kinematics
from mocapd.io.prior import resolve_prior
from mocapd.service.bench_solver import synthetic_case
from mocapd.service.config import load_config


def run(seconds: float = 10.0, rate_hz: float = 60.0, people: int = 2) -> int:
    frames = int(seconds * rate_hz)
    print(f"mocapd demo: {people} people, 8 cameras and 13 IMUs each, {rate_hz:.0f} Hz for {seconds:.0f} s")
    print("preparing the synthetic rig and the solver kernel ...", flush=True)
    prior = resolve_prior(load_config().solver.prior)  # the shipped CMU prior unless config.toml says otherwise
    if prior is None:
        raise SystemExit("mocapd demo needs a pose prior: set [solver] prior in config.toml")
    case = synthetic_case(8, IMU_SET_13, people, frames, prior, seed=1)
    kin = Kinematics(case.solvers[0].skeleton)
    case.solvers[0].solve(case.observations[0][0], update_state=False)  # compile / load the kernel now
    period = 1.0 / rate_hz
    start = last_report = time.monotonic()
    next_tick = start
    solve_s: list[float] = []
    errors: list[float] = []
    late = 0
    for f in range(1, frames + 1):
        next_tick += period
        t0 = time.perf_counter()
        for solver, obs, truth in zip(case.solvers, case.observations, case.truth, strict=True):
            theta = solver.solve(obs[f]).theta
            joints = kin.forward(theta).positions - kin.forward(truth[f]).positions
            errors.append(float(np.linalg.norm(joints, axis=1).mean()))
        solve_s.append(time.perf_counter() - t0)
        now = time.monotonic()
        if now > next_tick:
            late += 1  # the tick's work overran its period
        else:
            time.sleep(next_tick - now)
        if now - last_report >= 1.0:
            print(
                f"t={now - start:5.1f} s  output {len(solve_s) / (now - last_report):5.1f} Hz"
                f"  solve p50 {1e3 * np.median(solve_s):5.2f} ms ({people} people)"
                f"  mean joint error {1e3 * np.mean(errors):5.1f} mm  late ticks {late}",
                flush=True,
            )
            solve_s.clear()
            errors.clear()
            last_report = now
    print(f"done: {frames} ticks, {late} late")
    return 0
