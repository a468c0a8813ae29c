"""One person's measurements at one solve time, and their validation against a problem's size."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mocapd.core.skeleton import N_BONES
from mocapd.errors import InputError

N_JOINTS = N_BONES
"""Learned joint observations cover every joint of the skeleton (one per bone)."""

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True, kw_only=True)
class Observations:
    """One person's measurements at one solve time (keyword arguments only; ``dt`` is required).

    Attributes
    ----------
    keypoints : array, shape (n_cams, n_kp, 2), optional
        Distorted pixel positions of the track targets per camera. Rows with confidence 0 are missing and may
        hold NaN.
    confidences : array, shape (n_cams, n_kp), optional
        Detector confidences w_cp in [0, 1]; 0 = missing.
    imu_orientations : array, shape (n_imu, 4), optional
        Measured global bone orientations R_gb (Eq. 8), quaternions (w, x, y, z).
    imu_accelerations : array, shape (n_imu, 3), optional
        Measured global accelerations at the *previous* frame t-1 (Eq. 12), m/s², gravity removed.
    imu_mask : bool array, shape (n_imu,), optional
        Which IMUs have a measurement (default: all). Masked rows may hold NaN.
    joint_positions : array, shape (21, 3), optional
        Learned 3D estimates of the 21 joints (world, metres) for the E_J term (issue 30); rows with weight 0 may
        hold NaN.
    joint_weights : array, shape (21,), optional
        Per-joint weights w_j >= 0 of those estimates (default: all 1).
    dt : float
        Time (seconds) from the previous solve to this one: the Δt of the acceleration term's finite
        difference. Required, with no default: a silent 1/60 s on 100 Hz data scales every measured
        acceleration by 2.8 (issue 14). Callers with time stamps pass their difference; a fixed-rate
        loop passes its period.
    """

    keypoints: FloatArray | None = None
    confidences: FloatArray | None = None
    imu_orientations: FloatArray | None = None
    imu_accelerations: FloatArray | None = None
    imu_mask: BoolArray | None = None
    joint_positions: FloatArray | None = None
    joint_weights: FloatArray | None = None
    dt: float


class ValidatedObservations:
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
            self.uv = np.where((conf > 0)[..., None], uv, 0.0)
            if not np.isfinite(self.uv).all():  # the keypoints used (the others are 0 here)
                raise InputError(
                    "observations: keypoints with confidence > 0 must be finite (use confidence 0 "
                    "for missing keypoints)"
                )
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


def _array(name: str, value: object, shape: tuple[int, ...]) -> FloatArray:
    if value is None:
        raise InputError(f"observations: {name} is missing (expected shape {shape})")
    a = np.asarray(value, dtype=np.float64)
    if a.shape != shape:
        raise InputError(f"observations: {name} must have shape {shape}, got {a.shape}")
    return a


def _bool_array(name: str, value: object, shape: tuple[int, ...]) -> BoolArray:
    a = np.asarray(value)
    if a.shape != shape or a.dtype != np.bool_:
        raise InputError(f"observations: {name} must be a boolean array of shape {shape}, got {a.dtype} {a.shape}")
    return a
