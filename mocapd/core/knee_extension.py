"""Knee extension from motion: a take's straightest knee measures the standing knee bend the still window shrank (pure).

The still window gives a knee's bend from its two sensors' half difference of sagittal leans
(:func:`mocapd.core.imu_calibration.knee_flexion`), but each sensor's own mounting error about the knee axis is as
large as the bend (8° per axis against 0-10° of bend), so the estimate is shrunk toward straight: about a third of
the bend held is found, the rest stays in the thigh's and shank's mountings, and every later knee angle reads that
much straighter (the simulated relaxed postures: knee bias −3.7°). The knee's hinge axis from motion
(:mod:`mocapd.core.functional_calibration`) cannot see it: it is the turn about the axis itself.

Motion can: a knee does not bend backwards. With the calibration's mountings the knee's flexion over the take
(:func:`mocapd.core.plausibility.bone_hinge_angles`, no solve) should not fall below :data:`FLOOR_DEG`; where its
straightest stretch (its :data:`PERCENTILE` th percentile) does by more than :data:`MIN_TURN_DEG`, the standing bend
was underestimated by that much, and the thigh's and shank's mountings turn by half of it each about the knee's
axis, the thigh forward and the shank back (the still window's model: the ankle stays under the hip, so the legs'
lean, :mod:`mocapd.core.stance_calibration`, does not change). A walk straightens the knees to 0-3° at every heel
strike, and a person standing straightens them; a take whose knees stay bent (a crouched walk, a bow) says nothing
and changes nothing: the correction is one-sided. A shortfall above :data:`MAX_TURN_DEG` is not a standing bend (a
sensor slipped or on another bone): kept and reported.

**Measured, not applied** (:data:`APPLY`): on the simulated walkers, whose knees straighten to 0-3°, it takes the
knee bias away; but a real person may walk with a knee a few degrees hyperextended, and the real MTw walk's right knee
does (Plug-in-Gait: −2° standing, −3° at its straightest): applied, its knee was raised 5° and the walk's knee RMSE
went 4.7 → 6.5° (docs/imu.md). Each knee's straightest flexion and shortfall is measured and reported
(``knee_extension`` in what ``calibrate imu --from`` prints), for a suit owner to read: a knee reading several
degrees backwards at its straightest is a standing bend the still window missed, or a knee that hyperextends.

All quaternions are (w, x, y, z), Hamilton, unit norm; a leg bone's flexion axis is its frame's x.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from mocapd.core.imu_calibration import ImuCalibration, Samples, common_grid
from mocapd.core.plausibility import HINGES, bone_hinge_angles
from mocapd.core.rotations import quat_canonical, quat_conjugate, quat_from_rotvec, quat_multiply
from mocapd.core.stance_calibration import posture_in_window

FloatArray = NDArray[np.float64]

FLOOR_DEG = 0.0
"""A knee's flexion is taken not to fall below this (degrees): a knee straightens, it does not bend backwards; most
walkers straighten to 0-3°, but some hyperextend a few degrees (why the correction is not applied, :data:`APPLY`)."""
PERCENTILE = 2.0
"""The straightest stretch of a take is its knee flexion's this percentile: a walk straightens the knees for 5-10 %
of its frames, and a moment of soft-tissue jolt at heel strike stays below it."""
MIN_TURN_DEG = 1.0
"""A shortfall below this (degrees) is left: orientation noise."""
MAX_TURN_DEG = 15.0
"""A shortfall above this (degrees) is not a standing bend the still window missed (a knee bent 0-10° standing, its
estimate shrunk toward straight): a sensor slipped or sits on another bone; kept and reported."""
APPLY = False
"""Whether the knees' shortfall turns their mountings (else it is measured and reported only): a floor at 0° is
wrong for a knee that hyperextends (the real MTw walk's right knee, docs/imu.md)."""
KNEES = {name: bones for name, bones in HINGES.items() if name.endswith("knee")}
"""Knee name -> (thigh, shank)."""


@dataclass(frozen=True, slots=True)
class ExtensionResult:
    """:func:`refine_knee_extension`'s answer: the refined calibration and what each knee showed."""

    calibration: ImuCalibration
    knees: dict[str, dict[str, object]]
    """Per knee: ``straightest_deg`` (its flexion's :data:`PERCENTILE` th percentile with the mountings before),
    ``shortfall_deg`` (how far that is below :data:`FLOOR_DEG`), ``used``, and why not (``reason``) or how far the
    bend was raised (``raised_deg``, split half to each sensor)."""


def knee_shortfall(flexion_deg: FloatArray, floor_deg: float = FLOOR_DEG) -> tuple[float, float]:
    """A knee's straightest flexion over a take and how far it falls short of ``floor_deg`` (degrees, ≥ 0).

    Parameters
    ----------
    flexion_deg : array, shape (n,)
        The knee's flexion (degrees, positive bent), NaN where unknown.
    """
    a = np.asarray(flexion_deg, dtype=np.float64)
    a = a[np.isfinite(a)]
    if a.size == 0:
        return float("nan"), 0.0
    straightest = float(np.percentile(a, PERCENTILE))
    return straightest, max(0.0, floor_deg - straightest)


def refine_knee_extension(
    calib: ImuCalibration,
    samples: Samples,
    still_window: tuple[float, float] | None = None,
    *,
    min_turn_deg: float = MIN_TURN_DEG,
    max_turn_deg: float = MAX_TURN_DEG,
    apply: bool = APPLY,
) -> ExtensionResult:
    """Raise each knee's standing bend where the take's knee bends backwards with the calibration's mountings.

    A knee with both sensors whose straightest flexion (:func:`knee_shortfall`) falls short of :data:`FLOOR_DEG` by
    ``min_turn_deg`` to ``max_turn_deg`` has its thigh's mounting turned by half the shortfall about the bone's x axis
    one way and its shank's the other (``M' = exp(±δ/2 · x) · M``), which raises every flexion of the take by the
    shortfall and leaves the leg's lean (the sum of the two tilts) and the hinge axis as they were, when ``apply``;
    the posture found in ``still_window`` (s) is then measured again. Without ``apply`` (the default,
    :data:`APPLY`) every knee's shortfall is measured and reported, and the mountings are kept.
    """
    by_bone = {b: sid for sid, b in calib.bones.items() if sid in samples}
    worn = {name: (by_bone[t], by_bone[s]) for name, (t, s) in KNEES.items() if t in by_bone and s in by_bone}
    if not worn:
        return ExtensionResult(calib, {})
    sensors = sorted({sid for pair in worn.values() for sid in pair})
    _, q = common_grid(samples, sensors)
    own = calib.device_heading_quats()

    def world(sid: str) -> FloatArray:
        s = quat_multiply(own[sid], q[sid]) if sid in own else q[sid]
        return np.asarray(quat_multiply(calib.q_ig, s), dtype=np.float64)

    orientations = {calib.bones[sid]: quat_multiply(world(sid), quat_conjugate(calib.q_ib[sid])) for sid in sensors}
    flexion = bone_hinge_angles(orientations)
    q_ib = dict(calib.q_ib)
    report: dict[str, dict[str, object]] = {}
    for name, (thigh, shank) in worn.items():
        straightest, short = knee_shortfall(flexion[name])
        entry: dict[str, object] = {"straightest_deg": round(straightest, 1), "shortfall_deg": round(short, 1)}
        if short < min_turn_deg:
            report[name] = entry | {"used": False, "reason": f"straightens to {straightest:.1f} deg: not backwards"}
            continue
        if short > max_turn_deg:
            report[name] = entry | {"used": False, "reason": f"bends {short:.1f} deg backwards, above "
                                    f"{max_turn_deg:g}: check the thigh and shank sensors"}  # fmt: skip
            continue
        if not apply:
            report[name] = entry | {"used": False, "reason": "measured, not applied: a knee may hyperextend"}
            continue
        # The thigh turned by -δ/2 about its x in the world (its knee forward) and the shank by +δ/2 (its ankle
        # back): R_gb' = R_gb · exp(∓δ/2 x), i.e. M' = exp(±δ/2 x) · M.
        half = np.radians(short) / 2.0
        for sid, sign in ((thigh, 1.0), (shank, -1.0)):
            q_ib[sid] = quat_canonical(quat_multiply(quat_from_rotvec(np.array([sign * half, 0.0, 0.0])), q_ib[sid]))
        report[name] = entry | {"used": True, "raised_deg": round(short, 1)}
    if not any(r["used"] for r in report.values()):
        return ExtensionResult(calib, report)
    refined = replace(calib, q_ib=q_ib)
    if still_window is not None and calib.posture:
        refined = replace(refined, posture=posture_in_window(refined, samples, still_window))
    return ExtensionResult(refined, report)
