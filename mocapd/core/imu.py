"""The IMU measurement model of seed 003 §3.1–3.2 (Eq. 8 and Eq. 12).

Frames: an IMU *i* reports its orientation ``R_i`` (sensor → its inertial reference frame) and its specific
force ``a_i`` in the sensor frame (gravity included: at rest it reads +g upwards). ``R_ig`` rotates the
IMU reference frame into the world (Y up). ``R_ib`` is the sensor's orientation in its bone's frame
(sensor → bone), calibrated in a T-pose; ``t_ib`` the sensor's position in the bone frame (metres).

- Eq. 8:  measured global bone orientation ``R_gb = R_ig · R_i · R_ib⁻¹``
- Eq. 12: measured global acceleration ``a_g = R_ig · R_i · a_i - [0, g, 0]``

The seeds quote g = 9.8707 m/s²; mocapd uses standard gravity (9.80665) by default and lets the caller choose.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from mocapd.core.rotations import quat_conjugate, quat_multiply, quat_normalize, quat_rotate
from mocapd.core.skeleton import BONE_INDEX, BONE_NAMES, Skeleton
from mocapd.errors import InputError

FloatArray = NDArray[np.float64]

STANDARD_GRAVITY = 9.80665
"""m/s²."""

IMU_SET_13: tuple[str, ...] = (
    "Hips", "Spine3", "Head",
    "LeftUpperArm", "RightUpperArm", "LeftLowerArm", "RightLowerArm",
    "LeftUpperLeg", "RightUpperLeg", "LeftLowerLeg", "RightLowerLeg", "LeftFoot", "RightFoot",
)  # fmt: skip
"""Pelvis, sternum, head, upper arms, forearms, thighs, shanks, feet (DESIGN.md)."""

IMU_SET_6: tuple[str, ...] = (
    "Hips",
    "Head",
    "LeftLowerArm",
    "RightLowerArm",
    "LeftLowerLeg",
    "RightLowerLeg",
)
"""Pelvis, head, forearms, shanks (DESIGN.md)."""

IMU_SET_LOWER: tuple[str, ...] = (
    "Hips", "LeftUpperLeg", "RightUpperLeg", "LeftLowerLeg", "RightLowerLeg", "LeftFoot", "RightFoot",
)  # fmt: skip
"""A lower-body suit: pelvis, thighs, shanks, feet (gait set-ups such as OpenSense's). A trunk sensor
(:data:`IMU_SET_LOWER_OPTIONAL`) may come with it; the arms and head then follow the pose prior."""

IMU_SET_LOWER_OPTIONAL: tuple[str, ...] = ("Spine", "Spine1", "Spine2", "Spine3")

# Where on each bone a strapped sensor sits by default (bone frame, metres, for a 1.75 m person): on the
# surface, roughly mid-segment. Refined by calibration where available.
_DEFAULT_SENSOR_POSITIONS: dict[str, tuple[float, float, float]] = {
    "Hips": (0.0, 0.02, -0.12),
    "Spine3": (0.0, 0.02, 0.11),
    "Head": (0.0, 0.12, 0.0),
    "LeftUpperArm": (0.15, 0.0, -0.05), "RightUpperArm": (-0.15, 0.0, -0.05),
    "LeftLowerArm": (0.15, 0.03, 0.0), "RightLowerArm": (-0.15, 0.03, 0.0),
    "LeftUpperLeg": (0.03, -0.22, 0.07), "RightUpperLeg": (-0.03, -0.22, 0.07),
    "LeftLowerLeg": (0.0, -0.20, 0.06), "RightLowerLeg": (0.0, -0.20, 0.06),
    "LeftFoot": (0.0, -0.02, 0.08), "RightFoot": (0.0, -0.02, 0.08),
    "Spine": (0.0, 0.05, -0.12), "Spine1": (0.0, 0.05, -0.13), "Spine2": (0.0, 0.05, -0.13),
    "Neck": (0.0, 0.05, -0.06),
    "LeftHand": (0.06, 0.02, 0.0), "RightHand": (-0.06, 0.02, 0.0),
    "LeftToes": (0.0, 0.02, 0.03), "RightToes": (0.0, 0.02, 0.03),
}  # fmt: skip


@dataclass(frozen=True)
class ImuMount:
    """Where one IMU sits on the solver's skeleton: its bone and its position on it.

    The mounting *rotation* ``R_ib`` is deliberately not part of a mount: the solver takes measured **bone**
    orientations (``Observations.imu_orientations``, Eq. 8 already applied), so it has nothing to apply a
    rotation to. The calibration (:class:`mocapd.core.imu_calibration.ImuCalibration`) holds ``R_ig`` and each
    sensor's ``R_ib``, and whoever turns sensor readings into observations applies them
    (:func:`measured_bone_orientation`; the scheduler does it for every suit). An earlier ``q_ib`` field here was
    accepted and silently ignored, so raw sensor quaternions gave ~97° knee errors without any error (issue 14).

    Attributes
    ----------
    bone : str
        One of the 21 bone names.
    t_ib : array, shape (3,)
        Sensor position in the bone frame (metres): where the acceleration term's site is.
    """

    bone: str
    t_ib: FloatArray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        if self.bone not in BONE_INDEX:
            raise InputError(f"IMU bone {self.bone!r} is not one of {BONE_NAMES}")
        t = np.asarray(self.t_ib, dtype=np.float64)
        if t.shape != (3,) or not np.all(np.isfinite(t)):
            raise InputError(f"IMU on {self.bone}: t_ib must be a finite (3,) vector, got {t!r}")
        object.__setattr__(self, "t_ib", t)

    @property
    def bone_index(self) -> int:
        return BONE_INDEX[self.bone]


def default_mounts(bones: tuple[str, ...], skeleton: Skeleton) -> tuple[ImuMount, ...]:
    """Mounts with identity orientation and default positions scaled to the skeleton's height."""
    s = skeleton.height / 1.75
    return tuple(ImuMount(b, t_ib=np.array(_DEFAULT_SENSOR_POSITIONS[b]) * s) for b in bones)


def measured_bone_orientation(q_ig: FloatArray, q_i: FloatArray, q_ib: FloatArray) -> FloatArray:
    """Seed 003 Eq. 8: ``R_gb = R_ig R_i R_ib⁻¹`` on quaternions; shapes (..., 4) broadcast -> (..., 4)."""
    return quat_normalize(quat_multiply(quat_multiply(q_ig, q_i), quat_conjugate(q_ib)))


def measured_global_acceleration(
    q_ig: FloatArray, q_i: FloatArray, a_i: FloatArray, gravity: float = STANDARD_GRAVITY
) -> FloatArray:
    """Seed 003 Eq. 12: ``a_g = R_ig R_i a_i - [0, g, 0]``; q (..., 4), a (..., 3) -> (..., 3) m/s²."""
    a = quat_rotate(quat_multiply(q_ig, q_i), a_i)
    return np.asarray(a - np.array([0.0, gravity, 0.0]))


def sensor_orientation_from_bone(q_ig: FloatArray, q_gb: FloatArray, q_ib: FloatArray) -> FloatArray:
    """Inverse of Eq. 8 (for simulation): the ``R_i`` a sensor reports when its bone has orientation ``q_gb``."""
    return quat_normalize(quat_multiply(quat_multiply(quat_conjugate(q_ig), q_gb), q_ib))


def specific_force_from_acceleration(
    q_ig: FloatArray, q_i: FloatArray, a_g: FloatArray, gravity: float = STANDARD_GRAVITY
) -> FloatArray:
    """Inverse of Eq. 12 (for simulation): sensor-frame specific force for a global acceleration ``a_g``."""
    f_world = np.asarray(a_g, dtype=np.float64) + np.array([0.0, gravity, 0.0])
    return quat_rotate(quat_conjugate(quat_multiply(q_ig, q_i)), f_world)
