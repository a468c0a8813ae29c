"""Levenberg–Marquardt after Ceres's trust-region minimiser, over callables (problem-agnostic).

Follows ``trust_region_minimizer.cc`` and ``levenberg_marquardt_strategy.cc``: the step solves
``(H + diag(clip(diag H))/radius) δ = -g`` (H = JᵀJ, g = Jᵀf, both already robust-corrected by the caller); a
step is accepted when its actual/predicted cost reduction ratio ρ exceeds ``min_relative_decrease``, after which
``radius /= max(1/3, 1 - (2ρ - 1)³)``; a rejected step divides the radius by a factor that doubles with each
consecutive rejection. Termination: function, gradient or parameter tolerance, the iteration cap (accepted and
rejected steps, which bounds a real-time frame), a collapsed trust region, or a numerical failure.
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from dataclasses import dataclass
from typing import Generic, TypeVar

import numpy as np
from numpy.typing import NDArray

from mocapd.core import _kernel

FloatArray = NDArray[np.float64]
Info = TypeVar("Info")


@dataclass(frozen=True)
class LMOptions:
    """Levenberg–Marquardt settings (names and defaults after Ceres, with a real-time iteration cap)."""

    max_iterations: int = 20
    """Cap on iterations (accepted and rejected steps), which bounds the per-frame cost."""
    function_tolerance: float = 1e-6
    """Stop when an accepted step reduces the cost by less than this fraction of it."""
    gradient_tolerance: float = 1e-10
    """Stop when the largest gradient component is below this."""
    parameter_tolerance: float = 1e-8
    """Stop when ``||δ|| <= tol (||x|| + tol)``."""
    initial_trust_region_radius: float = 1e4
    """1/μ of the first step: large, i.e. nearly Gauss–Newton from a warm start."""
    max_trust_region_radius: float = 1e16
    min_trust_region_radius: float = 1e-32
    min_relative_decrease: float = 1e-3
    """Accept a step when actual/predicted cost reduction exceeds this."""
    min_lm_diagonal: float = 1e-6
    max_lm_diagonal: float = 1e32


class Termination(enum.Enum):
    """Why a minimisation stopped."""

    FUNCTION_TOLERANCE = "function_tolerance"
    GRADIENT_TOLERANCE = "gradient_tolerance"
    PARAMETER_TOLERANCE = "parameter_tolerance"
    MAX_ITERATIONS = "max_iterations"
    TRUST_REGION_COLLAPSED = "trust_region_collapsed"
    NUMERICAL_FAILURE = "numerical_failure"


@dataclass(frozen=True)
class LMResult(Generic[Info]):
    """Outcome: the best point found and how the run went. ``info`` is the callables' payload at ``x``."""

    x: FloatArray
    initial_cost: float
    final_cost: float
    iterations: int
    successful_iterations: int
    termination: Termination
    message: str
    info: Info


Linearize = Callable[[FloatArray], tuple[float, FloatArray, FloatArray, Info]]
"""x -> (cost, H (n, n), g (n,), info)."""
CostOnly = Callable[[FloatArray], tuple[float, Info]]
"""x -> (cost, info)."""


def levenberg_marquardt(
    x0: FloatArray, linearize: Linearize[Info], cost_only: CostOnly[Info], options: LMOptions
) -> LMResult[Info]:
    """Minimise ``½ Σ ρ`` from ``x0``.

    On a numerical failure (non-finite cost or Jacobian, a Cholesky that keeps failing) the result's
    ``termination`` says so and ``x`` is ``x0``: callers keep their previous state rather than use NaN.
    """
    x = np.array(x0, dtype=np.float64)
    cost, H, g, info = linearize(x)
    initial = cost
    if not np.isfinite(initial):
        return LMResult(x, initial, initial, 0, 0, Termination.NUMERICAL_FAILURE, "cost is not finite at the start",
                        info)  # fmt: skip
    radius = options.initial_trust_region_radius
    decrease = 2.0
    iterations = successful = 0
    reason, message = Termination.MAX_ITERATIONS, ""
    while iterations < options.max_iterations:
        if not (np.all(np.isfinite(H)) and np.all(np.isfinite(g))):
            reason, message = Termination.NUMERICAL_FAILURE, "non-finite Jacobian"
            break
        if float(np.max(np.abs(g))) <= options.gradient_tolerance:
            reason = Termination.GRADIENT_TOLERANCE
            break
        iterations += 1
        step, model_reduction, ok = _kernel.lm_step(H, g, radius, options.min_lm_diagonal, options.max_lm_diagonal)
        if not (ok and np.all(np.isfinite(step))):  # not positive definite: damp more and retry
            radius /= decrease
            decrease *= 2.0
            if radius < options.min_trust_region_radius:
                reason, message = Termination.NUMERICAL_FAILURE, "linear solve failed repeatedly"
                break
            continue
        tol = options.parameter_tolerance
        if float(np.linalg.norm(step)) <= tol * (float(np.linalg.norm(x)) + tol):
            reason = Termination.PARAMETER_TOLERANCE
            break
        trial = x + step
        trial_cost, trial_info = cost_only(trial)
        actual = cost - trial_cost
        rel = actual / model_reduction if model_reduction > 0 else -1.0
        # Only accepted steps move x: a rejected step changes the damping, never the point.
        if np.isfinite(trial_cost) and rel > options.min_relative_decrease:
            successful += 1
            x, cost, info = trial, trial_cost, trial_info
            radius = min(radius / max(1.0 / 3.0, 1.0 - (2.0 * rel - 1.0) ** 3), options.max_trust_region_radius)
            decrease = 2.0
            if actual <= options.function_tolerance * (cost + actual):
                reason = Termination.FUNCTION_TOLERANCE
                break
            cost, H, g, info = linearize(x)
        else:
            radius /= decrease
            decrease *= 2.0
            if radius < options.min_trust_region_radius:
                reason = Termination.TRUST_REGION_COLLAPSED
                break
    if reason is Termination.NUMERICAL_FAILURE or not np.all(np.isfinite(x)):
        return LMResult(np.array(x0, dtype=np.float64), initial, initial, iterations, successful,
                        Termination.NUMERICAL_FAILURE, message or "non-finite point", info)  # fmt: skip
    return LMResult(x, initial, cost, iterations, successful, reason, message, info)
