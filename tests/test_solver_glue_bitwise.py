"""The person solve's Python glue cut (issue 39: a camera-only person's IMU sites, the compiled loop's options and
termination looked up once, the views counted without ``np.any``'s wrapper, the pose wound back only where a joint
is wound, the observations' finite check on the array kept) gives what the old code gave (kept here verbatim as the
oracle): the same poses, summaries, warm starts and acceleration histories after every solve, bit for bit, and the
same observations refused with the same messages."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray

from mocapd.core import _lm_kernel
from mocapd.core.lm import LMOptions, Termination
from mocapd.core.observations import N_JOINTS, Observations, ValidatedObservations, _array, _bool_array
from mocapd.core.rotations import rotvec_principal
from mocapd.core.skeleton import POSE_DIM
from mocapd.core.solver import (
    TERM_NAMES,
    PoseSolver,
    SolveResult,
    SolveSummary,
    _check_theta,
    principal_pose,
)
from mocapd.errors import InputError

from .conftest import Scene

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


def old_rotvec_principal(r: FloatArray) -> FloatArray:
    """The same rotations as rotation vectors of angle at most π: (..., 3) -> (..., 3).

    ``r`` and ``r - 2πk · r/|r|`` are one rotation; this takes the ``k`` that brings the angle into [0, π] (at
    exactly π either sign is the rotation). Unlike :func:`rotvec_from_quat` ∘ :func:`quat_from_rotvec` it leaves a
    vector already in range bit for bit unchanged.
    """
    r = np.asarray(r, dtype=np.float64)
    angle = np.linalg.norm(r, axis=-1, keepdims=True)
    turns = np.floor((angle - np.pi) / (2.0 * np.pi)) + 1.0  # 0 while angle < π
    wound = turns > 0.0
    scale = np.where(wound, 1.0 - 2.0 * np.pi * turns / np.where(wound, angle, 1.0), 1.0)
    return np.asarray(r * scale)


def old_principal_pose(theta: FloatArray) -> FloatArray:
    """``theta`` (66,) with every bone's rotation vector wound back to an angle of at most π (the same pose).

    The minimiser steps in rotation-vector space, where a joint can wind past π and on by whole turns: the IMU and
    keypoint terms see the same rotation, but the pose prior (a Gaussian over θ) sees a vector far from every pose
    it knows, where its Cauchy loss is flat. A solve started far from the body (the rest pose while a suit's first
    sensors stream, or samples of different instants) wound joints that no sensor fixes — spine, neck, hands, toes
    — by up to tens of turns, and with the prior no longer pulling, the warm start kept that pose for good
    (the IMU-only demo at 110-190 mm joint error instead of 50 mm). Winding back after every solve keeps the prior
    meaningful; the pose itself does not change.
    """
    out = theta.copy()
    out[3:] = old_rotvec_principal(theta[3:].reshape(-1, 3)).reshape(-1)
    return out


class OldValidatedObservations(ValidatedObservations):
    """``observations.ValidatedObservations`` before this change, verbatim (a subclass only for the types)."""

    """Observations checked and converted to dense arrays for a given problem size."""

    def __init__(self, obs: Observations, n_cams: int, n_kp: int, n_imu: int) -> None:
        if not (np.isfinite(obs.dt) and obs.dt > 0):
            raise InputError(f"observations: dt must be a positive finite period in seconds, got {obs.dt!r}")
        self.dt = float(obs.dt)
        if obs.keypoints is None and obs.confidences is None:
            self.uv = np.zeros((n_cams, n_kp, 2))
            self.conf = np.zeros((n_cams, n_kp))
        else:
            uv = _array("keypoints", obs.keypoints, (n_cams, n_kp, 2))
            conf = _array("confidences", obs.confidences, (n_cams, n_kp))
            if not ((conf >= 0.0) & (conf <= 1.0)).all():  # NaN fails both: one pass for finite and in range
                raise InputError("observations: confidences must be finite and within [0, 1]")
            used = conf > 0
            if not np.all(np.isfinite(uv[used])):
                raise InputError(
                    "observations: keypoints with confidence > 0 must be finite (use confidence 0 "
                    "for missing keypoints)"
                )
            self.uv = np.where(used[..., None], uv, 0.0)
            self.conf = conf
        mask = np.ones(n_imu, dtype=bool) if obs.imu_mask is None else _bool_array("imu_mask", obs.imu_mask, (n_imu,))
        self.has_orientation = obs.imu_orientations is not None and n_imu > 0
        self.has_acceleration = obs.imu_accelerations is not None and n_imu > 0
        self.q = np.zeros((n_imu, 4))  # identity rotations (w = 1), a tenth of np.tile's call
        self.q[:, 0] = 1.0
        self.acc = np.zeros((n_imu, 3))
        self.mask = mask
        if obs.imu_orientations is not None:
            q = _array("imu_orientations", obs.imu_orientations, (n_imu, 4))
            if not np.all(np.isfinite(q[mask])):
                raise InputError("observations: imu_orientations must be finite where imu_mask is set")
            norms = np.linalg.norm(q[mask], axis=-1)
            if np.any(np.abs(norms - 1.0) > 1e-3):
                raise InputError("observations: imu_orientations must be unit quaternions (w, x, y, z)")
            self.q[mask] = q[mask] / norms[:, None]
        if obs.imu_accelerations is not None:
            a = _array("imu_accelerations", obs.imu_accelerations, (n_imu, 3))
            if not np.all(np.isfinite(a[mask])):
                raise InputError("observations: imu_accelerations must be finite where imu_mask is set")
            self.acc[mask] = a[mask]
        self.has_joints = obs.joint_positions is not None
        self.joints = np.zeros((N_JOINTS, 3))
        self.joint_weights = np.zeros(N_JOINTS)
        if obs.joint_positions is not None:
            j = _array("joint_positions", obs.joint_positions, (N_JOINTS, 3))
            w = (
                np.ones(N_JOINTS)
                if obs.joint_weights is None
                else _array("joint_weights", obs.joint_weights, (N_JOINTS,))
            )
            if not np.all(np.isfinite(w)) or np.any(w < 0):
                raise InputError("observations: joint_weights must be finite and >= 0")
            used = w > 0
            if not np.all(np.isfinite(j[used])):
                raise InputError("observations: joint_positions must be finite where joint_weights > 0")
            self.joints[used] = j[used]
            self.joint_weights = w
        elif obs.joint_weights is not None:
            raise InputError("observations: joint_weights without joint_positions")


class OldPoseSolver(PoseSolver):
    """The solver with its solve and glue before this change, verbatim (the compiled loop and the rest are the same)."""

    def solve(
        self,
        obs: Observations,
        theta0: FloatArray | None = None,
        update_state: bool = True,
        alternative: FloatArray | None = None,
    ) -> SolveResult:
        """Solve one frame.

        Parameters
        ----------
        obs : Observations
        theta0 : array, shape (66,), optional
            Start pose; default the previous solution (warm start).
        update_state : bool
            Keep the result as the next warm start and push it into the acceleration history.
        alternative : array, shape (66,), optional
            A pose solved for this frame before (``resolve``: the live solve of the same observations). Where the
            objective rates it lower than the pose LM converged to from ``theta0``, it is the result (and the next
            warm start): LM descends to the nearest minimum of its start, so a longer solve that started elsewhere
            can end in a worse one. :attr:`SolveSummary.final_cost` is then the alternative's.
        """
        v = OldValidatedObservations(obs, self.n_cams, self.n_kp, self.n_imu)
        start = self._prediction() if theta0 is None else _check_theta(theta0)
        if self._has_solved and not self._had_reference and self._views(v) >= self.ground_options.reference_views:
            # Cameras see the person again: the acceleration history holds the sites of solves without a position
            # reference (drifted); E_A would pull the root along that path. It restarts from this solve.
            self._history.clear()
            if theta0 is None:
                start = self._recentre(start, v)
        result = self._minimize(start.copy(), v)
        if alternative is not None and result.summary.converged:
            result = self._better_of(result, _check_theta(alternative), v)
        theta = old_principal_pose(result.theta)
        published = theta
        if self.ground is not None and result.summary.converged:
            tracker = self.ground if update_state else self.ground.copy()
            theta = theta.copy()
            published = self._place_root(tracker, theta, v)
        elif (
            self.ground_options.enabled
            and self.n_imu > 0
            and self._has_solved
            and result.summary.converged
            and self._views(v) == 0
        ):
            # A suit with legs without sensors and no camera: nothing measures where the feet are, so nothing may
            # move the root (the floor term would push it up whenever the prior folds the legs under the floor).
            theta = theta.copy()
            theta[:3] = self.theta[:3]
            published = theta
        if update_state:
            reference = self._views(v) >= self.ground_options.reference_views
            self._prev_root = self.theta[:3].copy() if self._has_solved and reference and self._had_reference else None
            self._has_solved = True
            self._had_reference = reference
            self.theta = theta
            self.push_history(theta)
        return SolveResult(published, result.summary)

    def _minimize_compiled(self, x: FloatArray, v: ValidatedObservations, on: dict[str, bool]) -> SolveResult:
        """The whole LM solve in one compiled call that releases the interpreter lock
        (:mod:`mocapd.core._lm_kernel`; the learned term's solves keep the Python loop)."""
        kp = self._kernel_static
        assert kp is not None
        zeros = np.zeros((self.n_imu, 3))
        prev1 = self._history[0] if len(self._history) == 2 else zeros
        prev2 = self._history[1] if len(self._history) == 2 else zeros
        enabled = np.array([on[n] for n in TERM_NAMES], dtype=np.float64)
        options = np.array([getattr(self.lm, f) for f in _lm_kernel.OPTION_FIELDS], dtype=np.float64)
        out = np.empty(POSE_DIM)
        stats = np.empty(6)
        _lm_kernel.lm_solve(
            np.ascontiguousarray(x, dtype=np.float64), options, kp.parents, kp.offsets, kp.point_bones,
            kp.point_offsets, kp.n_kp, kp.n_imu, kp.K, kp.dist, kp.R, kp.t, v.uv, v.conf, v.q, v.acc,
            v.mask.astype(np.float64), prev1, prev2, v.dt, kp.mu, kp.A_pp, kp.A_pd, kp.AtA_pp, kp.AtA_pd,
            kp.lambdas, kp.loss_codes, kp.loss_scales, enabled, kp.floor_radius, kp.floor_height, out, self._tc, stats,
        )  # fmt: skip
        termination = Termination(_lm_kernel.TERMINATIONS[int(stats[4])])
        failed = termination is Termination.NUMERICAL_FAILURE
        message = _lm_kernel.FAILURE_MESSAGES[int(stats[5])] or ("non-finite point" if failed else "")
        summary = SolveSummary(
            initial_cost=float(stats[0]),
            final_cost=float(stats[1]),
            iterations=int(stats[2]),
            successful_iterations=int(stats[3]),
            termination=termination,
            message=f"{message}; previous pose kept" if failed else message,
            term_costs={} if failed else self._term_dict(on),
        )
        return SolveResult(self.theta.copy() if failed else out, summary)

    def imu_sites(self, theta: FloatArray) -> FloatArray:
        """World positions of the IMU sites for θ, shape (n_imu, 3)."""
        return self.points(theta, self._imu_bones, self._point_offsets[self._sl_imu])

    def _views(self, v: ValidatedObservations) -> int:
        """Cameras that see the person (at least one keypoint with confidence > 0) this frame."""
        return (
            int(np.count_nonzero(np.any(v.conf > 0, axis=1))) if self.n_cams and self.cost_options.use_position else 0
        )


def _bits(a: Any) -> bytes:
    return np.ascontiguousarray(a).tobytes()


def test_rotvec_principal_is_the_old_one_to_the_bit() -> None:
    rng = np.random.default_rng(3)
    r = rng.normal(0.0, 1.0, (2000, 3))
    r *= rng.choice([0.1, 1.0, 3.0, 40.0], size=(2000, 1))  # angles from small to many turns
    unit = r[:50] / np.linalg.norm(r[:50], axis=1, keepdims=True)
    cases = [r, r[:1] * 0.0, -0.0 * r[:2], np.pi * unit, np.nextafter(np.pi, 0.0) * unit, 3 * np.pi * unit]
    nan = r[:30].copy()
    nan[::3, 1] = np.nan
    nan[1::3, 0] = np.inf
    cases += [nan, r[:21] * 0.9, (r[:21] * 0.01).reshape(7, 3, 3), r[:0]]
    for rows in cases:
        with np.errstate(invalid="ignore"):
            assert _bits(rotvec_principal(rows)) == _bits(old_rotvec_principal(rows))
    theta = np.concatenate(([0.1, 0.9, -0.2], r[:63].ravel() * 0.2))
    assert _bits(principal_pose(theta)) == _bits(old_principal_pose(theta))


def _same_validated(a: ValidatedObservations, b: ValidatedObservations) -> None:
    for name in ("uv", "conf", "q", "acc", "mask", "joints", "joint_weights"):
        assert _bits(getattr(a, name)) == _bits(getattr(b, name)), name
    for name in ("dt", "has_orientation", "has_acceleration", "has_joints"):
        assert getattr(a, name) == getattr(b, name), name


def test_the_observations_are_validated_as_before() -> None:
    rng = np.random.default_rng(4)
    kp = rng.uniform(0.0, 1000.0, (4, 17, 2))
    conf = rng.uniform(0.0, 1.0, (4, 17))
    conf[1, 3:7] = 0.0
    kp[1, 3] = np.nan  # unseen: allowed
    kp[1, 4, 0] = np.inf
    q = rng.normal(size=(13, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    good = [
        Observations(keypoints=kp, confidences=conf, dt=1 / 30),
        Observations(dt=0.02),
        Observations(keypoints=kp, confidences=conf, imu_orientations=q, imu_accelerations=rng.normal(size=(13, 3)),
                     imu_mask=np.arange(13) % 4 != 0, dt=0.01),
        Observations(keypoints=kp.astype(np.float32), confidences=conf, dt=1 / 60),
    ]  # fmt: skip
    for obs in good:
        n_imu = 0 if obs.imu_orientations is None else 13
        _same_validated(ValidatedObservations(obs, 4, 17, n_imu), OldValidatedObservations(obs, 4, 17, n_imu))
    seen_nan = kp.copy()
    seen_nan[2, 5, 1] = np.nan
    seen_inf = kp.copy()
    seen_inf[0, 0, 0] = -np.inf
    bad_conf = conf.copy()
    bad_conf[0, 0] = np.nan
    bad = [
        Observations(keypoints=seen_nan, confidences=conf, dt=1 / 30),
        Observations(keypoints=seen_inf, confidences=conf, dt=1 / 30),
        Observations(keypoints=seen_nan, confidences=bad_conf, dt=1 / 30),
        Observations(keypoints=kp, confidences=conf * 1.5, dt=1 / 30),
        Observations(keypoints=kp[:3], confidences=conf, dt=1 / 30),
        Observations(keypoints=kp, confidences=conf, dt=0.0),
    ]
    for obs in bad:
        with pytest.raises(InputError) as new:
            ValidatedObservations(obs, 4, 17, 0)
        with pytest.raises(InputError) as old:
            OldValidatedObservations(obs, 4, 17, 0)
        assert str(new.value) == str(old.value)


def _observations(scene: Scene, rng: np.random.Generator, imus: bool) -> list[Observations]:
    """The scene's frames with detector-like noise, views and keypoints missing (NaN where unseen), and (with
    IMUs) some sensors masked; a frame now and then with no camera at all."""
    out = []
    for k, obs in enumerate(scene.observations):
        assert obs.keypoints is not None and obs.confidences is not None
        kp = obs.keypoints + rng.normal(0.0, 2.0, obs.keypoints.shape)
        conf = np.clip(obs.confidences * rng.uniform(0.5, 1.0, obs.confidences.shape), 0.0, 1.0)
        conf[rng.uniform(size=conf.shape) < 0.1] = 0.0
        conf[rng.integers(0, len(conf))] = 0.0
        kp[conf == 0] = np.nan
        if k % 13 == 7:
            conf[:] = 0.0
        if not imus:
            out.append(Observations(keypoints=kp, confidences=conf, dt=1 / 30))
            continue
        mask = rng.uniform(size=len(scene.imus)) > 0.1
        out.append(replace(obs, keypoints=kp, confidences=conf, imu_mask=mask, dt=1 / 30))
    return out


@pytest.mark.parametrize("imus", [False, True])
def test_the_solver_solves_as_before_to_the_bit(scene: Scene, imus: bool) -> None:
    rng = np.random.default_rng(5 + imus)
    frames = _observations(scene, rng, imus)
    mounts = scene.imus if imus else ()
    solvers = [
        cls(scene.skeleton, scene.cameras, scene.targets, mounts, scene.prior) for cls in (PoseSolver, OldPoseSolver)
    ]
    wound = scene.truth[0].copy()
    wound[9:12] *= 1.0 + 4.0 * np.pi / max(float(np.linalg.norm(wound[9:12])), 1e-3)  # a joint two turns on
    for s in solvers:
        s.reset(wound)
    for k, obs in enumerate(frames):
        if k == 20:
            for s in solvers:
                s.lm = LMOptions(max_iterations=2)  # a new options object: the cached copy must follow
        alternative = scene.truth[k] if k % 5 == 3 else None
        theta0 = wound if k % 11 == 10 else None
        results = [s.solve(obs, theta0=theta0, alternative=alternative, update_state=k % 9 != 8) for s in solvers]
        new, old = results
        assert _bits(new.theta) == _bits(old.theta), k
        assert new.summary == old.summary, k
        a, b = solvers
        assert _bits(a.theta) == _bits(b.theta) and len(a._history) == len(b._history), k
        assert all(_bits(x) == _bits(y) and x.shape == y.shape for x, y in zip(a._history, b._history, strict=True))
        assert (a._prev_root is None) == (b._prev_root is None)
        if a._prev_root is not None and b._prev_root is not None:
            assert _bits(a._prev_root) == _bits(b._prev_root)
