"""The generic Levenberg–Marquardt minimiser on problems whose optimum is known exactly."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from mocapd.core.lm import LMOptions, Termination, levenberg_marquardt

Arr = np.ndarray
Fn = Callable[[Arr], Arr]


def _least_squares(
    residual: Fn, jacobian: Fn
) -> tuple[Callable[[Arr], tuple[float, Arr, Arr, None]], Callable[[Arr], tuple[float, None]]]:
    def linearize(x: Arr) -> tuple[float, Arr, Arr, None]:
        f, J = residual(x), jacobian(x)
        return 0.5 * float(f @ f), J.T @ J, J.T @ f, None

    def cost(x: Arr) -> tuple[float, None]:
        f = residual(x)
        return 0.5 * float(f @ f), None

    return linearize, cost


def test_rosenbrock_reaches_the_exact_minimum() -> None:
    res = lambda x: np.array([10.0 * (x[1] - x[0] ** 2), 1.0 - x[0]])  # noqa: E731
    jac = lambda x: np.array([[-20.0 * x[0], 10.0], [-1.0, 0.0]])  # noqa: E731
    lin, cost = _least_squares(res, jac)
    r = levenberg_marquardt(np.array([-1.2, 1.0]), lin, cost, LMOptions(max_iterations=200))
    np.testing.assert_allclose(r.x, [1.0, 1.0], atol=1e-8)
    assert r.final_cost < 1e-16 < r.initial_cost
    assert r.termination in (
        Termination.GRADIENT_TOLERANCE,
        Termination.PARAMETER_TOLERANCE,
        Termination.FUNCTION_TOLERANCE,
    )


def test_linear_problem_matches_the_normal_equations() -> None:
    rng = np.random.default_rng(0)
    A = rng.normal(size=(30, 5))
    b = rng.normal(size=30)
    lin, cost = _least_squares(lambda x: A @ x - b, lambda x: A)
    r = levenberg_marquardt(np.zeros(5), lin, cost, LMOptions())
    np.testing.assert_allclose(r.x, np.linalg.lstsq(A, b, rcond=None)[0], atol=1e-7)


def test_iteration_cap_is_honoured_and_reported() -> None:
    res = lambda x: np.array([10.0 * (x[1] - x[0] ** 2), 1.0 - x[0]])  # noqa: E731
    jac = lambda x: np.array([[-20.0 * x[0], 10.0], [-1.0, 0.0]])  # noqa: E731
    lin, cost = _least_squares(res, jac)
    r = levenberg_marquardt(np.array([-1.2, 1.0]), lin, cost, LMOptions(max_iterations=6))
    assert r.iterations == 6 and r.termination is Termination.MAX_ITERATIONS
    assert r.final_cost == cost(r.x)[0] <= r.initial_cost


def test_rejected_steps_do_not_move_the_point() -> None:
    """A cost that is infinite away from the start: every step is rejected and x stays put."""

    def lin(x: Arr) -> tuple[float, Arr, Arr, None]:
        return 1.0, np.eye(2), np.array([1.0, 1.0]), None

    def cost(x: Arr) -> tuple[float, None]:
        return (1.0 if np.allclose(x, 0) else np.inf), None

    r = levenberg_marquardt(np.zeros(2), lin, cost, LMOptions(max_iterations=50))
    np.testing.assert_array_equal(r.x, [0.0, 0.0])
    assert r.successful_iterations == 0
    assert r.termination in (Termination.MAX_ITERATIONS, Termination.PARAMETER_TOLERANCE)


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_numerical_failure_returns_the_start(bad: float) -> None:
    def lin(x: Arr) -> tuple[float, Arr, Arr, None]:
        return bad, np.eye(2), np.ones(2), None

    def cost(x: Arr) -> tuple[float, None]:
        return bad, None

    r = levenberg_marquardt(np.array([3.0, 4.0]), lin, cost, LMOptions())
    assert r.termination is Termination.NUMERICAL_FAILURE
    np.testing.assert_array_equal(r.x, [3.0, 4.0])
