"""Behaviour of the Levenberg–Marquardt pose solver (seed 003 §3.2) on exact synthetic measurements."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mocapd.core.ground import GroundOptions
from mocapd.core.keypoints import COCO17
from mocapd.core.kinematics import Kinematics
from mocapd.core.loss import TrivialLoss
from mocapd.core.rotations import quat_angle, quat_from_matrix
from mocapd.core.skeleton import BONE_INDEX, BONE_NAMES
from mocapd.core.solver import LMOptions, Observations, PoseSolver, Termination, solve_many
from mocapd.core.synthetic import perturb_pose
from mocapd.core.terms import CostOptions
from mocapd.errors import InputError

from .conftest import Scene

# Joints a camera keypoint or an IMU pins down directly; Spine1/Spine2 (and the split of the bend between the
# three lower spine bones) are only fixed through the pose prior.
OBSERVED_JOINTS = sorted({BONE_INDEX[b] for _, b, _ in COCO17} | {0, 4, 5, 6})


def _joint_errors_mm(scene: Scene, theta: np.ndarray, frame: int) -> np.ndarray:
    kin = Kinematics(scene.skeleton)
    return np.asarray(
        1000.0 * np.linalg.norm(kin.forward(theta).positions - kin.forward(scene.truth[frame]).positions, axis=1)
    )


def _solver(scene: Scene, **kw: object) -> PoseSolver:
    args: dict[str, object] = {
        "cameras": scene.cameras,
        "targets": scene.targets,
        "imus": scene.imus,
        "prior": scene.prior,
    }
    args.update(kw)
    return PoseSolver(scene.skeleton, **args)  # type: ignore[arg-type]


def _with_history(solver: PoseSolver, scene: Scene, frame: int) -> PoseSolver:
    solver.push_history(scene.truth[frame - 2])
    solver.push_history(scene.truth[frame - 1])
    return solver


DATA_ONLY = CostOptions(use_prior_projection=False, use_prior_deviation=False)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_recovers_true_pose_from_ten_degrees_off(scene: Scene, seed: int) -> None:
    """8 cameras x 17 keypoints + 13 IMUs, exact data, every joint 10° off: the data terms' exact minimum.

    The prior is off so that the truth *is* the minimum (any prior biases the answer; see the next test).
    Spine1/Spine2 joints are not observed by any sensor (only how far the three lower spine bones bend in
    total is), so they are held to the mean over all joints rather than to the per-joint bound.
    """
    frame = 10 + seed
    solver = _with_history(_solver(scene, cost=DATA_ONLY, lm=LMOptions(max_iterations=50)), scene, frame)
    start = perturb_pose(scene.truth[frame], np.random.default_rng(seed), 10.0)
    assert _joint_errors_mm(scene, start, frame).mean() > 50.0
    res = solver.solve(scene.observations[frame], theta0=start)
    err = _joint_errors_mm(scene, res.theta, frame)
    assert res.summary.converged and res.summary.final_cost < 1e-12
    assert err.mean() < 1.0
    assert err[OBSERVED_JOINTS].max() < 1.0


def test_prior_bias_is_bounded(scene: Scene) -> None:
    """With the seed's default weights the PCA prior pulls exact data by a few millimetres at most."""
    for frame in (1, 10, 20, 30):
        solver = _with_history(_solver(scene), scene, frame)
        res = solver.solve(scene.observations[frame], theta0=scene.truth[frame])
        assert _joint_errors_mm(scene, res.theta, frame).mean() < 5.0


def _outlier_observations(scene: Scene, frame: int, fraction: float, seed: int) -> Observations:
    rng = np.random.default_rng(seed)
    o = scene.observations[frame]
    assert o.keypoints is not None
    uv = o.keypoints.copy()
    bad = rng.uniform(size=uv.shape[:2]) < fraction
    uv[bad] = rng.uniform([0, 0], [1920, 1080], size=(int(bad.sum()), 2))
    return replace(o, keypoints=uv)


@pytest.mark.parametrize("seed", [0, 1])
def test_cauchy_loss_rejects_gross_outliers_where_l2_does_not(scene: Scene, seed: int) -> None:
    frame = 15
    obs = _outlier_observations(scene, frame, 0.2, seed)
    start = perturb_pose(scene.truth[frame], np.random.default_rng(seed), 10.0)
    robust = _with_history(_solver(scene, lm=LMOptions(max_iterations=50)), scene, frame)
    plain = _with_history(
        _solver(scene, cost=CostOptions(loss_position=TrivialLoss()), lm=LMOptions(max_iterations=50)),
        scene,
        frame,
    )
    err_robust = _joint_errors_mm(scene, robust.solve(obs, theta0=start).theta, frame)
    err_plain = _joint_errors_mm(scene, plain.solve(obs, theta0=start).theta, frame)
    assert err_robust.mean() < 3.0
    assert err_plain.mean() > 20.0


TERMS_OFF = {
    "position": CostOptions(use_position=False),
    "orientation": CostOptions(use_orientation=False),
    "acceleration": CostOptions(use_acceleration=False),
    "prior_projection": CostOptions(use_prior_projection=False),
    "prior_deviation": CostOptions(use_prior_deviation=False),
    "floor": CostOptions(use_floor=False),
}


@pytest.mark.parametrize("term", sorted(TERMS_OFF))
def test_each_term_switched_off_still_solves(scene: Scene, term: str) -> None:
    frame = 20
    solver = _with_history(_solver(scene, cost=TERMS_OFF[term]), scene, frame)
    start = perturb_pose(scene.truth[frame], np.random.default_rng(3), 10.0)
    res = solver.solve(scene.observations[frame], theta0=start)
    assert res.summary.converged and np.all(np.isfinite(res.theta))
    assert term not in res.summary.term_costs
    assert res.summary.final_cost < res.summary.initial_cost


def _imu_only(o: Observations) -> Observations:
    return Observations(imu_orientations=o.imu_orientations, imu_accelerations=o.imu_accelerations, dt=o.dt)


def test_imu_only_leaves_global_position_unconstrained(scene: Scene) -> None:
    """Without the position term nothing locates the body: a global offset is never corrected.

    Orientation + prior only: the cost does not depend on the root translation at all, so it stays where it
    started while the body itself follows the IMUs (with the root placed by the LM alone: foot contacts off).
    With the acceleration term the translation is only double-integrated (seed 003 §3.2.3: "not sufficient to
    locate the body"), so a start offset survives too.
    """
    offset = np.array([0.5, 0.0, -0.4])
    start = scene.truth[0].copy()
    start[:3] += offset
    kin = Kinematics(scene.skeleton)
    orient_only = _solver(
        scene,
        cameras=[],
        cost=CostOptions(use_acceleration=False, use_floor=False),
        ground=GroundOptions(enabled=False),
    )
    orient_only.reset(start)
    for frame in range(1, 30):
        res = orient_only.solve(_imu_only(scene.observations[frame]))
        np.testing.assert_array_equal(res.theta[:3], start[:3])  # zero gradient in the translation
    fk_s, fk_t = kin.forward(res.theta), kin.forward(scene.truth[29])
    solved, true = fk_s.positions, fk_t.positions
    # The body follows the IMUs (up to the prior's pull at the seed's weights, a few degrees).
    bones = [m.bone_index for m in scene.imus]
    angle = np.degrees(quat_angle(quat_from_matrix(fk_s.rotations[bones]), quat_from_matrix(fk_t.rotations[bones])))
    assert angle.mean() < 5.0
    assert np.linalg.norm((solved - solved[0]) - (true - true[0]), axis=1).mean() < 0.05

    with_acc = _solver(scene, cameras=[], ground=GroundOptions(enabled=False))
    with_acc.reset(start)
    for frame in range(1, 30):
        res = with_acc.solve(_imu_only(scene.observations[frame]))
    assert np.linalg.norm((kin.forward(res.theta).positions[0] - true[0])[[0, 2]]) > 0.2

    with_cams = _solver(scene)  # the same start with the cameras: pulled back to the truth
    with_cams.reset(start)
    for frame in range(1, 30):
        res = with_cams.solve(scene.observations[frame])
    assert _joint_errors_mm(scene, res.theta, 29)[0] < 5.0


def test_cameras_alone_fix_the_pose(scene: Scene) -> None:
    frame = 25
    solver = _solver(scene, imus=())
    start = perturb_pose(scene.truth[frame], np.random.default_rng(4), 10.0)
    start[:3] += [0.3, 0.0, 0.2]
    o = scene.observations[frame]
    res = solver.solve(Observations(keypoints=o.keypoints, confidences=o.confidences, dt=o.dt), theta0=start)
    err = _joint_errors_mm(scene, res.theta, frame)
    assert err[0] < 2.0  # the root, including its global position
    assert err[OBSERVED_JOINTS].mean() < 5.0


def test_observations_require_the_frame_period() -> None:
    """Δt scales every measured acceleration in E_A; a silent 1/60 s default on 100 Hz data was a trap (issue 14).
    It has no default now, and fields are keyword-only so a positional call cannot shift into it."""
    with pytest.raises(TypeError, match="dt"):
        Observations(imu_orientations=np.array([[1.0, 0.0, 0.0, 0.0]]))  # type: ignore[call-arg]
    with pytest.raises(TypeError):
        Observations(np.zeros((0, 17, 2)), np.zeros((0, 17)), dt=0.01)  # type: ignore[call-arg]
    assert Observations(dt=0.01).dt == 0.01


def test_no_sensors_at_all_is_finite(scene: Scene) -> None:
    solver = _solver(scene, cameras=[], imus=())
    res = solver.solve(Observations(dt=1 / 60))
    assert res.summary.converged and np.all(np.isfinite(res.theta))


def test_missing_keypoints_and_imus(scene: Scene) -> None:
    frame = 12
    o = scene.observations[frame]
    assert o.keypoints is not None and o.confidences is not None
    uv = o.keypoints.copy()
    conf = o.confidences.copy()
    uv[:, ::3] = np.nan
    conf[:, ::3] = 0.0
    conf[5:] = 0.0  # three cameras see nothing
    mask = np.ones(13, dtype=bool)
    mask[[2, 5, 9]] = False
    q = np.array(o.imu_orientations)
    q[~mask] = np.nan
    obs = replace(o, keypoints=uv, confidences=conf, imu_orientations=q, imu_mask=mask)
    solver = _with_history(_solver(scene), scene, frame)
    res = solver.solve(obs, theta0=perturb_pose(scene.truth[frame], np.random.default_rng(5), 5.0))
    assert _joint_errors_mm(scene, res.theta, frame)[OBSERVED_JOINTS].mean() < 5.0


def test_warm_started_tracking_of_a_sequence(scene: Scene) -> None:
    solver = _solver(scene)
    solver.reset(scene.truth[0])
    errs = []
    for frame in range(1, len(scene.truth)):
        res = solver.solve(scene.observations[frame])
        errs.append(_joint_errors_mm(scene, res.theta, frame).mean())
        assert res.summary.iterations <= solver.lm.max_iterations
    assert max(errs) < 5.0  # the prior's bias on exact data (test_prior_bias_is_bounded)


def test_several_people_in_one_call_equal_sequential_solves(scene: Scene) -> None:
    frames = [10, 20, 30]
    people = [_with_history(_solver(scene), scene, f) for f in frames]
    alone = [_with_history(_solver(scene), scene, f) for f in frames]
    starts = [perturb_pose(scene.truth[f], np.random.default_rng(f), 8.0) for f in frames]
    for s, th in zip(people + alone, starts + starts, strict=True):
        s.reset(th)
        s.push_history(scene.truth[frames[people.index(s) if s in people else alone.index(s)] - 2])
        s.push_history(scene.truth[frames[people.index(s) if s in people else alone.index(s)] - 1])
    together = solve_many(people, [scene.observations[f] for f in frames])
    for s, f, r in zip(alone, frames, together, strict=True):
        np.testing.assert_array_equal(s.solve(scene.observations[f]).theta, r.theta)


def test_backends_take_identical_steps(scene: Scene) -> None:
    frame = 14
    start = perturb_pose(scene.truth[frame], np.random.default_rng(6), 10.0)
    a = _with_history(_solver(scene, backend="numpy"), scene, frame).solve(scene.observations[frame], start)
    b = _with_history(_solver(scene), scene, frame).solve(scene.observations[frame], start)
    assert a.summary.iterations == b.summary.iterations
    np.testing.assert_allclose(a.theta, b.theta, atol=1e-9)


@pytest.mark.parametrize("frame", [6, 14, 33])
def test_the_compiled_lm_loop_takes_the_python_loops_steps(scene: Scene, frame: int) -> None:
    """Issue 39: the LM loop compiled (it released the interpreter lock for the whole solve) is the Python loop
    step for step: the same iterations, stopping rule, point and per-term costs, on warm and cold starts."""
    for seed, degrees in ((frame, 3.0), (frame + 1, 25.0)):
        start = perturb_pose(scene.truth[frame], np.random.default_rng(seed), degrees)
        ref = _with_history(_solver(scene), scene, frame)
        ref.compiled_loop = False
        a = ref.solve(scene.observations[frame], start)
        b = _with_history(_solver(scene), scene, frame).solve(scene.observations[frame], start)
        assert (a.summary.iterations, a.summary.successful_iterations, a.summary.termination) == (
            b.summary.iterations, b.summary.successful_iterations, b.summary.termination)  # fmt: skip
        np.testing.assert_allclose(b.theta, a.theta, rtol=0.0, atol=1e-10)
        assert b.summary.final_cost == pytest.approx(a.summary.final_cost, rel=1e-12)
        assert b.summary.initial_cost == a.summary.initial_cost
        assert b.summary.term_costs == pytest.approx(a.summary.term_costs, rel=1e-12)


def test_bad_inputs_raise_clear_errors(scene: Scene) -> None:
    solver = _solver(scene)
    o = scene.observations[3]
    assert o.keypoints is not None
    with pytest.raises(InputError, match=r"keypoints must have shape \(8, 17, 2\)"):
        solver.solve(replace(o, keypoints=o.keypoints[:7]))
    bad = o.keypoints.copy()
    bad[0, 0, 0] = np.inf
    with pytest.raises(InputError, match="keypoints with confidence > 0 must be finite"):
        solver.solve(replace(o, keypoints=bad))
    with pytest.raises(InputError, match="imu_orientations must have shape"):
        solver.solve(replace(o, imu_orientations=np.zeros((12, 4))))
    with pytest.raises(InputError, match="unit quaternions"):
        solver.solve(replace(o, imu_orientations=np.zeros((13, 4))))
    with pytest.raises(InputError, match="dt"):
        solver.solve(replace(o, dt=0.0))
    with pytest.raises(InputError, match=r"θ must have shape \(66,\)"):
        solver.solve(o, theta0=np.zeros(65))
    with pytest.raises(InputError, match="backend"):
        _solver(scene, backend="gpu")


def test_numerical_failure_keeps_previous_pose(scene: Scene) -> None:
    solver = _solver(scene)
    solver.reset(scene.truth[5])
    o = scene.observations[6]
    assert o.keypoints is not None
    huge = np.full_like(o.keypoints, 1e300)  # finite inputs whose squared error overflows to inf
    res = solver.solve(replace(o, keypoints=huge))
    assert res.summary.termination is Termination.NUMERICAL_FAILURE
    assert not res.summary.converged and "previous pose" in res.summary.message
    np.testing.assert_array_equal(res.theta, scene.truth[5])
    assert np.all(np.isfinite(solver.theta))


def test_summary_reports_costs_per_term(scene: Scene) -> None:
    solver = _with_history(_solver(scene), scene, 8)
    res = solver.solve(scene.observations[8], theta0=scene.truth[8])
    assert set(res.summary.term_costs) == {
        "position",
        "orientation",
        "acceleration",
        "prior_projection",
        "prior_deviation",
        "floor",
    }
    assert res.summary.final_cost == pytest.approx(sum(res.summary.term_costs.values()))
    assert BONE_NAMES[0] == "Hips"


def test_acceleration_term_needs_an_absolute_position_reference(scene: Scene) -> None:
    """E_A is gated on views (acceleration_min_views): IMU-only it would integrate sensor noise into the body."""
    frame = 16
    imu_only = _imu_only(scene.observations[frame])
    gated = _with_history(_solver(scene, cameras=[]), scene, frame)
    assert "acceleration" not in gated.solve(imu_only, theta0=scene.truth[frame]).summary.term_costs
    always = _with_history(_solver(scene, cameras=[], cost=CostOptions(acceleration_min_views=0)), scene, frame)
    assert "acceleration" in always.solve(imu_only, theta0=scene.truth[frame]).summary.term_costs
    seen = _with_history(_solver(scene), scene, frame)
    assert "acceleration" in seen.solve(scene.observations[frame], theta0=scene.truth[frame]).summary.term_costs


def test_a_pose_solved_before_is_kept_where_the_objective_rates_it_lower(scene: Scene) -> None:
    """``resolve``'s guard (issue 41): LM ends in the minimum nearest its warm start, and a re-solve that started
    elsewhere than live can end in a worse one (Demo_MultiPerson: 16 of 1112 solves). Given the pose solved before
    for the same observations, the solve keeps it where the objective is lower there, and warm-starts the next
    frame from it; a worse alternative changes nothing."""
    frame = 20
    o = scene.observations[frame]
    obs = Observations(keypoints=o.keypoints, confidences=o.confidences, dt=o.dt)
    start = perturb_pose(scene.truth[frame], np.random.default_rng(5), 25.0)
    short = LMOptions(max_iterations=2)  # a solve stopped far from its minimum: the truth's objective is lower
    plain = _solver(scene, imus=(), lm=short).solve(obs, theta0=start)
    solver = _solver(scene, imus=(), lm=short)
    kept = solver.solve(obs, theta0=start, alternative=scene.truth[frame])
    assert kept.summary.kept_alternative and not plain.summary.kept_alternative
    np.testing.assert_allclose(kept.theta, scene.truth[frame], atol=1e-12)
    np.testing.assert_allclose(solver.theta, scene.truth[frame], atol=1e-12)  # the next warm start
    assert kept.summary.final_cost == pytest.approx(solver.cost(scene.truth[frame], obs)[0])
    assert kept.summary.final_cost < plain.summary.final_cost
    assert _joint_errors_mm(scene, plain.theta, frame).mean() > 5.0 * _joint_errors_mm(scene, kept.theta, frame).mean()
    worse = _solver(scene, imus=(), lm=short).solve(obs, theta0=start, alternative=start)
    assert not worse.summary.kept_alternative
    np.testing.assert_array_equal(worse.theta, plain.theta)
