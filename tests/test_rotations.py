"""Seeded round trips and derivative checks for mocapd.core.rotations."""

from __future__ import annotations

import numpy as np
import pytest

from mocapd.core import rotations as rot

RNG_SEEDS = [0, 1, 2]


def _rng(seed: int) -> np.random.Generator:
    return np.random.default_rng(seed)


def _same_quat(a: np.ndarray, b: np.ndarray, atol: float = 1e-10) -> None:
    np.testing.assert_allclose(rot.quat_canonical(a), rot.quat_canonical(b), atol=atol)


@pytest.mark.parametrize("seed", RNG_SEEDS)
def test_quat_matrix_round_trip(seed: int) -> None:
    q = rot.random_quat(_rng(seed), (500,))
    R = rot.matrix_from_quat(q)
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    _same_quat(rot.quat_from_matrix(R), q)


def test_quat_from_matrix_every_branch() -> None:
    # 180° about each axis exercises the three diagonal branches; identity the trace branch.
    for axis in np.eye(3):
        R = rot.matrix_from_rotvec(axis * np.pi)
        q = rot.quat_from_matrix(R)
        np.testing.assert_allclose(rot.matrix_from_quat(q), R, atol=1e-12)
    np.testing.assert_allclose(rot.quat_from_matrix(np.eye(3)), [1, 0, 0, 0])


@pytest.mark.parametrize("seed", RNG_SEEDS)
def test_rotvec_round_trips(seed: int) -> None:
    r = rot.random_rotvec(_rng(seed), (500,), max_angle=np.pi - 1e-6)
    np.testing.assert_allclose(rot.rotvec_from_quat(rot.quat_from_rotvec(r)), r, atol=1e-9)
    np.testing.assert_allclose(rot.so3_log(rot.so3_exp(r)), r, atol=1e-8)
    np.testing.assert_allclose(rot.matrix_from_quat(rot.quat_from_rotvec(r)), rot.so3_exp(r), atol=1e-12)


def test_small_angles_are_smooth() -> None:
    r = np.array([[1e-9, -2e-9, 3e-9], [0.0, 0.0, 0.0], [1e-7, 0.0, 0.0]])
    np.testing.assert_allclose(rot.so3_log(rot.so3_exp(r)), r, atol=1e-15)
    np.testing.assert_allclose(rot.rotvec_from_quat(rot.quat_from_rotvec(r)), r, atol=1e-15)
    assert np.all(np.isfinite(rot.so3_right_jacobian(r)))
    assert np.all(np.isfinite(rot.so3_right_jacobian_inv(r)))


@pytest.mark.parametrize("seed", RNG_SEEDS)
def test_product_matches_matrices_and_rotation(seed: int) -> None:
    rng = _rng(seed)
    a, b = rot.random_quat(rng, (100,)), rot.random_quat(rng, (100,))
    v = rng.normal(size=(100, 3))
    np.testing.assert_allclose(
        rot.matrix_from_quat(rot.quat_multiply(a, b)),
        rot.matrix_from_quat(a) @ rot.matrix_from_quat(b),
        atol=1e-12,
    )
    np.testing.assert_allclose(rot.quat_rotate(a, v), np.einsum("nij,nj->ni", rot.matrix_from_quat(a), v), atol=1e-12)
    ident = rot.quat_multiply(a, rot.quat_conjugate(a))
    np.testing.assert_allclose(ident, rot.quat_identity((100,)), atol=1e-12)


@pytest.mark.parametrize("seed", RNG_SEEDS)
def test_right_and_left_jacobians(seed: int) -> None:
    rng = _rng(seed)
    r = rot.random_rotvec(rng, (50,), max_angle=3.0)
    d = rng.normal(size=(50, 3)) * 1e-6
    Jr = rot.so3_right_jacobian(r)
    Jl = rot.so3_left_jacobian(r)
    lhs = rot.so3_exp(r + d)
    right = rot.so3_exp(r) @ rot.so3_exp(np.einsum("nij,nj->ni", Jr, d))
    left = rot.so3_exp(np.einsum("nij,nj->ni", Jl, d)) @ rot.so3_exp(r)
    np.testing.assert_allclose(lhs, right, atol=1e-11)
    np.testing.assert_allclose(lhs, left, atol=1e-11)
    np.testing.assert_allclose(rot.so3_right_jacobian_inv(r) @ Jr, np.broadcast_to(np.eye(3), Jr.shape), atol=1e-10)


def test_right_jacobian_series_matches_closed_form_at_the_switch() -> None:
    r = np.array([0.6e-4, -0.5e-4, 0.3e-4])  # below the 1e-4 switch: the series branch
    t = np.linalg.norm(r)
    K = rot.skew(r)
    closed = np.eye(3) - (1 - np.cos(t)) / t**2 * K + (t - np.sin(t)) / t**3 * K @ K
    # The closed form loses ~eps/θ² to cancellation here, hence the tolerance.
    np.testing.assert_allclose(rot.so3_right_jacobian(r), closed, atol=1e-7)


@pytest.mark.parametrize("seed", RNG_SEEDS)
def test_slerp(seed: int) -> None:
    rng = _rng(seed)
    a, b = rot.random_quat(rng, (100,)), rot.random_quat(rng, (100,))
    _same_quat(rot.quat_slerp(a, b, 0.0), a)
    _same_quat(rot.quat_slerp(a, b, 1.0), b)
    mid = rot.quat_slerp(a, b, 0.5)
    np.testing.assert_allclose(rot.quat_angle(a, mid), 0.5 * rot.quat_angle(a, b), atol=1e-9)
    np.testing.assert_allclose(rot.quat_angle(mid, b), 0.5 * rot.quat_angle(a, b), atol=1e-9)
    # Shorter arc even when the inputs are on opposite hemispheres.
    mid2 = rot.quat_slerp(a, -b, 0.5)
    _same_quat(mid2, mid)
    # Nearly identical inputs fall back to lerp without NaN.
    assert np.all(np.isfinite(rot.quat_slerp(a, a, 0.3)))


def test_skew() -> None:
    rng = _rng(3)
    v, u = rng.normal(size=(10, 3)), rng.normal(size=(10, 3))
    np.testing.assert_allclose(np.einsum("nij,nj->ni", rot.skew(v), u), np.cross(v, u), atol=1e-12)


def test_rotvec_principal_winds_back_whole_turns_and_keeps_the_rotation() -> None:
    rng = np.random.default_rng(3)
    r = rot.random_rotvec(rng, (200,))
    axis = r / np.linalg.norm(r, axis=-1, keepdims=True)
    wound = r + axis * 2.0 * np.pi * rng.integers(-30, 31, size=(200, 1))  # up to 30 turns either way
    back = rot.rotvec_principal(wound)
    assert np.all(np.linalg.norm(back, axis=-1) <= np.pi + 1e-9)
    np.testing.assert_allclose(rot.matrix_from_rotvec(back), rot.matrix_from_rotvec(wound), atol=1e-9)
    np.testing.assert_allclose(back, r, atol=1e-9)  # the principal vector of each rotation
    assert np.array_equal(rot.rotvec_principal(r), r)  # in range: bit for bit unchanged
    assert np.array_equal(rot.rotvec_principal(np.zeros((2, 3))), np.zeros((2, 3)))
    np.testing.assert_allclose(rot.rotvec_principal(np.array([0.0, 2.0 * np.pi, 0.0])), 0.0, atol=1e-12)
