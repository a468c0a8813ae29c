"""Gravity from stance phases: the walk's stances refine the leg and trunk sensors' inclination (pure).

A still window gives each sensor's inclination once, in whatever posture the wearer held: a trunk leaning a few
degrees, knees bent with the hips ahead of the ankles. The priors that split that posture from the mountings
(:func:`mocapd.core.imu_calibration.estimate_mounting`) assume the trunk upright and the ankle under the hip; a real
suit owner rarely holds them well, and the difference stays in the mountings. Every stance of a walk gives another
look at gravity in another posture (what gait labs and commercial suits use besides the N-pose):

- a **stance** is a stretch in which a foot's sensor is still (:func:`detect_stances`: its orientation turns less
  than :data:`STILL_RATE_DEG_S`, its specific force within :data:`ACC_TOL` of g, for
  :data:`MIN_STANCE_S` to :data:`MAX_STANCE_S`: a walk's foot-flat, not a stand);
- in it the trunk (pelvis, sternum) is upright and the stance leg's ankle is under its hip: the thigh's and the
  shank's sagittal tilts cancel (their sum is zero whatever the knee's bend, the same model as the still window's
  :func:`mocapd.core.imu_calibration.knee_flexion`);
- with the calibration's mountings each sensor's bone tilt in each stance is measured (its up axis in the world);
  what the model says it should be is the stance's **gravity misfit**: for a trunk sensor its bone's tilt from
  upright, for a leg the half sum of its thigh's and shank's sagittal tilts (the part of the leg's lean that the
  knee's bend does not explain). A mounting off by ``ε`` about the leg's flexion axis adds ``ε/2`` to every stance's
  half sum; a posture held badly in the still window adds nothing here.

Combined over a take's stances (the mean, :func:`stance_gravity`), the misfit is the mounting's error in the
directions gravity sees. A **trunk** sensor is refined where it is consistent (:func:`refine_from_stances`): at least
:data:`MIN_STANCES` stances, their misfits agreeing within :data:`MAX_SPREAD_DEG` (RMS about their mean), a mean misfit
of at most :data:`MAX_TURN_DEG`; then the still window's mounting and the stances' are combined by their variances
(:data:`STILL_SIGMA_DEG`: how well a person holds the model standing; :data:`STANCE_SIGMA_DEG`: how well a walk's
stances do). A **leg**'s misfit (about its flexion axis only, the one the knees' hinge axes cannot see,
:mod:`mocapd.core.functional_calibration`) is measured and kept but not applied (:data:`REFINE_LEGS`): a walk's
foot-flat rolls the leg over the ankle, and the stances' mean lean is off the model by as much as it would correct.
Every sensor with stances keeps its gravity misfit after the refinement (RMS over its stances, degrees) in the
calibration (``gravity_misfit_deg``): in the calibration file, ``/status`` and the console.

All quaternions are (w, x, y, z), Hamilton, unit norm; world +Y up; bone frames are the solver's rest frames (a leg's
flexion axis x, up y).
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
    quat_angle,
    quat_canonical,
    quat_conjugate,
    quat_from_rotvec,
    quat_multiply,
)

FloatArray = NDArray[np.float64]

GRAVITY = 9.81
"""m/s²."""
STILL_RATE_DEG_S = 30.0
"""A foot's sensor is still while its orientation turns slower than this (degrees per second, over
:data:`RATE_SPAN_S`): foot-flat in a walk turns the foot a few degrees per second; heel strike and push-off hundreds."""
RATE_SPAN_S = 0.1
"""The span (s) over which the turn rate is measured: long enough that 0.2-0.5° of orientation noise reads as a few
degrees per second, short enough for a 0.2 s foot-flat."""
ACC_TOL = 1.5
"""A still foot's specific force is within this of g (m/s²): a foot flat on the floor does not accelerate; heel
strike jolts it by tens."""
MIN_STANCE_S = 0.1
"""A stance lasts at least this (s): shorter still stretches are a foot turning through zero rate."""
MAX_STANCE_S = 1.5
"""A still stretch longer than this (s) is a stand, not a walk's stance: the still window's posture again."""
MIN_STANCES = 3
"""A sensor's stances must number at least this: a leg's own side's, every foot's for the trunk."""
MAX_SPREAD_DEG = 6.0
"""The stances' misfits must agree within this (RMS about their mean, degrees): stances that disagree more are not
one posture, and their mean says little of the mounting."""
MAX_TURN_DEG = 15.0
"""A mean misfit above this (degrees) is not a mounting error (a sensor is strapped within about 8° of its segment,
:data:`~mocapd.core.imu_calibration.MOUNT_SIGMA_DEG`): the still window's mounting stays."""
STILL_SIGMA_DEG = 3.0
"""How far (degrees) a standing person's trunk tilt, or half sum of a leg's tilts, strays from the model."""
STANCE_SIGMA_DEG = 3.0
"""How far (degrees) a walk's mean over its stances does: a trunk leaning into the walk, a leg at foot-flat rolling
over the ankle (the development walks: 1-3°)."""

REFINE_LEGS = False
"""Whether the legs' stances turn their mountings (else their gravity misfit is measured and kept only): a walk's
foot-flat rolls the leg over the ankle, so the stances' mean leg lean is a few degrees off the model (the development
walks: 1-4°; the real MTw walk's 2-3°), the size of the errors it would fix. Applied, it made the real MTw walk's path
−3.0 → −3.5 % and its hip RMSE 8.7 → 9.2° (docs/imu.md). No other instant of the stance does better: the true leg
lean at the foot-flat's middle, the shank's slowest turn, the top of the pelvis's vault, the knee's straightest moves
by 2-7° from walker to walker (``tools/stance_leg_lean.py``, docs/imu.md "The legs in the stances")."""
TRUNK = ("Hips", "Spine3")
"""Trunk bones whose sensors the stances refine (upright in every stance)."""
LEGS = {"Left": ("LeftUpperLeg", "LeftLowerLeg", "LeftFoot"), "Right": ("RightUpperLeg", "RightLowerLeg", "RightFoot")}
"""Per side: thigh, shank and the foot whose stillness marks the stance."""


def turn_rate(t: FloatArray, q: FloatArray, span_s: float = RATE_SPAN_S) -> FloatArray:
    """Each sample's turn rate (rad/s, shape (n,)) over ``span_s`` centred on it; inf where the span leaves the
    recording. ``t`` (n,) seconds, ``q`` (n, 4)."""
    n = len(t)
    rate = np.full(n, np.inf)
    if n < 3:
        return rate
    dt = float(np.median(np.diff(t)))
    h = max(1, round(span_s / dt / 2)) if dt > 0 else 1
    if n <= 2 * h:
        return rate
    angle = quat_angle(q[2 * h :], q[: -2 * h])
    rate[h : n - h] = angle / np.maximum(t[2 * h :] - t[: -2 * h], 1e-9)
    return rate


def detect_stances(
    t: FloatArray,
    q: FloatArray,
    acc: FloatArray,
    *,
    exclude: tuple[float, float] | None = None,
) -> list[tuple[float, float]]:
    """The stances in one foot sensor's samples: stretches (start, end, s) that are still by both tests.

    Parameters
    ----------
    t : array, shape (n,)
        Sample times (s).
    q : array, shape (n, 4)
        The sensor's orientations.
    acc : array, shape (n, 3)
        Its specific force (m/s², gravity included).
    exclude : (float, float), optional
        A span (s) whose still stretch is left out: the still window the calibration stood in.
    """
    t = np.asarray(t, dtype=np.float64)
    still = (turn_rate(t, np.asarray(q, dtype=np.float64)) < np.radians(STILL_RATE_DEG_S)) & (
        np.abs(np.linalg.norm(np.asarray(acc, dtype=np.float64), axis=1) - GRAVITY) < ACC_TOL
    )
    edges = np.flatnonzero(np.diff(np.concatenate([[0], still.astype(np.int8), [0]])))
    out = []
    for i0, i1 in zip(edges[::2], edges[1::2], strict=True):
        start, end = float(t[i0]), float(t[i1 - 1])
        if exclude is not None and start <= exclude[1] and end >= exclude[0]:
            continue  # the stand the calibration's still window is in, not a stance
        if MIN_STANCE_S <= end - start <= MAX_STANCE_S:
            out.append((start, end))
    return out


def _bone_up(q_gb: FloatArray) -> FloatArray:
    """The world's up direction in a bone's frame (3,), from the bone's world orientation (4,)."""
    return np.asarray(matrix_from_quat(q_gb).T @ np.array([0.0, 1.0, 0.0]), dtype=np.float64)


def trunk_misfit(q_gb: FloatArray) -> FloatArray:
    """A trunk bone's misfit in a stance: the turn (rotation vector in its frame, (3,), radians; y is 0) that takes
    its measured up direction to the world's, i.e. ``δ`` with ``M' = δ · M`` making it upright."""
    u = _bone_up(q_gb)
    horizontal = float(np.hypot(u[0], u[2]))
    angle = float(np.arctan2(horizontal, u[1]))
    return np.array([-u[2], 0.0, u[0]]) * angle / max(horizontal, 1e-12)


def sagittal_tilt(q_gb: FloatArray) -> float:
    """A leg bone's tilt about its flexion axis (radians): the angle of its frame's up axis from the world's up, in
    the bone's y-z plane (a thigh turned by ``a`` about x tilts by ``-a``)."""
    u = _bone_up(q_gb)
    return float(np.arctan2(u[2], u[1]))


@dataclass(frozen=True, slots=True)
class StanceGravity:
    """One sensor's stances (:func:`stance_gravity`): per stance its misfit (rotation vector in its bone's frame,
    radians), its mean, and their spread."""

    misfits: FloatArray  # (k, 3)
    mean: FloatArray  # (3,)
    spread_deg: float  # RMS of the stances' misfits about their mean

    @property
    def count(self) -> int:
        return len(self.misfits)

    @property
    def mean_deg(self) -> float:
        return float(np.degrees(np.linalg.norm(self.mean)))


def _summarise(misfits: list[FloatArray]) -> StanceGravity:
    m = np.array(misfits, dtype=np.float64).reshape(-1, 3)
    mean = m.mean(axis=0) if len(m) else np.zeros(3)
    spread = float(np.degrees(np.sqrt(np.mean(np.sum((m - mean) ** 2, axis=1))))) if len(m) else float("nan")
    return StanceGravity(m, mean, spread)


def stance_gravity(
    calib: ImuCalibration, samples: Samples, stances: Mapping[str, list[tuple[float, float]]]
) -> dict[str, StanceGravity]:
    """Each refinable sensor's gravity misfit over the stances, with the calibration's mountings.

    Parameters
    ----------
    calib : ImuCalibration
        The calibration whose mountings are measured.
    samples : Samples
        The recording (per sensor: times (s), orientations, specific force).
    stances : mapping of side ("Left", "Right") to list of (float, float)
        Each foot's stances (s, :func:`detect_stances`).

    Returns per sensor id (a trunk sensor, or a thigh or shank with its own side's stances) its
    :class:`StanceGravity`; a leg's misfit is about the bone's x axis only, the same for its thigh and shank.
    """
    by_bone = {b: sid for sid, b in calib.bones.items() if sid in samples}
    own = calib.device_heading_quats()
    sensors = sorted(by_bone.values())
    if not sensors:
        return {}
    t, q = common_grid(samples, sensors)

    def bone_at(bone: str, span: tuple[float, float]) -> FloatArray | None:
        sid = by_bone.get(bone)
        sel = (t >= span[0]) & (t <= span[1])
        if sid is None or not sel.any():
            return None
        s = quat_average(q[sid][sel])
        s = quat_multiply(own[sid], s) if sid in own else s
        return np.asarray(quat_multiply(quat_multiply(calib.q_ig, s), quat_conjugate(calib.q_ib[sid])))

    misfits: dict[str, list[FloatArray]] = {}
    for side, spans in stances.items():
        thigh, shank, _ = LEGS[side]
        for span in spans:
            for bone in TRUNK:
                q_gb = bone_at(bone, span)
                if q_gb is not None:
                    misfits.setdefault(by_bone[bone], []).append(trunk_misfit(q_gb))
            q_t, q_s = bone_at(thigh, span), bone_at(shank, span)
            if q_t is None or q_s is None:
                continue
            # the turn about x that makes both tilts cancel when given to both mountings
            half_sum = (sagittal_tilt(q_t) + sagittal_tilt(q_s)) / 2.0
            for bone in (thigh, shank):
                misfits.setdefault(by_bone[bone], []).append(np.array([-half_sum, 0.0, 0.0]))
    return {sid: _summarise(m) for sid, m in misfits.items()}


def foot_stances(
    calib: ImuCalibration, samples: Samples, still_window: tuple[float, float] | None
) -> dict[str, list[tuple[float, float]]]:
    """Each worn foot's stances (side -> list of (start, end) s), the still window left out."""
    by_bone = {b: sid for sid, b in calib.bones.items() if sid in samples}
    out = {}
    for side, (_, _, foot) in LEGS.items():
        sid = by_bone.get(foot)
        if sid is not None:
            t, q, a = samples[sid]
            out[side] = detect_stances(t, q, a, exclude=still_window)
    return out


@dataclass(frozen=True, slots=True)
class StanceResult:
    """:func:`refine_from_stances`' answer: the refined calibration and what each sensor's stances showed."""

    calibration: ImuCalibration
    sensors: dict[str, dict[str, object]]
    """Per sensor id: ``bone``, ``stances``, ``misfit_deg`` (the stances' mean misfit with the mountings before),
    ``spread_deg``, ``used``, and why not (``reason``) or how far the mounting turned (``turned_deg``)."""
    stances: dict[str, int]
    """Per side, the foot's stances found."""


def _weight() -> float:
    """The share of the stances' estimate in the combined one (their variances)."""
    return STILL_SIGMA_DEG**2 / (STILL_SIGMA_DEG**2 + STANCE_SIGMA_DEG**2)


def refine_from_stances(
    calib: ImuCalibration,
    samples: Samples,
    still_window: tuple[float, float] | None,
    *,
    min_stances: int = MIN_STANCES,
    max_spread_deg: float = MAX_SPREAD_DEG,
    max_turn_deg: float = MAX_TURN_DEG,
) -> StanceResult:
    """Refine the trunk, thigh and shank mountings with gravity in a take's stances (see the module docstring).

    A sensor is refined when it has at least ``min_stances`` stances, their misfits agree within ``max_spread_deg``
    and their mean is at most ``max_turn_deg``: its mounting turns by the variance-weighted share of the mean misfit
    (``M' = exp(w · m̄) · M`` in the bone's frame, which turns every stance's bone tilt by ``w · m̄`` back toward the
    model). Every sensor with stances gets its gravity misfit (the RMS of its stances' misfits with the mountings
    kept, degrees) in ``gravity_misfit_deg``; the posture found in the still window is measured again.
    """
    stances = foot_stances(calib, samples, still_window)
    gravity = stance_gravity(calib, samples, stances)
    q_ib = dict(calib.q_ib)
    report: dict[str, dict[str, object]] = {}
    turns: dict[str, FloatArray] = {}
    w = _weight()
    for sid, g in sorted(gravity.items()):
        entry: dict[str, object] = {"bone": calib.bones[sid], "stances": g.count, "misfit_deg": round(g.mean_deg, 1),
                                    "spread_deg": round(g.spread_deg, 1)}  # fmt: skip
        if not REFINE_LEGS and calib.bones[sid] not in TRUNK:
            report[sid] = entry | {"used": False, "reason": "a leg: its stances' lean is measured, not applied"}
            continue
        if g.count < min_stances:
            report[sid] = entry | {"used": False, "reason": f"{g.count} stances, needs {min_stances}"}
            continue
        if not g.spread_deg <= max_spread_deg:
            report[sid] = entry | {"used": False, "reason": f"stances spread {g.spread_deg:.1f} deg, "
                                   f"above {max_spread_deg:g}"}  # fmt: skip
            continue
        if g.mean_deg > max_turn_deg:
            report[sid] = entry | {"used": False, "reason": f"misfit {g.mean_deg:.1f} deg, above {max_turn_deg:g}"}
            continue
        turns[sid] = w * g.mean
        q_ib[sid] = quat_canonical(quat_multiply(quat_from_rotvec(turns[sid]), q_ib[sid]))
        report[sid] = entry | {"used": True, "turned_deg": round(float(np.degrees(np.linalg.norm(turns[sid]))), 1)}
    # Each sensor's misfit with the mountings kept: a refined one's stances shift by its turn.
    misfit = dict(calib.gravity_misfit_deg)
    for sid, g in gravity.items():
        shifted = g.misfits - turns.get(sid, np.zeros(3))
        misfit[sid] = float(np.degrees(np.sqrt(np.mean(np.sum(shifted**2, axis=1)))))
        report[sid]["gravity_misfit_deg"] = round(misfit[sid], 1)
    counts = {side: len(s) for side, s in stances.items()}
    if not turns:
        return StanceResult(replace(calib, gravity_misfit_deg=misfit), report, counts)
    refined = replace(calib, q_ib=q_ib, gravity_misfit_deg=misfit)
    if still_window is not None and calib.posture:
        refined = replace(refined, posture=posture_in_window(refined, samples, still_window))
    return StanceResult(refined, report, counts)


def posture_in_window(calib: ImuCalibration, samples: Samples, window: tuple[float, float]) -> dict[str, float]:
    """The still window's posture measured with ``calib``'s mountings (``R_pose = S · M⁻¹``, ``S`` its mean)."""
    sensors = sorted(sid for sid in calib.bones if sid in samples)
    t, q = common_grid(samples, sensors)
    sel = window_samples(t, *window)
    own = calib.device_heading_quats()
    pose = {}
    for sid in sensors:
        s = quat_average(q[sid][sel])
        s = quat_multiply(own[sid], s) if sid in own else s
        pose[calib.bones[sid]] = quat_multiply(quat_multiply(calib.q_ig, s), quat_conjugate(calib.q_ib[sid]))
    return posture_angles(pose)
