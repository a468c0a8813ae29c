"""Every cost term's analytic Jacobian against central finite differences (float64, relative error < 1e-6)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mocapd.core.solver import TERM_NAMES, Observations, PoseSolver
from mocapd.core.synthetic import perturb_pose

from .conftest import Scene


def _noisy(scene: Scene, frame: int, rng: np.random.Generator) -> Observations:
    o = scene.observations[frame]
    assert o.keypoints is not None and o.confidences is not None and o.imu_accelerations is not None
    conf = rng.uniform(0.2, 1.0, size=o.confidences.shape) * (rng.uniform(size=o.confidences.shape) > 0.1)
    return replace(
        o,
        keypoints=o.keypoints + rng.normal(scale=25.0, size=o.keypoints.shape),
        confidences=conf,
        imu_accelerations=o.imu_accelerations + rng.normal(size=(13, 3)),
    )


def _into_floor(solver: PoseSolver, theta: np.ndarray) -> np.ndarray:
    """Lower the body so its lowest foot joint is 2 cm above the floor: the floor term is active."""
    fk = solver.kin.forward(theta)
    lowest = min(fk.positions[b, 1] for b in (15, 16, 19, 20))
    out = theta.copy()
    out[1] += 0.02 - lowest
    return out


def _numeric_jacobian(solver: PoseSolver, theta: np.ndarray, obs: Observations, name: str) -> np.ndarray:
    eps = 1e-6
    f0 = solver.term_residuals(theta, obs)[name]
    J = np.zeros((*f0.shape, theta.size))
    for k in range(theta.size):
        d = np.zeros_like(theta)
        d[k] = eps
        J[..., k] = (solver.term_residuals(theta + d, obs)[name] - solver.term_residuals(theta - d, obs)[name]) / (
            2 * eps
        )
    return J


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_every_term_jacobian_matches_finite_differences(scene: Scene, seed: int) -> None:
    rng = np.random.default_rng(seed)
    frame = 5 + seed
    solver = PoseSolver(scene.skeleton, scene.cameras, scene.targets, scene.imus, scene.prior, backend="numpy")
    solver.push_history(scene.truth[frame - 2])
    solver.push_history(scene.truth[frame - 1])
    theta = _into_floor(solver, perturb_pose(scene.truth[frame], rng, 25.0))
    obs = _noisy(scene, frame, rng)
    analytic = solver.term_jacobians(theta, obs)
    assert set(analytic) == set(TERM_NAMES)
    for name, (f, J) in analytic.items():
        assert np.any(f != 0.0), f"{name} residuals are all zero: the check would be vacuous"
        Jn = _numeric_jacobian(solver, theta, obs, name)
        err = np.max(np.abs(J - Jn)) / np.max(np.abs(Jn))
        assert err < 1e-6, f"{name}: relative Jacobian error {err:.2e}"


def test_compiled_kernel_equals_numpy_reference(scene: Scene) -> None:
    """Cost, per-term costs, gradient and JᵀJ of the compiled backend equal the tested numpy reference."""
    from mocapd.core.observations import ValidatedObservations

    rng = np.random.default_rng(7)
    frame = 9
    ref = PoseSolver(scene.skeleton, scene.cameras, scene.targets, scene.imus, scene.prior, backend="numpy")
    fast = PoseSolver(scene.skeleton, scene.cameras, scene.targets, scene.imus, scene.prior)
    for s in (ref, fast):
        s.push_history(scene.truth[frame - 2])
        s.push_history(scene.truth[frame - 1])
    obs = _noisy(scene, frame, rng)
    for _ in range(3):
        theta = _into_floor(fast, perturb_pose(scene.truth[frame], rng, 20.0))
        v = ValidatedObservations(obs, fast.n_cams, fast.n_kp, fast.n_imu)
        on = fast._enabled(v)
        c1, t1, H1, g1 = ref._linearize(theta, v, on)
        c2, t2, H2, g2 = fast._linearize(theta, v, on)
        assert c2 == pytest.approx(c1, rel=1e-12)
        assert t2.keys() == t1.keys()
        for k in t1:
            assert t2[k] == pytest.approx(t1[k], rel=1e-10, abs=1e-14)
        np.testing.assert_allclose(H2, H1, rtol=1e-10, atol=1e-12 * np.abs(H1).max())
        np.testing.assert_allclose(g2, g1, rtol=1e-10, atol=1e-12 * np.abs(g1).max())
