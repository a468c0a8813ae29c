"""Functional calibration: the knees' and elbows' hinge axes from motion refine the sensors' mountings (pure).

A still window tells each sensor's inclination, but not how the sensor sits on its segment: its mounting ``M``
(``R_ib``) and the bone's posture share one measured orientation ``S = R_pose · M``, split by priors
(:func:`mocapd.core.imu_calibration.estimate_mounting`). Motion adds what gravity cannot: a knee and an elbow flex
about one axis of their bones (``e``: the bone-frame x axis for the legs, y for the arms), so while the joint bends,
the rotation between the two sensors on either side turns about that axis as each sensor sees it:

- ``Q(t) = S_p(t)⁻¹ · S_c(t)`` (the child sensor's frame in the parent sensor's), and with the bones' relative
  rotation ``J(t) = M_p · Q(t) · M_c⁻¹ = Rot(e, φ(t))`` (a hinge),
- ``Q(t) · Q₀⁻¹ = M_p⁻¹ · Rot(e, φ(t) − φ₀) · M_p``: a turn about ``a_p = M_p⁻¹ e``, the hinge axis in the parent
  sensor's frame, and ``Q₀⁻¹ · Q(t)`` one about ``a_c = M_c⁻¹ e`` in the child sensor's (``Q₀`` the still window's).

The axis is the principal direction of those turns' rotation vectors over the take (seed: Seel, Raisch & Schauer
2014 estimate the same axes from gyroscopes; orientations give them without a rate model). It fixes two of the
mounting's three degrees of freedom (the turns that move ``e``: for an upper arm its twist and elevation) from the
data, whatever posture was held; the third, the turn about the hinge axis itself, stays the still window's. The
turns' part off the axis is the **hinge misfit** (RMS, degrees): a real knee also rotates and a forearm pronates, a
sensor slides on soft tissue; a misfit above :data:`MAX_MISFIT_DEG` keeps the still window's mounting.

All quaternions are (w, x, y, z), Hamilton, unit norm.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from mocapd.core.imu_calibration import (
    ImuCalibration,
    Samples,
    common_grid,
    posture_angles,
    quat_average,
    window_samples,
)
from mocapd.core.rotations import (
    matrix_from_quat,
    quat_canonical,
    quat_conjugate,
    quat_from_rotvec,
    quat_multiply,
    rotvec_from_quat,
)

FloatArray = NDArray[np.float64]

HINGES: dict[str, tuple[str, str, int]] = {
    "left_knee": ("LeftUpperLeg", "LeftLowerLeg", 0),
    "right_knee": ("RightUpperLeg", "RightLowerLeg", 0),
    "left_elbow": ("LeftUpperArm", "LeftLowerArm", 1),
    "right_elbow": ("RightUpperArm", "RightLowerArm", 1),
}
"""Hinge -> (parent bone, child bone, the hinge's bone-frame axis: 0 x, 1 y)."""

MIN_RANGE_DEG = 30.0
"""A hinge must bend through at least this much (degrees, 5th to 95th percentile of its flexion) to refine the
mountings: a few walking steps bend the knees 40-60°, an elbow bent on purpose 60-100°."""
MAX_MISFIT_DEG = 10.0
"""A hinge whose turns stray more than this (RMS degrees) from one axis keeps the still window's mountings: the real
MTw walk's knees (Neura S02) stray 12-14° (knee rotation, soft tissue), and their axes made that walk worse
(docs/imu.md); the simulated development takes' hinges that refined stray at most 9°."""
MAX_TURN_DEG = 15.0
"""A hinge whose axis would turn a mounting by more than this (degrees) keeps the still window's mountings: a sensor is
strapped within about 8° of its segment's axes (:data:`~mocapd.core.imu_calibration.MOUNT_SIGMA_DEG`), so an axis that
far off is the joint's or the soft tissue's, not the mounting's (the real walk's knees: 18-27°; the simulated takes'
hinges: at most 11.5°)."""
MOVING_DEG = 5.0
"""Samples whose joint turned less than this from the still window's carry no axis and are left out of the misfit."""


@dataclass(frozen=True, slots=True)
class HingeFit:
    """One hinge's axis as each sensor sees it, from :func:`hinge_axes`."""

    axis_parent: FloatArray  # (3,) unit, the parent sensor's frame
    axis_child: FloatArray  # (3,) unit, the child sensor's frame
    range_deg: float  # flexion covered about the axis (5th to 95th percentile)
    misfit_parent_deg: float  # RMS of the turns' part off the axis, parent side
    misfit_child_deg: float
    moving: int  # samples that turned more than MOVING_DEG


def _principal_axis(v: FloatArray, moving: NDArray[np.bool_]) -> tuple[FloatArray, float, float]:
    """Unit axis (3,) of the rotation vectors ``v`` (n, 3) that moved, the range of all along it (degrees, 5th to
    95th percentile) and the RMS of the moving ones' part off it (degrees)."""
    _, vecs = np.linalg.eigh(v[moving].T @ v[moving])
    axis = vecs[:, -1]
    along = v @ axis
    off = np.linalg.norm(v[moving] - along[moving, None] * axis, axis=1)
    lo, hi = np.percentile(along, [5.0, 95.0])
    return axis, float(np.degrees(hi - lo)), float(np.degrees(np.sqrt(np.mean(off**2))))


def hinge_axes(q_parent: FloatArray, q_child: FloatArray, q_parent0: FloatArray, q_child0: FloatArray) -> HingeFit:
    """The hinge axis between two sensors in each one's frame, from their world orientations over a take.

    Parameters
    ----------
    q_parent, q_child : array, shape (n, 4)
        The two sensors' orientations on one time grid (any common world frame: it cancels).
    q_parent0, q_child0 : array, shape (4,)
        Their orientations in the still window (the reference the turns are measured from).
    """
    q0 = quat_multiply(quat_conjugate(q_parent0), q_child0)
    q = quat_multiply(quat_conjugate(np.asarray(q_parent, dtype=np.float64)), np.asarray(q_child, dtype=np.float64))
    v_p = rotvec_from_quat(quat_canonical(quat_multiply(q, quat_conjugate(q0)[None])))
    v_c = rotvec_from_quat(quat_canonical(quat_multiply(quat_conjugate(q0)[None], q)))
    moving = np.linalg.norm(v_p, axis=1) > np.radians(MOVING_DEG)
    if moving.sum() < 3:
        nan = np.full(3, np.nan)
        return HingeFit(nan, nan, 0.0, np.nan, np.nan, int(moving.sum()))
    a_p, range_p, misfit_p = _principal_axis(v_p, moving)
    a_c, _, misfit_c = _principal_axis(v_c, moving)
    return HingeFit(a_p, a_c, range_p, misfit_p, misfit_c, int(moving.sum()))


def aligned_mounting(q_ib: FloatArray, axis_sensor: FloatArray, bone_axis: int) -> tuple[FloatArray, float]:
    """The mounting nearest ``q_ib`` (4,) whose bone-frame axis ``bone_axis`` (0 x, 1 y, 2 z) lies along
    ``axis_sensor`` (3,, the sensor frame; either sign), and the angle it turned by (degrees).

    With ``u = M⁻¹ e`` the axis the mounting has and ``a`` the one measured, ``M' = M · R`` where ``R`` is the
    smallest rotation taking ``a`` to ``u``: then ``M'⁻¹ e = a``.
    """
    e = np.zeros(3)
    e[bone_axis] = 1.0
    u = matrix_from_quat(quat_conjugate(q_ib)) @ e
    a = np.asarray(axis_sensor, dtype=np.float64) / np.linalg.norm(axis_sensor)
    a = a if a @ u >= 0.0 else -a
    cross = np.cross(a, u)
    angle = float(np.arctan2(np.linalg.norm(cross), a @ u))
    turn = quat_from_rotvec(cross / np.linalg.norm(cross) * angle) if angle > 1e-12 else np.array([1.0, 0, 0, 0])
    return quat_canonical(quat_multiply(q_ib, turn)), float(np.degrees(angle))


@dataclass(frozen=True, slots=True)
class FunctionalResult:
    """:func:`refine_mountings`' answer: the refined calibration and what each hinge showed."""

    calibration: ImuCalibration
    hinges: dict[str, dict[str, object]]
    """Per hinge: ``range_deg``, ``misfit_deg`` (the larger side's), ``used`` (whether it refined the mountings),
    and why not (``reason``) or how far each sensor's mounting turned (``turned_deg``)."""


def refine_mountings(
    calib: ImuCalibration,
    orientations: Mapping[str, FloatArray],
    still: Mapping[str, FloatArray],
    *,
    min_range_deg: float = MIN_RANGE_DEG,
    max_misfit_deg: float = MAX_MISFIT_DEG,
    max_turn_deg: float = MAX_TURN_DEG,
) -> FunctionalResult:
    """Refine a still-window calibration's mountings with the hinge axes a take's motion shows.

    Parameters
    ----------
    calib : ImuCalibration
        From the still window (:func:`mocapd.core.imu_calibration.calibrate_recording`).
    orientations : mapping of sensor id to array, shape (n, 4)
        Device-frame orientations ``R_i`` of the calibrated sensors on one time grid (the take's motion).
    still : mapping of sensor id to array, shape (4,)
        Each sensor's mean ``R_i`` in the still window.

    Each hinge with both bones worn, enough flexion (``min_range_deg``), a small misfit (``max_misfit_deg``) and an
    axis near the still window's (each mounting turned by at most ``max_turn_deg``) turns both sensors' mountings onto
    its axis (:func:`aligned_mounting`); their ``hinge_misfit_deg`` is the misfit on their side, and the posture
    found in the still window is measured again with the new mountings.
    """
    by_bone = {b: sid for sid, b in calib.bones.items()}
    own = calib.device_heading_quats()

    def world(sid: str, q: FloatArray) -> FloatArray:
        q = quat_multiply(own[sid], q) if sid in own else q
        return np.asarray(quat_multiply(calib.q_ig, q), dtype=np.float64)

    q_ib = dict(calib.q_ib)
    misfit = dict(calib.hinge_misfit_deg)
    report: dict[str, dict[str, object]] = {}
    for name, (parent, child, axis) in HINGES.items():
        sp, sc = by_bone.get(parent), by_bone.get(child)
        if sp is None or sc is None or sp not in orientations or sc not in orientations:
            continue
        fit = hinge_axes(world(sp, orientations[sp]), world(sc, orientations[sc]),
                         world(sp, still[sp]), world(sc, still[sc]))  # fmt: skip
        worst = max(fit.misfit_parent_deg, fit.misfit_child_deg)
        entry: dict[str, object] = {"range_deg": round(fit.range_deg, 1),
                                    "misfit_deg": None if not np.isfinite(worst) else round(worst, 1)}  # fmt: skip
        if fit.range_deg < min_range_deg:
            report[name] = entry | {"used": False, "reason": f"bent {fit.range_deg:.0f} deg, needs {min_range_deg:g}"}
            continue
        if not worst <= max_misfit_deg:
            report[name] = entry | {"used": False, "reason": f"misfit {worst:.1f} deg, above {max_misfit_deg:g}"}
            continue
        sides = ((sp, fit.axis_parent, fit.misfit_parent_deg), (sc, fit.axis_child, fit.misfit_child_deg))
        aligned = {sid: aligned_mounting(q_ib[sid], a, axis) for sid, a, _ in sides}
        turned = {sid: round(t, 1) for sid, (_, t) in aligned.items()}
        if max(turned.values()) > max_turn_deg:
            report[name] = entry | {"used": False, "turned_deg": turned, "reason": f"its axis would turn a mounting "
                                    f"{max(turned.values()):.0f} deg, above {max_turn_deg:g}"}  # fmt: skip
            continue
        for sid, _, m in sides:
            q_ib[sid] = aligned[sid][0]
            misfit[sid] = m
        report[name] = entry | {"used": True, "turned_deg": turned}
    if not any(r["used"] for r in report.values()):
        return FunctionalResult(calib, report)
    pose = {calib.bones[sid]: quat_multiply(world(sid, still[sid]), quat_conjugate(q)) for sid, q in q_ib.items()
            if sid in still}  # fmt: skip
    return FunctionalResult(replace(calib, q_ib=q_ib, hinge_misfit_deg=misfit, posture=posture_angles(pose)), report)


def still_orientations(orientations: Mapping[str, FloatArray], window: slice) -> dict[str, FloatArray]:
    """Each sensor's mean orientation (4,) over ``window`` of its samples (n, 4)."""
    return {sid: quat_average(np.asarray(q)[window]) for sid, q in orientations.items()}


def refine_from_recording(calib: ImuCalibration, samples: Samples, window: tuple[float, float]) -> FunctionalResult:
    """:func:`refine_mountings` with a recording's motion (every calibrated sensor on the first one's time grid) and
    its still window ``window`` (s), what ``calibrate imu --from`` does after the still window's calibration."""
    sensors = sorted(sid for sid in calib.bones if sid in samples)
    if not sensors:
        return FunctionalResult(calib, {})
    t, orientations = common_grid(samples, sensors)
    return refine_mountings(calib, orientations, still_orientations(orientations, window_samples(t, *window)))
