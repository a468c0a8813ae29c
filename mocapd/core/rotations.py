"""Vectorized rotations: quaternions (w, x, y, z; Hamilton), rotation vectors, matrices, SO(3) exp/log.

Every function broadcasts over leading dimensions: a quaternion array has shape ``(..., 4)``, a rotation
vector array ``(..., 3)`` and a matrix array ``(..., 3, 3)``. Quaternions are unit, Hamilton convention,
scalar first; they rotate vectors as ``v' = q v q*``, which equals ``matrix_from_quat(q) @ v``.

The SO(3) Jacobians follow the usual right/left convention:

``exp(phi + d) ≈ exp(phi) exp(jr(phi) d) ≈ exp(jl(phi) d) exp(phi)``.

Small-angle branches use Taylor series so that everything is smooth (and finite) at zero.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from mocapd.core.norms import norms

FloatArray = NDArray[np.float64]

# Below this angle (radians) the closed forms lose precision and the Taylor series take over.
_SMALL = 1e-6


def skew(v: FloatArray) -> FloatArray:
    """Cross-product matrices.

    Parameters
    ----------
    v : array, shape (..., 3)

    Returns
    -------
    array, shape (..., 3, 3)
        ``skew(v) @ u == cross(v, u)``.
    """
    v = np.asarray(v, dtype=np.float64)
    out = np.zeros((*v.shape[:-1], 3, 3))
    out[..., 0, 1] = -v[..., 2]
    out[..., 0, 2] = v[..., 1]
    out[..., 1, 0] = v[..., 2]
    out[..., 1, 2] = -v[..., 0]
    out[..., 2, 0] = -v[..., 1]
    out[..., 2, 1] = v[..., 0]
    return out


def quat_identity(shape: tuple[int, ...] = ()) -> FloatArray:
    """Identity quaternions of the given leading shape, shape ``(*shape, 4)``."""
    q = np.zeros((*shape, 4))
    q[..., 0] = 1.0
    return q


def quat_normalize(q: FloatArray) -> FloatArray:
    """Unit quaternions, shape (..., 4)."""
    q = np.asarray(q, dtype=np.float64)
    return np.asarray(q / np.linalg.norm(q, axis=-1, keepdims=True))


def quat_conjugate(q: FloatArray) -> FloatArray:
    """Conjugate (= inverse for unit quaternions), shape (..., 4)."""
    q = np.asarray(q, dtype=np.float64)
    return np.asarray(q * np.array([1.0, -1.0, -1.0, -1.0]))


def quat_multiply(a: FloatArray, b: FloatArray) -> FloatArray:
    """Hamilton product ``a ⊗ b``; shapes (..., 4) broadcast."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    aw, ax, ay, az = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bw, bx, by, bz = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return np.stack(
        (
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ),
        axis=-1,
    )


def quat_multiply_floats(a: Sequence[float], b: Sequence[float]) -> tuple[float, float, float, float]:
    """Hamilton product ``a ⊗ b`` of two single quaternions given as 4 numbers each, in plain Python.

    The same operations in the same order as :func:`quat_multiply`, so the result is bit for bit the same; for one
    quaternion at a time (an IMU sample as it arrives) it skips numpy's per-call cost (~25 µs → ~1 µs).
    """
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


def quat_canonical(q: FloatArray) -> FloatArray:
    """The representative of ``±q`` with ``w >= 0``, shape (..., 4)."""
    q = np.asarray(q, dtype=np.float64)
    return np.where(q[..., :1] < 0.0, -q, q)


def quat_rotate(q: FloatArray, v: FloatArray) -> FloatArray:
    """Rotate vectors: ``q v q*``; q shape (..., 4), v shape (..., 3) (broadcast)."""
    q = np.asarray(q, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    w = q[..., :1]
    u = q[..., 1:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def matrix_from_quat(q: FloatArray) -> FloatArray:
    """Rotation matrices from unit quaternions: (..., 4) -> (..., 3, 3)."""
    q = np.asarray(q, dtype=np.float64)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    out = np.empty((*q.shape[:-1], 3, 3))
    out[..., 0, 0] = 1.0 - 2.0 * (yy + zz)
    out[..., 0, 1] = 2.0 * (xy - wz)
    out[..., 0, 2] = 2.0 * (xz + wy)
    out[..., 1, 0] = 2.0 * (xy + wz)
    out[..., 1, 1] = 1.0 - 2.0 * (xx + zz)
    out[..., 1, 2] = 2.0 * (yz - wx)
    out[..., 2, 0] = 2.0 * (xz - wy)
    out[..., 2, 1] = 2.0 * (yz + wx)
    out[..., 2, 2] = 1.0 - 2.0 * (xx + yy)
    return out


def quat_from_matrix(R: FloatArray) -> FloatArray:
    """Unit quaternions (w >= 0) from rotation matrices: (..., 3, 3) -> (..., 4).

    Uses the numerically stable branch on the largest of (trace, diagonal) per element (Shepperd's method).
    """
    R = np.asarray(R, dtype=np.float64)
    m00, m11, m22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    trace = m00 + m11 + m22
    cand = np.stack((trace, m00, m11, m22), axis=-1)
    choice = np.argmax(cand, axis=-1)
    q = np.empty((*R.shape[:-2], 4))

    # Each branch computes all four components from the dominant one; evaluate all, then select.
    s0 = np.sqrt(np.maximum(1.0 + trace, 1e-300)) * 2.0
    b0 = np.stack(
        (
            0.25 * s0,
            (R[..., 2, 1] - R[..., 1, 2]) / s0,
            (R[..., 0, 2] - R[..., 2, 0]) / s0,
            (R[..., 1, 0] - R[..., 0, 1]) / s0,
        ),
        axis=-1,
    )
    s1 = np.sqrt(np.maximum(1.0 + m00 - m11 - m22, 1e-300)) * 2.0
    b1 = np.stack(
        (
            (R[..., 2, 1] - R[..., 1, 2]) / s1,
            0.25 * s1,
            (R[..., 0, 1] + R[..., 1, 0]) / s1,
            (R[..., 0, 2] + R[..., 2, 0]) / s1,
        ),
        axis=-1,
    )
    s2 = np.sqrt(np.maximum(1.0 + m11 - m00 - m22, 1e-300)) * 2.0
    b2 = np.stack(
        (
            (R[..., 0, 2] - R[..., 2, 0]) / s2,
            (R[..., 0, 1] + R[..., 1, 0]) / s2,
            0.25 * s2,
            (R[..., 1, 2] + R[..., 2, 1]) / s2,
        ),
        axis=-1,
    )
    s3 = np.sqrt(np.maximum(1.0 + m22 - m00 - m11, 1e-300)) * 2.0
    b3 = np.stack(
        (
            (R[..., 1, 0] - R[..., 0, 1]) / s3,
            (R[..., 0, 2] + R[..., 2, 0]) / s3,
            (R[..., 1, 2] + R[..., 2, 1]) / s3,
            0.25 * s3,
        ),
        axis=-1,
    )
    c = choice[..., None]
    q = np.where(c == 0, b0, np.where(c == 1, b1, np.where(c == 2, b2, b3)))
    return quat_canonical(quat_normalize(q))


def quat_from_rotvec(r: FloatArray) -> FloatArray:
    """Quaternions from rotation vectors (axis · angle, radians): (..., 3) -> (..., 4)."""
    r = np.asarray(r, dtype=np.float64)
    angle = np.linalg.norm(r, axis=-1, keepdims=True)
    half = 0.5 * angle
    small = angle < _SMALL
    safe = np.where(small, 1.0, angle)
    # sin(a/2)/a, with its series 1/2 - a^2/48 near zero.
    k = np.where(small, 0.5 - angle * angle / 48.0, np.sin(half) / safe)
    return np.concatenate((np.cos(half), k * r), axis=-1)


def rotvec_from_quat(q: FloatArray) -> FloatArray:
    """Rotation vectors with angle in [0, π] from quaternions: (..., 4) -> (..., 3)."""
    q = quat_canonical(q)
    w = np.clip(q[..., :1], -1.0, 1.0)
    v = q[..., 1:]
    s = np.linalg.norm(v, axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(s, w)
    small = s < _SMALL
    safe = np.where(small, 1.0, s)
    # angle / sin(angle/2) -> 2 / w * (1 + s^2 / (3 w^2)) near zero.
    k = np.where(small, 2.0 / w * (1.0 + s * s / (3.0 * w * w)), angle / safe)
    return np.asarray(k * v)


def rotvec_principal(r: FloatArray) -> FloatArray:
    """The same rotations as rotation vectors of angle at most π: (..., 3) -> (..., 3).

    ``r`` and ``r - 2πk · r/|r|`` are one rotation; this takes the ``k`` that brings the angle into [0, π] (at
    exactly π either sign is the rotation). Unlike :func:`rotvec_from_quat` ∘ :func:`quat_from_rotvec` it leaves a
    vector already in range bit for bit unchanged.
    """
    r = np.asarray(r, dtype=np.float64)
    angle = norms(r, keepdims=True)  # np.linalg.norm's floats: every person solve winds its pose
    if not (angle >= np.pi).any():  # nothing wound (angle - π < 0 exactly when angle < π): every scale 1.0
        return r * 1.0
    turns = np.floor((angle - np.pi) / (2.0 * np.pi)) + 1.0  # 0 while angle < π
    wound = turns > 0.0
    scale = np.where(wound, 1.0 - 2.0 * np.pi * turns / np.where(wound, angle, 1.0), 1.0)
    return np.asarray(r * scale)


def matrix_from_rotvec(r: FloatArray) -> FloatArray:
    """SO(3) exponential (Rodrigues): (..., 3) -> (..., 3, 3)."""
    r = np.asarray(r, dtype=np.float64)
    theta2 = np.sum(r * r, axis=-1)[..., None, None]
    theta = np.sqrt(theta2)
    small = theta < _SMALL
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta2 / 24.0, (1.0 - np.cos(safe)) / (safe * safe))
    K = skew(r)
    return np.asarray(np.eye(3) + a * K + b * (K @ K))


def rotvec_from_matrix(R: FloatArray) -> FloatArray:
    """SO(3) logarithm, angle in [0, π]: (..., 3, 3) -> (..., 3). Stable near 0 and π (via quaternions)."""
    return rotvec_from_quat(quat_from_matrix(R))


# Short aliases following the Lie-group naming used in the solver.
so3_exp = matrix_from_rotvec
so3_log = rotvec_from_matrix


def so3_right_jacobian(r: FloatArray) -> FloatArray:
    """Right Jacobian of the SO(3) exponential: ``exp(r + d) ≈ exp(r) exp(jr(r) d)``.

    Parameters
    ----------
    r : array, shape (..., 3)

    Returns
    -------
    array, shape (..., 3, 3)
        ``I - (1 - cos θ)/θ² [r]× + (θ - sin θ)/θ³ [r]×²``.
    """
    r = np.asarray(r, dtype=np.float64)
    theta2 = np.sum(r * r, axis=-1)[..., None, None]
    theta = np.sqrt(theta2)
    small = theta < 1e-4
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 0.5 - theta2 / 24.0, (1.0 - np.cos(safe)) / (safe * safe))
    b = np.where(small, 1.0 / 6.0 - theta2 / 120.0, (safe - np.sin(safe)) / (safe * safe * safe))
    K = skew(r)
    return np.asarray(np.eye(3) - a * K + b * (K @ K))


def so3_left_jacobian(r: FloatArray) -> FloatArray:
    """Left Jacobian: ``exp(r + d) ≈ exp(jl(r) d) exp(r)``; equals ``jr(-r)``. Shape (..., 3) -> (..., 3, 3)."""
    return so3_right_jacobian(-np.asarray(r, dtype=np.float64))


def so3_right_jacobian_inv(r: FloatArray) -> FloatArray:
    """Inverse of :func:`so3_right_jacobian`: ``log(exp(r) exp(d)) ≈ r + jr_inv(r) d``. (..., 3) -> (..., 3, 3).

    ``I + [r]×/2 + (1/θ² - (1 + cos θ)/(2 θ sin θ)) [r]×²``; singular at θ = 2π, finite on [0, π].
    """
    r = np.asarray(r, dtype=np.float64)
    theta2 = np.sum(r * r, axis=-1)[..., None, None]
    theta = np.sqrt(theta2)
    small = theta < 1e-4
    safe = np.where(small, 1.0, theta)
    c = np.where(
        small,
        1.0 / 12.0 + theta2 / 720.0,
        1.0 / (safe * safe) - (1.0 + np.cos(safe)) / (2.0 * safe * np.sin(safe)),
    )
    K = skew(r)
    return np.eye(3) + 0.5 * K + c * (K @ K)


def quat_slerp(q0: FloatArray, q1: FloatArray, t: FloatArray | float) -> FloatArray:
    """Spherical linear interpolation along the shorter arc.

    Parameters
    ----------
    q0, q1 : array, shape (..., 4)
    t : float or array broadcastable to shape (...)
        0 gives ``q0``, 1 gives ``q1`` (up to sign).

    Returns
    -------
    array, shape (..., 4)
    """
    q0 = np.asarray(q0, dtype=np.float64)
    q1 = np.asarray(q1, dtype=np.float64)
    t_arr = np.asarray(t, dtype=np.float64)[..., None]
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0.0, -q1, q1)
    dot = np.abs(dot)
    close = dot > 1.0 - 1e-9
    omega = np.arccos(np.clip(dot, -1.0, 1.0))
    sin_omega = np.where(close, 1.0, np.sin(omega))
    w0 = np.where(close, 1.0 - t_arr, np.sin((1.0 - t_arr) * omega) / sin_omega)
    w1 = np.where(close, t_arr, np.sin(t_arr * omega) / sin_omega)
    return quat_normalize(w0 * q0 + w1 * q1)


def quat_angle(a: FloatArray, b: FloatArray) -> FloatArray:
    """Angle (radians, in [0, π]) of the relative rotation between two quaternion arrays (..., 4)."""
    d = np.abs(np.sum(quat_normalize(a) * quat_normalize(b), axis=-1))
    return np.asarray(2.0 * np.arccos(np.clip(d, 0.0, 1.0)))


def random_quat(rng: np.random.Generator, shape: tuple[int, ...] = ()) -> FloatArray:
    """Uniformly distributed unit quaternions (w >= 0), shape ``(*shape, 4)``."""
    return quat_canonical(quat_normalize(rng.normal(size=(*shape, 4))))


def random_rotvec(rng: np.random.Generator, shape: tuple[int, ...] = (), max_angle: float = np.pi) -> FloatArray:
    """Rotation vectors with uniform axis and angle uniform in [0, max_angle), shape ``(*shape, 3)``."""
    axis = rng.normal(size=(*shape, 3))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    return axis * rng.uniform(0.0, max_angle, size=(*shape, 1))
