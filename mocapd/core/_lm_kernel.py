"""Compiled (numba) Levenberg-Marquardt loop around the compiled cost kernel (:mod:`mocapd.core._kernel`).

Why compiled. The kernels that evaluate the cost and the normal equations were compiled already, but the loop
between them (:func:`mocapd.core.lm.levenberg_marquardt`: ~9 iterations a solve, each with finiteness checks,
norms, a trial point and closures that copy H and g) ran as Python: on the 2-core camera demo that was ~60 % of a
person's solve and held the interpreter lock throughout, which the tick thread shares with the capture, tracking
and detector threads (issue 39's profile of the tick: 5.4 ms CPU a tick p50, ``levenberg_marquardt`` 58 % of it).
Here the whole solve is one call that releases the lock (``nogil``): people solve in parallel on the solve pool,
and the other threads run meanwhile.

The same algorithm, step for step, as the Python loop (kept for the numpy backend and the learned fusion term,
and for the test that compares the two): trust-region radius, damping, the acceptance ratio and every stopping
rule. Termination codes index :data:`TERMINATIONS`.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numpy.typing import NDArray

from mocapd.core._kernel import evaluate, lm_step

FloatArray = NDArray[np.float64]

#: the termination codes :func:`lm_solve` returns, in :class:`mocapd.core.lm.Termination` value names
TERMINATIONS = (
    "function_tolerance",
    "gradient_tolerance",
    "parameter_tolerance",
    "max_iterations",
    "trust_region_collapsed",
    "numerical_failure",
)
FUNCTION, GRADIENT, PARAMETER, MAX_ITERATIONS, COLLAPSED, FAILURE = range(6)
#: messages of the numerical failures, by the code in ``stats[5]``
FAILURE_MESSAGES = ("", "cost is not finite at the start", "non-finite Jacobian", "linear solve failed repeatedly")

#: the layout of ``options`` (float64): the fields of :class:`mocapd.core.lm.LMOptions` in this order
OPTION_FIELDS = (
    "max_iterations",
    "function_tolerance",
    "gradient_tolerance",
    "parameter_tolerance",
    "initial_trust_region_radius",
    "max_trust_region_radius",
    "min_trust_region_radius",
    "min_relative_decrease",
    "min_lm_diagonal",
    "max_lm_diagonal",
)


@nb.njit(cache=True, nogil=True)
def _finite(a: FloatArray) -> bool:
    for v in a.flat:  # noqa: SIM110  # a loop: numba compiles it, not all() over a generator
        if not math.isfinite(v):
            return False
    return True


@nb.njit(cache=True, nogil=True)
def _norm(a: FloatArray) -> float:
    s = 0.0
    for v in a:
        s += v * v
    return math.sqrt(s)


@nb.njit(cache=True, nogil=True)
def lm_solve(
    x0: FloatArray,
    options: FloatArray,
    parents: FloatArray,
    offsets: FloatArray,
    point_bones: FloatArray,
    point_offsets: FloatArray,
    n_kp: int,
    n_imu: int,
    K: FloatArray,
    dist: FloatArray,
    Rc: FloatArray,
    tc: FloatArray,
    uv: FloatArray,
    conf: FloatArray,
    q_meas: FloatArray,
    acc_meas: FloatArray,
    imu_mask: FloatArray,
    prev1: FloatArray,
    prev2: FloatArray,
    dt: float,
    mu: FloatArray,
    A_pp: FloatArray,
    A_pd: FloatArray,
    AtA_pp: FloatArray,
    AtA_pd: FloatArray,
    lambdas: FloatArray,
    loss_codes: FloatArray,
    loss_scales: FloatArray,
    enabled: FloatArray,
    floor_radius: float,
    floor_height: float,
    x_out: FloatArray,
    term_costs_out: FloatArray,
    stats: FloatArray,
) -> None:
    """Minimise ``½ Σ ρ`` from ``x0`` (66,): the point into ``x_out``, its per-term costs into
    ``term_costs_out``, and ``stats`` (6,) = initial cost, final cost, iterations, successful iterations,
    termination code (:data:`TERMINATIONS`), failure message code (:data:`FAILURE_MESSAGES`). On a numerical
    failure ``x_out`` is ``x0`` and both costs the initial one. The other arguments are
    :func:`mocapd.core._kernel.evaluate`'s."""
    n = x0.shape[0]
    max_iterations = int(options[0])
    ftol, gtol, ptol = options[1], options[2], options[3]
    radius, max_radius, min_radius = options[4], options[5], options[6]
    min_rel, min_diag, max_diag = options[7], options[8], options[9]
    H = np.zeros((n, n))
    g = np.zeros(n)
    H_trial = np.zeros((n, n))
    g_trial = np.zeros(n)
    tcs = np.zeros(term_costs_out.shape[0])
    x = x0.copy()
    cost = evaluate(x, True, parents, offsets, point_bones, point_offsets, n_kp, n_imu, K, dist, Rc, tc, uv, conf,
                    q_meas, acc_meas, imu_mask, prev1, prev2, dt, mu, A_pp, A_pd, AtA_pp, AtA_pd, lambdas,
                    loss_codes, loss_scales, enabled, floor_radius, floor_height, H, g, tcs)  # fmt: skip
    term_costs_out[:] = tcs
    initial = cost
    if not math.isfinite(initial):
        x_out[:] = x0
        stats[:] = (initial, initial, 0.0, 0.0, float(FAILURE), 1.0)
        return
    decrease = 2.0
    iterations = successful = 0
    reason, message = MAX_ITERATIONS, 0
    while iterations < max_iterations:
        if not (_finite(H) and _finite(g)):
            reason, message = FAILURE, 2
            break
        gmax = 0.0
        for v in g:
            gmax = max(gmax, abs(v))
        if gmax <= gtol:
            reason = GRADIENT
            break
        iterations += 1
        step, model_reduction, ok = lm_step(H, g, radius, min_diag, max_diag)
        if not (ok and _finite(step)):  # not positive definite: damp more and retry
            radius /= decrease
            decrease *= 2.0
            if radius < min_radius:
                reason, message = FAILURE, 3
                break
            continue
        if _norm(step) <= ptol * (_norm(x) + ptol):
            reason = PARAMETER
            break
        trial = x + step
        trial_cost = evaluate(trial, False, parents, offsets, point_bones, point_offsets, n_kp, n_imu, K, dist, Rc,
                              tc, uv, conf, q_meas, acc_meas, imu_mask, prev1, prev2, dt, mu, A_pp, A_pd, AtA_pp,
                              AtA_pd, lambdas, loss_codes, loss_scales, enabled, floor_radius, floor_height,
                              H_trial, g_trial, tcs)  # fmt: skip
        actual = cost - trial_cost
        rel = actual / model_reduction if model_reduction > 0 else -1.0
        # Only accepted steps move x: a rejected step changes the damping, never the point.
        if math.isfinite(trial_cost) and rel > min_rel:
            successful += 1
            x, cost = trial, trial_cost
            term_costs_out[:] = tcs
            radius = min(radius / max(1.0 / 3.0, 1.0 - (2.0 * rel - 1.0) ** 3), max_radius)
            decrease = 2.0
            if actual <= ftol * (cost + actual):
                reason = FUNCTION
                break
            cost = evaluate(x, True, parents, offsets, point_bones, point_offsets, n_kp, n_imu, K, dist, Rc, tc,
                            uv, conf, q_meas, acc_meas, imu_mask, prev1, prev2, dt, mu, A_pp, A_pd, AtA_pp, AtA_pd,
                            lambdas, loss_codes, loss_scales, enabled, floor_radius, floor_height, H, g,
                            tcs)  # fmt: skip
            term_costs_out[:] = tcs
        else:
            radius /= decrease
            decrease *= 2.0
            if radius < min_radius:
                reason = COLLAPSED
                break
    if reason == FAILURE or not _finite(x):
        x_out[:] = x0
        stats[:] = (initial, initial, float(iterations), float(successful), float(FAILURE), float(message))
        return
    x_out[:] = x
    stats[:] = (initial, cost, float(iterations), float(successful), float(reason), float(message))
