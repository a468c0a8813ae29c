"""E_J, the learned 3D joint observations in the LM solve (issue 30): analytic Jacobian against finite
differences, compiled backend against the numpy reference, and what the term does to a solve."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mocapd.core.kinematics import Kinematics
from mocapd.core.loss import CauchyLoss
from mocapd.core.observations import ValidatedObservations
from mocapd.core.solver import LEARNED_TERM, TERM_NAMES, Observations, PoseSolver
from mocapd.core.synthetic import perturb_pose
from mocapd.core.terms import CostOptions
from mocapd.errors import InputError

from .conftest import Scene
from .test_terms import _noisy, _numeric_jacobian


def _joints(scene: Scene, frame: int, rng: np.random.Generator, noise: float = 0.03) -> tuple[np.ndarray, np.ndarray]:
    """Noisy learned joints of the true pose (one of them a 0.5 m outlier, two unweighted) and their weights."""
    j = Kinematics(scene.skeleton).forward(scene.truth[frame]).positions + rng.normal(scale=noise, size=(21, 3))
    j[7] += 0.5
    w = rng.uniform(0.5, 1.5, size=21)
    w[[3, 12]] = 0.0
    j[3] = np.nan  # unweighted rows may hold NaN
    return j, w


@pytest.mark.parametrize("seed", [0, 1])
def test_learned_term_jacobian_matches_finite_differences(scene: Scene, seed: int) -> None:
    rng = np.random.default_rng(seed)
    frame = 6 + seed
    solver = PoseSolver(scene.skeleton, scene.cameras, scene.targets, scene.imus, scene.prior, backend="numpy")
    solver.push_history(scene.truth[frame - 2])
    solver.push_history(scene.truth[frame - 1])
    theta = perturb_pose(scene.truth[frame], rng, 25.0)
    j, w = _joints(scene, frame, rng)
    obs = replace(_noisy(scene, frame, rng), joint_positions=j, joint_weights=w)
    analytic = solver.term_jacobians(theta, obs)
    assert set(analytic) == {*TERM_NAMES, LEARNED_TERM}
    f, J = analytic[LEARNED_TERM]
    assert f.shape == (21, 3) and np.all(f[[3, 12]] == 0.0) and np.all(np.abs(f[7]) > 0)
    Jn = _numeric_jacobian(solver, theta, obs, LEARNED_TERM)
    err = np.max(np.abs(J - Jn)) / np.max(np.abs(Jn))
    assert err < 1e-6, f"relative Jacobian error {err:.2e}"


def test_compiled_kernel_plus_learned_term_equals_numpy_reference(scene: Scene) -> None:
    rng = np.random.default_rng(3)
    frame = 9
    cost = CostOptions(lambda_learned=400.0, loss_learned=CauchyLoss(0.5))
    ref = PoseSolver(scene.skeleton, scene.cameras, scene.targets, scene.imus, scene.prior, cost, backend="numpy")
    fast = PoseSolver(scene.skeleton, scene.cameras, scene.targets, scene.imus, scene.prior, cost)
    for s in (ref, fast):
        s.push_history(scene.truth[frame - 2])
        s.push_history(scene.truth[frame - 1])
    j, w = _joints(scene, frame, rng)
    obs = replace(_noisy(scene, frame, rng), joint_positions=j, joint_weights=w)
    theta = perturb_pose(scene.truth[frame], rng, 20.0)
    v = ValidatedObservations(obs, fast.n_cams, fast.n_kp, fast.n_imu)
    on = fast._enabled(v)
    assert on[LEARNED_TERM]
    c1, t1, H1, g1 = ref._linearize(theta, v, on)
    c2, t2, H2, g2 = fast._linearize(theta, v, on)
    assert t2.keys() == t1.keys() and LEARNED_TERM in t1 and t1[LEARNED_TERM] > 0
    assert c2 == pytest.approx(c1, rel=1e-12)
    np.testing.assert_allclose(H2, H1, rtol=1e-10, atol=1e-12 * np.abs(H1).max())
    np.testing.assert_allclose(g2, g1, rtol=1e-10, atol=1e-12 * np.abs(g1).max())
    assert fast._cost_only(theta, v, on)[0] == pytest.approx(c1, rel=1e-12)


def test_without_joint_observations_the_solve_is_unchanged(scene: Scene) -> None:
    """No joint estimates, or all of weight zero: exactly the seed-003 solve, for any λ_J."""
    frame = 12
    start = perturb_pose(scene.truth[frame], np.random.default_rng(4), 10.0)
    obs = scene.observations[frame]
    base = PoseSolver(scene.skeleton, scene.cameras, scene.targets, scene.imus, scene.prior)
    heavy = PoseSolver(
        scene.skeleton, scene.cameras, scene.targets, scene.imus, scene.prior, CostOptions(lambda_learned=1e4)
    )
    a = base.solve(obs, start, update_state=False)
    b = heavy.solve(obs, start, update_state=False)
    zero = replace(obs, joint_positions=np.zeros((21, 3)), joint_weights=np.zeros(21))
    c = heavy.solve(zero, start, update_state=False)
    np.testing.assert_array_equal(a.theta, b.theta)
    np.testing.assert_array_equal(a.theta, c.theta)
    assert LEARNED_TERM not in a.summary.term_costs and LEARNED_TERM not in c.summary.term_costs


def test_learned_joints_alone_place_the_skeleton(scene: Scene) -> None:
    """No camera, no IMU: the skeleton fitted to learned joints (the daemon's mode "learned") finds the pose,
    global position included, and the Cauchy loss keeps a 0.5 m outlier joint from pulling it away."""
    rng = np.random.default_rng(5)
    frame = 15
    solver = PoseSolver(scene.skeleton, [], scene.targets, (), scene.prior)
    j, w = _joints(scene, frame, rng, noise=0.01)
    solver.reset(perturb_pose(scene.truth[frame], rng, 15.0))
    for _ in range(3):
        r = solver.solve(Observations(joint_positions=j, joint_weights=w, dt=1 / 60))
    kin = Kinematics(scene.skeleton)
    err = np.linalg.norm(kin.forward(r.theta).positions - kin.forward(scene.truth[frame]).positions, axis=1)
    assert r.summary.converged and LEARNED_TERM in r.summary.term_costs
    assert np.median(err) < 0.02, err
    assert err[7] < 0.1, f"the 0.5 m outlier pulled its joint {err[7]:.3f} m away"


def test_bad_joint_observations_are_refused(scene: Scene) -> None:
    solver = PoseSolver(scene.skeleton, [], scene.targets, (), scene.prior)
    good = np.zeros((21, 3))
    for kw, msg in (
        ({"joint_positions": np.zeros((20, 3))}, "joint_positions must have shape"),
        ({"joint_positions": np.full((21, 3), np.nan)}, "must be finite where joint_weights > 0"),
        ({"joint_positions": good, "joint_weights": -np.ones(21)}, "joint_weights must be finite and >= 0"),
        ({"joint_weights": np.ones(21)}, "joint_weights without joint_positions"),
    ):
        with pytest.raises(InputError, match=msg):
            solver.solve(Observations(dt=1 / 60, **kw))
