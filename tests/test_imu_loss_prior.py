"""IMU measurement model (seed 003 Eq. 8, 12), robust losses with Ceres's corrector, and the PCA prior."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mocapd.core.imu import (
    IMU_SET_6,
    IMU_SET_13,
    ImuMount,
    measured_bone_orientation,
    measured_global_acceleration,
    sensor_orientation_from_bone,
    specific_force_from_acceleration,
)
from mocapd.core.loss import CauchyLoss, HuberLoss, TrivialLoss, corrector_weights
from mocapd.core.prior import PcaPrior
from mocapd.core.rotations import matrix_from_quat, quat_angle, random_quat
from mocapd.errors import InputError, ModelError


def test_imu_sets() -> None:
    assert len(IMU_SET_13) == 13 and len(IMU_SET_6) == 6 and set(IMU_SET_6) <= set(IMU_SET_13)


def test_eq8_and_its_inverse() -> None:
    rng = np.random.default_rng(0)
    q_ig, q_gb, q_ib = random_quat(rng, (50,)), random_quat(rng, (50,)), random_quat(rng, (50,))
    q_i = sensor_orientation_from_bone(q_ig, q_gb, q_ib)
    assert np.max(quat_angle(measured_bone_orientation(q_ig, q_i, q_ib), q_gb)) < 1e-7
    # Matrix form of Eq. 8: R_gb = R_ig R_i R_ib^-1
    R = matrix_from_quat(q_ig) @ matrix_from_quat(q_i) @ np.swapaxes(matrix_from_quat(q_ib), -1, -2)
    np.testing.assert_allclose(R, matrix_from_quat(q_gb), atol=1e-12)


def test_eq12_gravity_and_inverse() -> None:
    rng = np.random.default_rng(1)
    q_ig, q_i = random_quat(rng, (20,)), random_quat(rng, (20,))
    # A sensor at rest reads +g up in the world: its global acceleration is zero.
    f_rest = specific_force_from_acceleration(q_ig, q_i, np.zeros((20, 3)))
    np.testing.assert_allclose(np.linalg.norm(f_rest, axis=1), 9.80665)
    np.testing.assert_allclose(measured_global_acceleration(q_ig, q_i, f_rest), 0.0, atol=1e-12)
    a = rng.normal(size=(20, 3))
    f = specific_force_from_acceleration(q_ig, q_i, a, gravity=9.8707)
    np.testing.assert_allclose(measured_global_acceleration(q_ig, q_i, f, gravity=9.8707), a, atol=1e-12)


def test_imu_mount_validation() -> None:
    with pytest.raises(InputError, match="not one of"):
        ImuMount("Tail")
    with pytest.raises(InputError, match="finite"):
        ImuMount("Head", t_ib=np.array([0.0, np.nan, 0.0]))


def test_imu_mount_takes_no_mounting_rotation() -> None:
    """The solver works on bone orientations: a mounting rotation given to it was silently ignored (issue 14).
    It is no longer accepted at all; the calibration applies R_ib (Eq. 8) where sensor readings become bone
    orientations."""
    with pytest.raises(TypeError, match="q_ib"):
        ImuMount("Head", q_ib=np.array([0.0, 1.0, 0.0, 0.0]))  # type: ignore[call-arg]
    assert not hasattr(ImuMount("Head"), "q_ib")


@pytest.mark.parametrize("loss", [TrivialLoss(), CauchyLoss(), CauchyLoss(3.0), HuberLoss(2.0)])
def test_loss_derivatives(loss: TrivialLoss | CauchyLoss | HuberLoss) -> None:
    s = np.linspace(0.01, 20.0, 200)
    _, d1, d2 = loss.evaluate(s)
    h = 1e-5
    rp, d1p, _ = loss.evaluate(s + h)
    rm, d1m, _ = loss.evaluate(s - h)
    np.testing.assert_allclose(d1, (rp - rm) / (2 * h), rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(d2, (d1p - d1m) / (2 * h), rtol=1e-4, atol=1e-8)
    np.testing.assert_allclose(loss.evaluate(np.zeros(1))[0], 0.0)


def test_cauchy_is_the_seeds_log1p() -> None:
    np.testing.assert_allclose(CauchyLoss().evaluate(np.array([3.0]))[0], np.log(4.0))


def test_corrector_matches_ceres_formulas() -> None:
    """Build Ceres's corrected residual and Jacobian explicitly and compare with our weights."""
    rng = np.random.default_rng(2)
    f = rng.normal(size=3)
    J = rng.normal(size=(3, 5))
    s = float(f @ f)

    def explicit(rho1: float, rho2: float) -> tuple[np.ndarray, np.ndarray]:
        alpha = 0.0 if rho2 <= 0.0 else 1.0 - np.sqrt(1.0 + 2.0 * s * rho2 / rho1)
        ft = np.sqrt(rho1) / (1 - alpha) * f
        Jt = np.sqrt(rho1) * (J - alpha / s * np.outer(f, f) @ J)
        return Jt.T @ Jt, Jt.T @ ft

    for rho1, rho2 in ((0.3, -0.05), (0.8, 0.02), (1.0, 0.0)):
        w, beta = corrector_weights(np.array([s]), np.array([rho1]), np.array([rho2]))
        gp = J.T @ f
        H = w[0] * (J.T @ J - beta[0] * np.outer(gp, gp))
        H_ref, g_ref = explicit(rho1, rho2)
        np.testing.assert_allclose(H, H_ref, atol=1e-12)
        np.testing.assert_allclose(w[0] * gp, g_ref, atol=1e-12)


def test_prior_fit_save_load(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    basis = np.linalg.qr(rng.normal(size=(60, 5)))[0]
    poses = np.zeros((2000, 66))
    poses[:, 6:] = 0.1 + rng.normal(size=(2000, 5)) * [1.0, 0.8, 0.5, 0.3, 0.2] @ basis.T
    poses[:, 6:] += rng.normal(scale=1e-3, size=(2000, 60))
    prior = PcaPrior.fit(poses, 0.95)
    assert 3 <= prior.n_components <= 5
    np.testing.assert_allclose(prior.mu, 0.1, atol=0.05)
    # The kept directions lie in the generating subspace.
    assert np.linalg.norm(prior.M - basis @ (basis.T @ prior.M)) < 0.05
    path = tmp_path / "prior.npz"
    prior.save(path)
    again = PcaPrior.load(path)
    np.testing.assert_array_equal(again.M, prior.M)
    (tmp_path / "bad.npz").write_bytes(b"not a numpy file")
    with pytest.raises(ModelError, match="cannot load"):
        PcaPrior.load(tmp_path / "bad.npz")
    with pytest.raises(ModelError, match="orthonormal"):
        PcaPrior(M=np.ones((60, 2)), mu=np.zeros(60), sigma=np.ones(2))
