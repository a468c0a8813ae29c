"""``mocapd bench solver``: per-frame solver cost on warm-started moving sequences, as JSON.

Configurations (issue: kinematic core):

- ``a``: 8 cameras × 17 keypoints + 13 IMUs + prior + floor
- ``b``: 4 cameras + 6 IMUs (+ prior + floor)
- ``c``: 0 cameras + 13 IMUs
- ``d``: 1 camera + 13 IMUs
- ``e``: four people of configuration ``a`` solved per frame (reported per frame and per person-frame)
- ``scipy_a``: problem ``a`` solved by ``scipy.optimize.least_squares`` with a finite-difference Jacobian on the
  same frames, same warm start and the same robust cost, as a speed ratio.

Measurements are synthetic but noisy (2 px keypoint noise with 2 % gross outliers, 1° IMU orientation noise,
0.2 m/s² acceleration noise) so the solver does real work each frame. BLAS is limited to one thread.
Wall-clock numbers on a shared machine are noisy: medians are reported, and the baseline runs in the same process.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray
from threadpoolctl import threadpool_info, threadpool_limits

from mocapd.core.camera import Camera
from mocapd.core.imu import IMU_SET_6, IMU_SET_13, default_mounts
from mocapd.core.keypoints import coco17_targets
from mocapd.core.kinematics import Kinematics
from mocapd.core.prior import PcaPrior
from mocapd.core.rotations import quat_from_rotvec, quat_multiply
from mocapd.core.skeleton import Skeleton
from mocapd.core.solver import Observations, PoseSolver
from mocapd.core.synthetic import exact_observations, moving_sequence, ring_rig
from mocapd.service.bench.machine import machine

FloatArray = NDArray[np.float64]


@dataclass
class SyntheticCase:
    """Solvers, truth and noisy observations of a synthetic multi-person rig."""

    solvers: list[PoseSolver]
    truth: list[FloatArray]  # per person (n_frames, 66)
    observations: list[list[Observations]]  # per person, per frame


def _noisy(obs: list[Observations], rng: np.random.Generator) -> list[Observations]:
    out = []
    for o in obs:
        kp = o.keypoints
        if kp is not None and kp.size:
            kp = kp + rng.normal(scale=2.0, size=kp.shape)
            bad = rng.uniform(size=kp.shape[:2]) < 0.02
            kp[bad] += rng.uniform(-300, 300, size=(int(bad.sum()), 2))
        q = o.imu_orientations
        if q is not None:
            q = quat_multiply(quat_from_rotvec(rng.normal(scale=np.deg2rad(1.0), size=(q.shape[0], 3))), q)
        a = o.imu_accelerations
        if a is not None:
            a = a + rng.normal(scale=0.2, size=a.shape)
        out.append(replace(o, keypoints=kp, imu_orientations=q, imu_accelerations=a))
    return out


def synthetic_case(
    n_cams: int, imu_set: tuple[str, ...], n_people: int, n_frames: int, prior: PcaPrior, seed: int
) -> SyntheticCase:
    rng = np.random.default_rng(seed)
    sk = Skeleton.from_height(1.75)
    cams: list[Camera] = ring_rig(8)[:n_cams]
    targets = coco17_targets(sk)
    imus = default_mounts(imu_set, sk)
    solvers, truths, observations = [], [], []
    for p in range(n_people):
        truth = moving_sequence(sk, n_frames + 1, seed=seed + 100 * p, start_still_s=1.0)
        truth[:, [0, 2]] += [1.2 * np.cos(p * np.pi / 2), 1.2 * np.sin(p * np.pi / 2)] if n_people > 1 else 0.0
        obs = _noisy(exact_observations(sk, cams, targets, imus, truth), rng)
        s = PoseSolver(sk, cams, targets, imus, prior)
        s.reset(truth[0])
        solvers.append(s)
        truths.append(truth)
        observations.append(obs)
    return SyntheticCase(solvers, truths, observations)


def _run(case: SyntheticCase, n_frames: int) -> dict[str, Any]:
    kin = Kinematics(case.solvers[0].skeleton)
    times: list[float] = []
    iters: list[int] = []
    errs: list[float] = []
    local_errs: list[float] = []
    for f in range(1, n_frames + 1):
        t0 = time.perf_counter()
        results = [s.solve(obs[f]) for s, obs in zip(case.solvers, case.observations, strict=True)]
        times.append(time.perf_counter() - t0)
        iters.extend(r.summary.iterations for r in results)
        for r, truth in zip(results, case.truth, strict=True):
            a, b = kin.forward(r.theta).positions, kin.forward(truth[f]).positions
            errs.append(float(np.linalg.norm(a - b, axis=1).mean()))
            local_errs.append(float(np.linalg.norm((a - a[0]) - (b - b[0]), axis=1).mean()))
    ms = np.array(times) * 1e3
    n_people = len(case.solvers)
    return {
        "people": n_people,
        "frames": n_frames,
        "median_ms": round(float(np.median(ms)), 3),
        "p90_ms": round(float(np.percentile(ms, 90)), 3),
        "median_ms_per_person": round(float(np.median(ms)) / n_people, 3),
        "mean_iterations": round(float(np.mean(iters)), 2),
        "mean_joint_error_mm": round(1e3 * float(np.mean(errs)), 2),
        "mean_root_relative_joint_error_mm": round(1e3 * float(np.mean(local_errs)), 2),
    }


def _scipy_baseline(case: SyntheticCase, n_frames: int) -> dict[str, Any]:
    """Problem ``a`` by scipy's least_squares (MINPACK LM, 2-point finite differences) on the same robust cost."""
    from scipy.optimize import least_squares

    solver, obs = case.solvers[0], case.observations[0]
    losses = solver._losses()
    theta = case.truth[0][0].copy()
    solver.reset(theta)
    times, nfev = [], []

    def residuals(x: FloatArray, o: Observations) -> FloatArray:
        # Blocks scaled so that ||r_b||² = ρ(s_b): least squares on these minimises ½ Σ ρ, our cost.
        parts = []
        for name, f in solver.term_residuals(x, o).items():
            s = np.einsum("ij,ij->i", f, f)
            rho = losses[name].evaluate(s)[0]
            scale = np.sqrt(np.where(s > 0, rho / np.where(s > 0, s, 1.0), 1.0))
            parts.append((f * scale[:, None]).ravel())
        return np.concatenate(parts)

    for f in range(1, n_frames + 1):
        t0 = time.perf_counter()
        res = least_squares(residuals, theta, jac="2-point", method="lm", args=(obs[f],), ftol=1e-6, xtol=1e-8)
        times.append(time.perf_counter() - t0)
        nfev.append(res.nfev)
        theta = res.x
        solver.push_history(theta)
    ms = np.array(times) * 1e3
    return {
        "frames": n_frames,
        "median_ms": round(float(np.median(ms)), 3),
        "p90_ms": round(float(np.percentile(ms, 90)), 3),
        "mean_function_evaluations": round(float(np.mean(nfev)), 1),
    }


def synthetic_prior() -> PcaPrior:
    """A PCA prior fitted on a broad pool of synthetic poses (until the trained default prior exists)."""
    sk = Skeleton.from_height(1.75)
    pool = [moving_sequence(sk, 2000, seed=s, amplitude=a) for s, a in ((900, 1.0), (901, 2.0), (902, 3.0))]
    return PcaPrior.fit(np.concatenate(pool), 0.95)


def run(frames: int = 600, scipy_frames: int = 30, seed: int = 0) -> dict[str, Any]:
    """Run every configuration and return the JSON-able report."""
    load0 = os.getloadavg()
    from mocapd.io.prior import resolve_prior
    from mocapd.service.config import load_config

    # The configured prior (the shipped CMU prior by default); the synthetic one only if config says "none".
    prior = resolve_prior(load_config().solver.prior) or synthetic_prior()
    import scipy.optimize  # noqa: F401  (load scipy's own BLAS before limiting threads, so the limit covers it)

    with threadpool_limits(limits=1):
        t0 = time.perf_counter()
        warm = synthetic_case(8, IMU_SET_13, 1, 3, prior, seed)
        _run(warm, 2)  # compiles the kernel, or loads it from numba's cache
        compile_s = time.perf_counter() - t0
        configs = {
            "a_8cam_13imu": (8, IMU_SET_13, 1),
            "b_4cam_6imu": (4, IMU_SET_6, 1),
            "c_0cam_13imu": (0, IMU_SET_13, 1),
            "d_1cam_13imu": (1, IMU_SET_13, 1),
            "e_4people_8cam_13imu": (8, IMU_SET_13, 4),
        }
        out: dict[str, Any] = {}
        for name, (n_cams, imu_set, people) in configs.items():
            out[name] = _run(synthetic_case(n_cams, imu_set, people, frames, prior, seed), frames)
        # The baseline and our solver on the very same first frames of problem a, back to back.
        ours = _run(synthetic_case(8, IMU_SET_13, 1, scipy_frames, prior, seed), scipy_frames)
        base = _scipy_baseline(synthetic_case(8, IMU_SET_13, 1, scipy_frames, prior, seed), scipy_frames)
        blas = [{k: i.get(k) for k in ("internal_api", "num_threads")} for i in threadpool_info()]
    out["scipy_a_8cam_13imu"] = base
    out["speedup_vs_scipy_same_frames"] = round(base["median_ms"] / ours["median_ms"], 1)
    out["ours_on_scipy_frames_median_ms"] = ours["median_ms"]
    out["kernel_compile_or_cache_load_s"] = round(compile_s, 2)
    out["machine"] = {
        **machine(),
        "numpy": np.__version__,
        "blas_in_run": blas,
        "loadavg_start": [round(x, 2) for x in load0],
        "loadavg_end": [round(x, 2) for x in os.getloadavg()],
    }
    return out
