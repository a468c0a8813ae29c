"""``mocapd calibrate imu --from SESSION``: calibrate a suit from the stillest standing moment of a recording.

The calibration is :func:`mocapd.core.imu_calibration.calibrate_recording`: every assigned sensor's mounting
``R_ib`` from one still window, in which the posture held is estimated from the sensors' orientations with ``pose``
as a hint (:func:`mocapd.core.imu_calibration.estimate_mounting`: ``"t-pose"``, ``"a-pose"``, ``"n-pose"``/
``"arms-down"``, or ``"auto"``: each tried, the one with which the take's knees and elbows bend the right way and
the arms never point into the body kept). A hint with which the arms swing through the chest over the take is
refused naming the one that works (the posture, not a mirrored facing, is then the cause).

The window is the one where *all* assigned sensors are jointly stillest by both tests it must pass (each sensor's
largest turn from its window mean and the std of its acceleration norm, as fractions of their limits, ``--max-turn``
and ``--max-acc-std``), searched every 0.05 s over the whole recording or over ``START:END`` seconds (exact bounds);
a window that still fails is refused with the sensor, the limit and the option that raises it named.

The heading comes from ``--facing-heading``, from a sensor axis that points forward (``--facing-from SENSOR:AXIS``),
or, with neither, from the take's steps: a knee bends about the body's left-right axis, its foot moving backwards
(:func:`mocapd.core.imu_calibration.facing_heading_from_steps`).

A facing direction with which knees or elbows bend the wrong way over the take for more than a moment
(:mod:`mocapd.core.plausibility`, measured on the calibrated sensors' bone orientations, no solve) is refused: with a
mirrored facing every bone's frame is turned by 180° about the vertical and every bend of a knee reads as a knee
bending backwards, while every later command succeeds. The refusal names the opposite sign (or heading) when that
one makes them bend the right way.

The take's motion then refines the mountings where it shows a knee or an elbow bending about one axis
(:mod:`mocapd.core.functional_calibration`), and, where its feet stand in enough stances, gravity in them refines the
trunk's and the legs' inclination (:mod:`mocapd.core.stance_calibration`; ``--no-motion`` keeps the still window's):
each sensor's hinge and gravity misfits are kept beside its mounting residual.

The result is written into the session's manifest (its ``suits``: what ``mocapd resolve`` solves with) and as a
calibration file (``<calibration_dir>/<person>.imu.json``).
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mocapd.core.functional_calibration import refine_from_recording
from mocapd.core.imu_calibration import (
    MAX_ACC_STD,
    MAX_TURN_DEG,
    POSE_HINTS,
    ImuCalibration,
    arms_through_body,
    calibrate_recording,
    calibration_hinges,
    facing_heading_from_steps,
    has_step_sensors,
    is_per_person,
    parse_assignment,
    parse_person_assignment,
    stillest_common_window,
)
from mocapd.core.knee_extension import refine_knee_extension
from mocapd.core.plausibility import HingeEvents
from mocapd.core.stance_calibration import refine_from_stances
from mocapd.errors import CalibrationError, ConfigError
from mocapd.io.mvnx import MVN_FACING_HEADING_DEG
from mocapd.io.session import MANIFEST, Session, write_json_atomic

FloatArray = NDArray[np.float64]


_NO_STEPS = "the take has no thigh and shank sensors on one leg to take the facing from its steps"
_MVN_FORWARD = "MVN's forward: where the wearer faced at MVN's calibration"


def _is_mvnx(manifest: dict[str, Any]) -> bool:
    return bool(manifest.get("imported", {}).get("from") == "mvnx")


def _mvn_facing(manifest: dict[str, Any]) -> str:
    """For an MVNX take, the facing MVN gives (:data:`~mocapd.io.mvnx.MVN_FACING_HEADING_DEG`): the end of a refusal
    that asks for one."""
    return (
        f"; for this MVNX take --facing-heading {MVN_FACING_HEADING_DEG:g} ({_MVN_FORWARD})"
        if _is_mvnx(manifest)
        else ""
    )


def calibrate_command(path: object, manifest: dict[str, Any]) -> str:
    """The ``calibrate imu --from`` command to type next for an imported session, with the facing argument it needs
    when the take's steps cannot give it."""
    if has_step_sensors(manifest.get("config", {}).get("imu", {}).get("assignment", {})):
        return f"mocapd calibrate imu --from {path}  (the facing from the take's steps; or --facing-from SENSOR:AXIS)"
    if _is_mvnx(manifest):
        heading = f"--facing-heading {MVN_FACING_HEADING_DEG:g}"
        return f"mocapd calibrate imu --from {path} {heading}  ({_MVN_FORWARD}; {_NO_STEPS})"
    return (f"mocapd calibrate imu --from {path} --facing-heading DEG  (the compass heading faced; or "
            f"--facing-from SENSOR:AXIS, a sensor axis that points forward: {_NO_STEPS})")  # fmt: skip


@dataclass(frozen=True)
class SessionCalibration:
    calibration: ImuCalibration
    window_s: tuple[float, float]
    """Start and end of the window used, seconds from the session's first sample."""
    pose: str
    facing: str = "heading"
    """Where the facing direction came from: "heading" (``--facing-heading``), "sensor" (``--facing-from``) or
    "steps" (the knees' bending in the take's steps)."""
    hinges: dict[str, HingeEvents] = field(default_factory=dict)
    """The knees and elbows over the take as this calibration measures them (wrong-way events)."""
    functional: dict[str, dict[str, object]] = field(default_factory=dict)
    """Per hinge, what the take's motion showed and whether it refined the mountings
    (:func:`mocapd.core.functional_calibration.refine_mountings`); empty with ``motion`` off."""
    knee_extension: dict[str, dict[str, object]] = field(default_factory=dict)
    """Per knee, how straight the take's knee came and whether the standing bend was raised
    (:func:`mocapd.core.knee_extension.refine_knee_extension`); empty with ``motion`` off."""
    stances: dict[str, dict[str, object]] = field(default_factory=dict)
    """Per sensor, what gravity in the take's stances showed and whether it refined the mounting
    (:func:`mocapd.core.stance_calibration.refine_from_stances`); empty with ``motion`` off or no foot sensor."""


def session_samples(session: Session) -> dict[str, tuple[FloatArray, FloatArray, FloatArray]]:
    """Per sensor: times (s, from the first sample of the session), quaternions (n, 4), accelerations (n, 3)."""
    by: dict[str, list[Any]] = defaultdict(list)
    for r in session.imu():
        if r.t_ns >= 0:
            by[r.sensor].append(r)
    if not by:
        raise CalibrationError(f"{session.path}: the session has no IMU samples")
    t0 = min(rs[0].t_ns for rs in by.values())
    out = {}
    for sid, rs in by.items():
        rs.sort(key=lambda r: r.t_ns)
        quat, acc = np.array([r.quat for r in rs]), np.array([r.acc for r in rs])
        with np.errstate(over="ignore", invalid="ignore"):
            bad = ~np.isfinite(acc).all(axis=1) | ~(np.abs(np.linalg.norm(quat, axis=1) - 1.0) < 0.1)
        if bad.any():  # written by an older import that stored a file's zero quaternions as NaN
            raise CalibrationError(
                f"{session.path}: sensor {sid}: {int(bad.sum())} of {len(rs)} samples hold no rotation or a "
                "non-finite acceleration (NaN); import the recording again"
            )
        out[sid] = (np.array([(r.t_ns - t0) / 1e9 for r in rs]), quat, acc)
    return out


def calibrate_session(
    session: Session,
    *,
    person: str,
    facing_heading_deg: float | None = None,
    facing_from: tuple[str, FloatArray] | None = None,
    world_heading: str = "subject",
    window_s: float = 1.0,
    span: tuple[float, float] | None = None,
    pose: str = "t-pose",
    assignment: dict[str, str] | None = None,
    suit: str | None = None,
    estimate_posture: bool = True,
    max_turn_deg: float = MAX_TURN_DEG,
    max_acc_std: float = MAX_ACC_STD,
    motion: bool = True,
    knee_extension: bool = False,
) -> SessionCalibration:
    """Calibrate the session's assigned sensors (see the module docstring).

    With ``motion`` the take's knees and elbows, where they bend enough about one axis, refine the still window's
    mountings (:func:`~mocapd.core.functional_calibration.refine_from_recording`: each hinge's axis as its sensors
    see it), then gravity in its stances the trunk's and legs' (:func:`~mocapd.core.stance_calibration.
    refine_from_stances`, where consistent); the plausibility checks run on the still window's calibration before.
    The knees' extension over the take (:func:`~mocapd.core.knee_extension.refine_knee_extension`) is measured, and
    with ``knee_extension`` applied.

    ``assignment`` defaults to the session's ``[imu.assignment]`` (an imported session has it); where the session's
    config has one table per person (``[imu.assignment.alice]``), ``suit``'s table (default ``person``'s). At most
    one of ``facing_heading_deg`` and ``facing_from`` (sensor id, unit axis in the sensor frame) may be given; with
    neither, the facing comes from the knees' bending in the take's steps
    (:func:`~mocapd.core.imu_calibration.facing_heading_from_steps`). ``pose`` is a hint (``"auto"``: each of
    :data:`~mocapd.core.imu_calibration.POSE_HINTS` tried, the one with which the knees and elbows bend the right
    way and the mountings stray least kept); ``estimate_posture`` False holds it exactly.

    Raises
    ------
    CalibrationError
        The calibration makes knees or elbows bend the wrong way for more than a moment (a mirrored facing
        direction): the message names the facing that works when the opposite one does.
    ConfigError
        No facing direction given and no steps to take it from.
    """
    imu_cfg = session.manifest.get("config", {}).get("imu", {})
    recorded = imu_cfg.get("assignment", {})
    if assignment is None and is_per_person(recorded):
        tables = parse_person_assignment(recorded)
        whose = suit or person
        if whose not in tables:
            raise ConfigError(
                f"{session.path}: its [imu.assignment] has one table per person, none for {whose!r}: name one of "
                f"{', '.join(tables)} with --suit"
            )
        bones = tables[whose]
    else:
        bones = parse_assignment(assignment if assignment is not None else recorded)
    if not bones:
        raise ConfigError(f"{session.path}: no sensor is assigned to a bone ([imu.assignment] of its config)")
    samples = session_samples(session)
    limits = {"max_turn_deg": max_turn_deg, "max_acc_std": max_acc_std}
    source = "sensor" if facing_from is not None else "heading"
    if facing_heading_deg is None and facing_from is None:
        try:
            start, end = stillest_common_window({s: samples[s] for s in bones if s in samples}, window_s, span,
                                                max_turn_deg=max_turn_deg, max_acc_std=max_acc_std)  # fmt: skip
        except CalibrationError as exc:
            raise CalibrationError(
                _from_a_recording(str(exc), session, samples, bones, window_s, span, pose, limits)
            ) from None
        facing_heading_deg = facing_heading_from_steps(samples, bones, (start, end))
        if facing_heading_deg is None:
            raise ConfigError(
                f"{session.path}: no facing direction: the take has no steps to take it from (it needs a thigh and a "
                "shank sensor on one leg and knees that bend); give --facing-from SENSOR:AXIS (a sensor axis that "
                "points forward while standing) or --facing-heading DEG" + _mvn_facing(session.manifest)
            )
        source = "steps"

    def calibrate(
        heading: float | None, axis: tuple[str, FloatArray] | None, hint: str = pose
    ) -> tuple[ImuCalibration, tuple[float, float]]:
        try:
            return calibrate_recording(
                person, samples, bones, facing_heading_deg=heading, facing_from=axis, world_heading=world_heading,
                window_s=window_s, span=span, pose=hint, estimate_posture=estimate_posture,
                max_turn_deg=max_turn_deg, max_acc_std=max_acc_std,
            )  # fmt: skip
        except CalibrationError as exc:
            raise CalibrationError(
                _from_a_recording(str(exc), session, samples, bones, window_s, span, hint, limits)
            ) from None

    def implausible(calib: ImuCalibration, hinges: dict[str, HingeEvents]) -> float:
        """Seconds of the take the calibration makes impossible: hinges bent the wrong way, arms through the body."""
        return _wrong_seconds(hinges) + sum(arms_through_body(samples, calib).values())

    if pose == "auto":
        tried = []
        for hint in POSE_HINTS:
            calib, window = calibrate(facing_heading_deg, facing_from, hint)
            hinges = calibration_hinges(samples, calib)
            rms = float(np.sqrt(np.mean(np.square(list(calib.residual_deg.values()) or [0.0]))))
            tried.append((implausible(calib, hinges), rms, hint, calib, window, hinges))
        _, _, pose, calib, window, hinges = min(tried, key=lambda x: (round(x[0], 1), x[1]))
    else:
        calib, window = calibrate(facing_heading_deg, facing_from)
        hinges = calibration_hinges(samples, calib)
        through = arms_through_body(samples, calib)
        if sum(through.values()) > ARMS_THROUGH_BODY_S:  # the arms held otherwise than the hint says
            bad = implausible(calib, hinges)
            for hint in POSE_HINTS:
                other, _ = calibrate(facing_heading_deg, facing_from, hint)
                if hint != pose and implausible(other, calibration_hinges(samples, other)) < 0.25 * bad:
                    raise CalibrationError(_wrong_posture(through, pose, hint))
    if _wrong_way(hinges):
        flipped_heading = None if facing_heading_deg is None else (facing_heading_deg + 180.0) % 360.0
        flipped_axis = None if facing_from is None else (facing_from[0], -np.asarray(facing_from[1]))
        other, _ = calibrate(flipped_heading, flipped_axis, pose)
        works = not _wrong_way(calibration_hinges(samples, other))
        posture = None
        if not works:  # the facing is not the cause: is the posture? (arms held otherwise than the hint says)
            posture = next((hint for hint in POSE_HINTS if hint != pose and not _wrong_way(
                calibration_hinges(samples, calibrate(facing_heading_deg, facing_from, hint)[0]))), None)  # fmt: skip
        raise CalibrationError(_refusal(hinges, source, facing_from, facing_heading_deg, works, posture, pose))
    functional: dict[str, dict[str, object]] = {}
    extension: dict[str, dict[str, object]] = {}
    stances: dict[str, dict[str, object]] = {}
    if motion:
        refined = refine_from_recording(calib, samples, window)
        calib, functional = refined.calibration, refined.hinges
        extended = refine_knee_extension(calib, samples, window, apply=knee_extension)
        calib, extension = extended.calibration, extended.knees
        by_stances = refine_from_stances(calib, samples, window)
        calib, stances = by_stances.calibration, by_stances.sensors
    return SessionCalibration(calib, window, pose, source, hinges, functional, extension, stances)


ARMS_THROUGH_BODY_S = 1.0
"""Seconds of a take in which the calibrated upper arms may point into the body before the posture hint is doubted."""


def _wrong_posture(through: dict[str, float], pose: str, works: str) -> str:
    arms = "; ".join(f"{k.replace('_', ' ')} {v:.1f} s" for k, v in through.items() if v > 0)
    return (
        f"with --pose {pose} the upper arms point into the body ({arms}): the posture held in the calibration window "
        f"was not {_POSTURE_TEXT.get(pose, pose)}; --pose {works} makes them move as arms do: calibrate again with it "
        "(or --pose auto)"
    )


def _wrong_seconds(hinges: dict[str, HingeEvents]) -> float:
    return sum(h.seconds for h in hinges.values())


def _wrong_way(hinges: dict[str, HingeEvents]) -> bool:
    return any(h.events for h in hinges.values())


def _axis_text(axis: FloatArray) -> str:
    i = int(np.argmax(np.abs(axis)))
    return f"{'+' if axis[i] > 0 else '-'}{'xyz'[i]}"


def _refusal(
    hinges: dict[str, HingeEvents],
    source: str,
    facing_from: tuple[str, FloatArray] | None,
    heading: float | None,
    flipped_works: bool,
    posture: str | None = None,
    pose: str = "t-pose",
) -> str:
    """The message refusing a facing direction with which hinges bend the wrong way, naming the one that works."""
    bent = [f"{name.replace('_', ' ')} {h.seconds:.1f} s (up to {h.worst_deg:.0f}°, first at {h.first_s:.1f} s)"
            for name, h in hinges.items() if h.events]  # fmt: skip
    if facing_from is not None:
        given = f"--facing-from {facing_from[0]}:{_axis_text(facing_from[1])}"
        other = f"--facing-from {facing_from[0]}:{_axis_text(-np.asarray(facing_from[1]))}"
    else:
        assert heading is not None
        given = "the facing found from the take's steps" if source == "steps" else f"--facing-heading {heading:g}"
        other = f"--facing-heading {(heading + 180.0) % 360.0:.0f}"
    kinds = " and ".join(sorted({f"{name.split('_')[1]}s" for name, h in hinges.items() if h.events}, reverse=True))
    if posture is not None:
        return (
            f"with --pose {pose} the {kinds} bend the wrong way ({'; '.join(bent)}): the posture held in the "
            f"calibration window was not {_POSTURE_TEXT.get(pose, pose)}; --pose {posture} bends them the right way: "
            f"calibrate again with it (or --pose auto)"
        )
    head = f"with {given} the {kinds} bend the wrong way ({'; '.join(bent)}): the facing direction is mirrored"
    if flipped_works:
        return f"{head}; {other} bends them the right way: calibrate again with it"
    return (
        f"{head}, and {other} does not make them bend the right way either, nor does another --pose: check the "
        "sensor assignment (a sensor on another bone, left and right swapped) or leave out "
        "--facing-from/--facing-heading to take the facing from the take's steps"
    )


_POSTURE_TEXT = {"t-pose": "a T-pose", "a-pose": "an A-pose", "n-pose": "standing, arms down",
                 "arms-down": "standing, arms down", "auto": "standing"}  # fmt: skip


def _from_a_recording(message: str, session: Session, samples: dict[str, Any], bones: dict[str, str],
                      window_s: float, span: tuple[float, float] | None, pose: str,
                      limits: dict[str, float]) -> str:  # fmt: skip
    """A still-window refusal as advice for a recording: it cannot be repeated, but another moment of it can be
    chosen (``--window START:END``); and it names the posture that was assumed, not always the T-pose."""
    if "stand still and repeat" not in message:
        return message
    limit = message[message.index("raise the limit:") :] if "raise the limit:" in message else ""
    try:
        start, end = stillest_common_window({s: samples[s] for s in bones if s in samples}, window_s, span, **limits)
        where = f"in the stillest {window_s:g} s of the recording ({start:.1f}-{end:.1f} s)"
    except CalibrationError:
        where = "in the stillest window of the recording"
    posture = _POSTURE_TEXT.get(pose, pose)
    head = message[: message.index("; stand still and repeat")].replace("during the calibration", where)
    flag = limit.removeprefix("raise the limit: ")
    return (
        f"{head}: choose a moment when the subject stands still ({posture}): `mocapd calibrate imu --from "
        f"{session.path} --window START:END` (seconds of the session; `mocapd session {session.path}` shows its "
        f"length)"
        + (
            f"; or, if the subject stood still there (a noisier sensor), `mocapd calibrate imu --from "
            f"{session.path} {flag}`"
            if flag
            else ""
        )
    )


def store_in_session(session: Session, suit: str, calib: ImuCalibration, info: dict[str, Any]) -> None:
    """Put the calibration into the session's manifest as suit ``suit`` (replacing one of that name)."""
    m = dict(session.manifest)
    suits = [s for s in m.get("suits", []) if s.get("id") != suit]
    suits.append({"id": suit, "sensors": sorted(calib.bones), "calibration": calib.to_json_dict()})
    m["suits"] = suits
    m.setdefault("calibrations", {})[suit] = info
    write_json_atomic(session.path / MANIFEST, m)
    session.manifest = m
