"""IMU-to-bone calibration from a T-pose: mounting rotations R_ib and heading alignment R_ig (pure).

Convention (seed 003, Eq. 8): the world orientation of a bone is ``R_gb = R_ig · R_i · R_ib⁻¹`` where

- ``R_i`` is the IMU's measured orientation (sensor frame → the device's global frame, ENU for Xsens),
- ``R_ib`` the mounting rotation of the IMU on its bone (sensor frame → bone frame), constant,
- ``R_ig`` the heading alignment (device global frame → mocapd world: right-handed, +Y up, metres).

The device frame ENU (x east, y north, z up) maps to world axes by :data:`ENU_TO_WORLD`: world +Y is up,
+Z is north and +X west. During the T-pose the subject faces compass heading ``h`` (degrees clockwise from
north); rotating the world about +Y by ``h`` makes the subject face +Z, the rest pose's facing direction, so
``R_ig = Ry(h) · ENU_TO_WORLD``. (With ``world_heading="north"`` R_ig stays ``ENU_TO_WORLD`` and the rest
pose is turned by ``Ry(-h)`` instead; R_ib is the same either way.) In the T-pose every bone's world
orientation is its rest orientation ``R_rest`` (identity for a T-pose rest skeleton), hence
``R_ib = R_rest⁻¹ · R_ig_T · R_i`` with ``R_ig_T`` the T-pose-facing alignment.

``R_i`` is the average over the stillest window of the recording (stillest by both tests: turn and acceleration,
each as a fraction of its limit); windows where a sensor turns more than ``max_spread_deg`` or its acceleration norm
varies more than ``max_acc_std`` are rejected as motion.

The calibration posture need not be the T-pose: ``R_rest`` is a hint (:func:`rest_orientations`: T-, A- or N-pose)
that :func:`estimate_mounting` refines with the sensors' orientations, splitting what the hint leaves over between
the bone's posture and the sensor's mounting by two priors (a case strapped along its segment; a real person's
still posture), so that a relaxed A-pose with bent elbows calibrates as what it is (issue 42).

Sensors without a shared heading reference (SlimeVR trackers: each 6-axis tracker's yaw is wherever its gyroscope
started) get a heading of their own, ``δ``, a rotation about the device's up axis applied to every sample before
Eq. 8 (``R_i ← Rz(δ) · R_i``, what SlimeVR calls a yaw reset). One T-pose cannot tell a sensor's heading from its
mounting (4 unknowns, 3 equations), so ``δ`` assumes the mounting's own yaw: with it the T-pose orientation
``R_ig_T · Rz(δ) · R_i`` turns about world up by ``mount_yaw`` (0 for a tracker on the front or back of a body
segment, its face forward or backward; +90° for one on the subject's left side, −90° on the right). A wrong
mounting yaw shows as a heading error of the same size, which the cameras' heading correction can take out.

All quaternions are (w, x, y, z), Hamilton, unit norm.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from mocapd.core.imu import (
    IMU_SET_6,
    IMU_SET_13,
    IMU_SET_LOWER,
    IMU_SET_LOWER_OPTIONAL,
    measured_bone_orientation,
)
from mocapd.core.names import check_name
from mocapd.core.plausibility import (
    HingeEvents,
    PlausibilityOptions,
    check_bone_orientations,
    facing_from_knees,
)
from mocapd.core.rotations import (
    matrix_from_quat,
    quat_angle,
    quat_canonical,
    quat_conjugate,
    quat_from_matrix,
    quat_from_rotvec,
    quat_multiply,
    rotvec_from_quat,
)
from mocapd.core.skeleton import BONE_NAMES
from mocapd.errors import CalibrationError, ConfigError, InputError

FloatArray = NDArray[np.float64]

# The 21 bone names (DESIGN.md order) and the 13/6-sensor sets, re-exported for the assignment checks.
__all__ = ["BONE_NAMES", "IMU_SET_6", "IMU_SET_13", "IMU_SET_LOWER"]

#: Rotation of ENU device coordinates into world coordinates (x west, y up, z north), as a matrix.
ENU_TO_WORLD = np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])


#: Rotations taking NED / NWU device-frame coordinates to ENU (rows: ENU axes in the source frame).
_TO_ENU = {
    "ENU": np.eye(3),
    "NED": np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]),
    "NWU": np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
}


def quat_to_enu(q: FloatArray, frame: str) -> FloatArray:
    """Re-express device orientations given in ``frame`` ("ENU", "NED" or "NWU") in ENU; shape (..., 4).

    Raises
    ------
    InputError
        For an unknown frame name.
    """
    if frame not in _TO_ENU:
        raise InputError(f"device frame must be ENU, NED or NWU, got {frame!r}")
    if frame == "ENU":
        return np.asarray(q, dtype=np.float64)
    return quat_multiply(quat_from_matrix(_TO_ENU[frame]), np.asarray(q, dtype=np.float64))


_HEX = frozenset("0123456789ABCDEF")


def is_sensor_id(sid: str) -> bool:
    """Whether an upper-case string is a sensor id: an Xsens device id (8 hex digits, as printed on the case) or a
    SlimeVR tracker's sensor, ``"<MAC>/<index>"`` (``"AA:BB:CC:DD:EE:FF/0"``, index 0..254)."""
    if len(sid) == 8:
        return all(c in _HEX for c in sid)
    mac, slash, index = sid.partition("/")
    octets = mac.split(":")
    return (
        slash == "/"
        and len(octets) == 6
        and all(len(o) == 2 and all(c in _HEX for c in o) for o in octets)
        and index.isdigit()
        and len(index) <= 3
        and int(index) < 255
    )


def parse_assignment(mapping: Mapping[str, str], *, imu_set: str | None = None) -> dict[str, str]:
    """Validate a sensor → bone assignment (``{"00B421E6": "Hips", "AA:BB:CC:DD:EE:FF/0": "Head", ...}``).

    Parameters
    ----------
    mapping : mapping of str to str
        Sensor id (:func:`is_sensor_id`: 8 hex digits as printed on an Xsens case, or a SlimeVR
        ``"<MAC>/<sensor index>"``; case-insensitive) to bone name.
    imu_set : {"13", "6", "lower", None}
        If given, the assigned bones must be exactly that set ("lower": pelvis, thighs, shanks and feet, plus at
        most one trunk sensor on Spine..Spine3).

    Returns
    -------
    dict
        Upper-case sensor ids to bone names.

    Raises
    ------
    ConfigError
        Unknown bone, malformed id, a bone used twice, or a set mismatch (the message lists what is wrong).
    """
    out: dict[str, str] = {}
    for sensor, bone in mapping.items():
        sid = sensor.upper()
        if not is_sensor_id(sid):
            raise ConfigError(
                f"imu assignment: sensor id {sensor!r} is neither 8 hex digits (Xsens) nor a SlimeVR "
                "'<MAC>/<sensor index>' such as 'AA:BB:CC:DD:EE:FF/0'"
            )
        if bone not in BONE_NAMES:
            raise ConfigError(f"imu assignment: {sensor} -> {bone!r} is not a bone; use one of {BONE_NAMES}")
        if bone in out.values():
            raise ConfigError(f"imu assignment: bone {bone} has more than one sensor")
        out[sid] = bone
    if imu_set is not None:
        expected = {"13": IMU_SET_13, "6": IMU_SET_6, "lower": IMU_SET_LOWER}.get(imu_set)
        if expected is None:
            raise ConfigError(f"imu assignment: imu_set must be '13', '6' or 'lower', got {imu_set!r}")
        missing = sorted(set(expected) - set(out.values()))
        extra = sorted(set(out.values()) - set(expected))
        if imu_set == "lower":
            trunk = [b for b in extra if b in IMU_SET_LOWER_OPTIONAL]
            extra = [b for b in extra if b not in IMU_SET_LOWER_OPTIONAL] + trunk[1:]
        if missing or extra:
            raise ConfigError(f"imu assignment for the {imu_set}-sensor set: missing {missing}, unexpected {extra}")
    return out


MAX_SUIT_SENSORS = 64
"""Sensors one person's table (or the flat assignment) assigns at most."""
MAX_PERSONS = 16
"""Persons one per-person assignment names at most."""


def is_per_person(mapping: Mapping[str, object]) -> bool:
    """Whether an assignment is written per person (``[imu.assignment.alice]``: a table per person) rather than
    flat (``"00B421E6" = "Hips"``, one suit)."""
    return any(isinstance(v, Mapping) for v in mapping.values())


def parse_person_assignment(mapping: Mapping[str, object], *, imu_set: str | None = None) -> dict[str, dict[str, str]]:
    """Validate a per-person assignment, ``{"alice": {"00B42000": "Hips", ...}, "bob": {...}}``: one suit each.

    Each person's table is checked as one suit by :func:`parse_assignment` (with ``imu_set`` when given); person
    names follow :data:`~mocapd.core.names.NAME_RULE` (a person names a calibration file, as ``--person`` does).

    Raises
    ------
    ConfigError
        A flat entry beside the tables (naming it), a bad person name, a bad table, or a sensor in two persons'
        tables (naming both).
    """
    flat = [k for k, v in mapping.items() if not isinstance(v, Mapping)]
    if flat:
        raise ConfigError(
            f"imu assignment: {flat[0]!r} = {mapping[flat[0]]!r} is a sensor entry beside per-person tables "
            f"({', '.join(k for k in mapping if k not in flat)}): write every sensor in its person's table"
        )
    if len(mapping) > MAX_PERSONS:
        raise ConfigError(f"imu assignment: {len(mapping)} persons; at most {MAX_PERSONS}")
    out: dict[str, dict[str, str]] = {}
    owner: dict[str, str] = {}
    for person, table in mapping.items():
        check_name(person, "imu assignment: person", ConfigError)
        assert isinstance(table, Mapping)
        if len(table) > MAX_SUIT_SENSORS:
            raise ConfigError(f"imu assignment: {person}: {len(table)} sensors; at most {MAX_SUIT_SENSORS}")
        if not all(isinstance(b, str) for b in table.values()):
            raise ConfigError(f"imu assignment: {person}: each value must be a bone name")
        try:
            out[person] = parse_assignment(table, imu_set=imu_set)
        except ConfigError as exc:
            raise ConfigError(f"imu assignment: {person}'s table{str(exc).removeprefix('imu assignment')}") from None
        for sid in out[person]:
            if sid in owner:
                raise ConfigError(f"imu assignment: sensor {sid} is in the tables of both {owner[sid]} and {person}")
            owner[sid] = person
    return out


def quat_average(q: FloatArray) -> FloatArray:
    """Average orientation of quaternions ``(n, 4)`` (sign-invariant; largest eigenvector of Σ q qᵀ)."""
    q = np.asarray(q, dtype=np.float64)
    if q.ndim != 2 or q.shape[1] != 4 or len(q) == 0:
        raise InputError(f"quat_average needs shape (n, 4) with n >= 1, got {q.shape}")
    _, vecs = np.linalg.eigh(q.T @ q)
    return quat_canonical(vecs[:, -1])


def yaw_quat(angle_rad: float) -> FloatArray:
    """Rotation about world +Y (up) by ``angle_rad``, shape (4,)."""
    return quat_from_rotvec(np.array([0.0, angle_rad, 0.0]))


def heading_alignment(facing_heading_deg: float, *, world_heading: str = "subject") -> FloatArray:
    """R_ig (device ENU → world) as a quaternion, shape (4,).

    ``world_heading="subject"``: world +Z is where the subject faced in the T-pose.
    ``world_heading="north"``: world +Z is magnetic north (the T-pose heading only enters R_ib).
    """
    base = quat_from_matrix(ENU_TO_WORLD)
    if world_heading == "north":
        return base
    if world_heading != "subject":
        raise ConfigError(f"world_heading must be 'subject' or 'north', got {world_heading!r}")
    return quat_canonical(quat_multiply(yaw_quat(np.radians(facing_heading_deg)), base))


MAX_TURN_DEG = 4.0
"""Default limit of a still window's turn (the largest angle of a sample from the window's mean, degrees):
above the orientation noise of standing still with Xsens MTx/MTw/Awinda and SlimeVR trackers (docs/imu.md,
"Still windows"), below a slow arm movement."""
MAX_ACC_STD = 0.5
"""Default limit of a still window's acceleration: the std of the acceleration norm (m/s²)."""


@dataclass(frozen=True, slots=True)
class StillWindow:
    """Result of :func:`stillest_window` for one sensor."""

    start: int
    stop: int
    mean: FloatArray  # (4,)
    spread_deg: float  # largest angle of a window sample from the window mean
    acc_std: float  # std of the acceleration norm in the window (m/s²), NaN without acceleration


def stillest_window(
    quat: FloatArray,
    acc: FloatArray | None,
    window: int,
    *,
    max_spread_deg: float = MAX_TURN_DEG,
    max_acc_std: float = MAX_ACC_STD,
    sensor: str = "imu",
) -> StillWindow:
    """Find the window of ``window`` samples that is stillest by both tests it must pass (turn and acceleration,
    each relative to its limit) and accept it if it passes them.

    Parameters
    ----------
    quat : array, shape (n, 4)
    acc : array, shape (n, 3), or None
    window : int
        Window length in samples (e.g. 1 s worth).

    Raises
    ------
    CalibrationError
        Fewer than ``window`` samples, or the stillest window still moves (names the sensor, the numbers, the
        limit and the option that sets it).
    """
    quat = np.asarray(quat, dtype=np.float64)
    n = len(quat)
    if n < window or window < 2:
        raise CalibrationError(f"{sensor}: {n} samples, need at least {max(window, 2)} for the calibration window")
    best: tuple[float, StillWindow] | None = None
    step = max(1, window // 4)
    for start in range(0, n - window + 1, step):
        chunk = quat[start : start + window]
        mean = quat_average(chunk)
        spread = float(np.degrees(np.max(quat_angle(chunk, mean))))
        acc_std = float(np.std(np.linalg.norm(acc[start : start + window], axis=1))) if acc is not None else np.nan
        score = max(spread / max_spread_deg, 0.0 if np.isnan(acc_std) else acc_std / max_acc_std)
        if best is None or score < best[0]:
            best = (score, StillWindow(start, start + window, mean, spread, acc_std))
    assert best is not None
    still = best[1]
    if still.spread_deg > max_spread_deg:
        raise CalibrationError(
            f"{sensor} moved during the calibration: its stillest {window}-sample window turns "
            f"{still.spread_deg:.1f}° (limit {max_spread_deg:g}°, --max-turn); stand still and repeat, or, if "
            f"the subject stood still (a noisier sensor), raise the limit: --max-turn {_above(still.spread_deg)}"
        )
    if not np.isnan(still.acc_std) and still.acc_std > max_acc_std:
        raise CalibrationError(
            f"{sensor} accelerated during the calibration: |acc| std {still.acc_std:.2f} m/s² "
            f"(limit {max_acc_std:g}, --max-acc-std); stand still and repeat, or, if the subject stood still (a "
            f"noisier sensor), raise the limit: --max-acc-std {_above(still.acc_std)}"
        )
    return still


def _above(value: float) -> str:
    """A limit just above ``value``, as typed (one decimal, rounded up)."""
    return f"{np.ceil(value * 10.0 + 1e-9) / 10.0:g}"


def mounting_rotation(q_i: FloatArray, q_ig_tpose: FloatArray, q_rest: FloatArray | None = None) -> FloatArray:
    """R_ib = R_rest⁻¹ · R_ig · R_i as a quaternion, shape (4,) (see the module docstring)."""
    rest = np.array([1.0, 0.0, 0.0, 0.0]) if q_rest is None else np.asarray(q_rest, dtype=np.float64)
    return quat_canonical(quat_multiply(quat_conjugate(rest), quat_multiply(q_ig_tpose, q_i)))


def bone_orientation(q_ig: FloatArray, q_i: FloatArray, q_ib: FloatArray) -> FloatArray:
    """R_gb = R_ig · R_i · R_ib⁻¹ (seed 003 Eq. 8); see :func:`mocapd.core.imu.measured_bone_orientation`."""
    return measured_bone_orientation(q_ig, q_i, q_ib)


@dataclass(frozen=True, slots=True)
class ImuCalibration:
    """Calibration of one person: R_ig and, per sensor, its bone and R_ib."""

    person: str
    facing_heading_deg: float
    world_heading: str
    q_ig: FloatArray  # (4,)
    bones: dict[str, str]  # sensor id -> bone
    q_ib: dict[str, FloatArray]  # sensor id -> (4,)
    spread_deg: dict[str, float]  # sensor id -> stillness of the window used
    device_heading_deg: dict[str, float] = field(default_factory=dict)
    """Sensor id -> δ (degrees) for sensors with a heading of their own (see the module docstring)."""
    residual_deg: dict[str, float] = field(default_factory=dict)
    """Sensor id -> its mounting's angle from the nearest case-along-the-segment mounting (degrees,
    :func:`estimate_mounting`): a large one is a sensor strapped askew, or a posture far from the hint."""
    posture: dict[str, float] = field(default_factory=dict)
    """What the calibration posture held (:func:`posture_angles`, degrees), with the hint under ``"hint"`` absent."""
    pose_hint: str = "t-pose"
    hinge_misfit_deg: dict[str, float] = field(default_factory=dict)
    """Sensor id -> how far its bone's hinge (knee, elbow) strays from one axis over the motion that refined its
    mounting (degrees, :mod:`mocapd.core.functional_calibration`); absent for a mounting from the still window only."""
    gravity_misfit_deg: dict[str, float] = field(default_factory=dict)
    """Sensor id -> how far gravity in a walk's stances strays from what its mounting says (RMS over the stances,
    degrees, :mod:`mocapd.core.stance_calibration`); absent for a sensor without stances (no walk, arms, feet)."""

    def summary(self) -> dict[str, object]:
        """What /status and the console say of this calibration: the posture it found (its hint and angles,
        degrees), and per sensor its bone, stillness and residuals (degrees: ``mount_residual_deg`` the gravity
        misfit, the mounting's angle from a case along its segment; ``hinge_misfit_deg`` where motion refined it),
        with the sensor of the largest residual under ``worst``."""
        sensors: dict[str, dict[str, object]] = {}
        for sid in sorted(self.q_ib):
            entry: dict[str, object] = {"bone": self.bones[sid]}
            spread = self.spread_deg.get(sid, float("nan"))
            entry["still_spread_deg"] = round(spread, 2) if np.isfinite(spread) else None
            if sid in self.residual_deg:
                entry["mount_residual_deg"] = round(self.residual_deg[sid], 1)
            if sid in self.hinge_misfit_deg:
                entry["hinge_misfit_deg"] = round(self.hinge_misfit_deg[sid], 1)
            if sid in self.gravity_misfit_deg:
                entry["gravity_misfit_deg"] = round(self.gravity_misfit_deg[sid], 1)
            sensors[sid] = entry
        residual = self.residuals()
        worst = max(residual, key=lambda k: residual[k], default=None)
        return {
            "pose_hint": self.pose_hint,
            "posture_deg": dict(self.posture),
            "functional": bool(self.hinge_misfit_deg),
            "stances": bool(self.gravity_misfit_deg),
            "sensors": sensors,
            "worst": None if worst is None else {"sensor": worst, "bone": self.bones[worst],
                                                 "residual_deg": round(residual[worst], 1)},
        }  # fmt: skip

    def residuals(self) -> dict[str, float]:
        """Sensor id -> its largest residual (degrees): mounting, hinge misfit or gravity misfit, for the sensors
        that have one."""
        kinds = (self.residual_deg, self.hinge_misfit_deg, self.gravity_misfit_deg)
        return {sid: max(k.get(sid, 0.0) for k in kinds) for sid in self.q_ib if any(sid in k for k in kinds)}

    def device_heading_quats(self) -> dict[str, FloatArray]:
        """Sensor id -> ``Rz(δ)`` (4,), to apply to that sensor's device-frame samples before Eq. 8."""
        return {sid: device_heading_quat(d) for sid, d in self.device_heading_deg.items()}

    def to_json_dict(self) -> dict[str, object]:
        """Plain data for the calibration file (version 1)."""
        return {
            "format": "mocapd-imu-calibration",
            "version": 1,
            "person": self.person,
            "convention": "R_gb = R_ig * R_i * R_ib^-1; quaternions (w, x, y, z); world +Y up",
            "facing_heading_deg": self.facing_heading_deg,
            "world_heading": self.world_heading,
            "R_ig": [float(v) for v in self.q_ig],
            "posture": {"hint": self.pose_hint, "angles_deg": dict(self.posture)},
            "sensors": {
                sid: {
                    "bone": self.bones[sid],
                    "R_ib": [float(v) for v in q],
                    "still_spread_deg": self.spread_deg[sid],
                    **({"mount_residual_deg": round(self.residual_deg[sid], 2)} if sid in self.residual_deg else {}),
                    **(
                        {"hinge_misfit_deg": round(self.hinge_misfit_deg[sid], 2)}
                        if sid in self.hinge_misfit_deg
                        else {}
                    ),
                    **(
                        {"gravity_misfit_deg": round(self.gravity_misfit_deg[sid], 2)}
                        if sid in self.gravity_misfit_deg
                        else {}
                    ),
                    **({"device_heading_deg": self.device_heading_deg[sid]} if sid in self.device_heading_deg else {}),
                }
                for sid, q in self.q_ib.items()
            },
        }

    @staticmethod
    def from_json_dict(data: Mapping[str, object]) -> ImuCalibration:
        """Inverse of :meth:`to_json_dict`. Raises CalibrationError on a wrong format or version."""
        if not isinstance(data, Mapping):
            raise CalibrationError(f"not a version-1 mocapd IMU calibration file (a {type(data).__name__})")
        if data.get("format") != "mocapd-imu-calibration" or data.get("version") != 1:
            raise CalibrationError("not a version-1 mocapd IMU calibration file")
        try:
            sensors = data["sensors"]
            assert isinstance(sensors, dict)
            q_ig = _unit_quat(data["R_ig"], "R_ig")
            posture = data.get("posture", {})
            assert isinstance(posture, dict)
            return ImuCalibration(
                person=str(data["person"]),
                facing_heading_deg=float(data["facing_heading_deg"]),  # type: ignore[arg-type]
                world_heading=str(data["world_heading"]),
                q_ig=q_ig,
                bones=parse_assignment({sid: str(s["bone"]) for sid, s in sensors.items()}),
                q_ib={sid.upper(): _unit_quat(s["R_ib"], f"{sid} R_ib") for sid, s in sensors.items()},
                spread_deg={sid.upper(): float(s.get("still_spread_deg", np.nan)) for sid, s in sensors.items()},
                device_heading_deg={
                    sid.upper(): _finite_float(s["device_heading_deg"], f"{sid} device_heading_deg")
                    for sid, s in sensors.items()
                    if "device_heading_deg" in s
                },
                residual_deg={
                    sid.upper(): _finite_float(s["mount_residual_deg"], f"{sid} mount_residual_deg")
                    for sid, s in sensors.items()
                    if "mount_residual_deg" in s
                },
                posture={str(k): float(v) for k, v in posture.get("angles_deg", {}).items()},
                pose_hint=str(posture.get("hint", "t-pose")),
                hinge_misfit_deg={
                    sid.upper(): _finite_float(s["hinge_misfit_deg"], f"{sid} hinge_misfit_deg")
                    for sid, s in sensors.items()
                    if "hinge_misfit_deg" in s
                },
                gravity_misfit_deg={
                    sid.upper(): _finite_float(s["gravity_misfit_deg"], f"{sid} gravity_misfit_deg")
                    for sid, s in sensors.items()
                    if "gravity_misfit_deg" in s
                },
            )
        except (KeyError, TypeError, ValueError, AssertionError) as exc:
            raise CalibrationError(f"malformed IMU calibration file: {exc!r}") from exc


def _finite_float(value: object, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not np.isfinite(value):
        raise CalibrationError(f"{name} must be a finite number, got {value!r}")
    return float(value)


def device_heading_quat(delta_deg: float) -> FloatArray:
    """``Rz(δ)``: a turn about the device frame's up axis (ENU z), shape (4,)."""
    return quat_from_rotvec(np.array([0.0, 0.0, np.radians(delta_deg)]))


def twist_about_up_deg(q: FloatArray) -> float:
    """Angle (degrees) of the twist about world +Y in the swing-twist split ``q = twist · swing``."""
    q = np.asarray(q, dtype=np.float64)
    return float((np.degrees(2.0 * np.arctan2(q[2], q[0])) + 180.0) % 360.0 - 180.0)


def _unit_quat(value: object, name: str) -> FloatArray:
    q = np.asarray(value, dtype=np.float64)
    if q.shape != (4,) or not np.all(np.isfinite(q)) or abs(np.linalg.norm(q) - 1.0) > 1e-6:
        raise CalibrationError(f"{name} must be a unit quaternion [w, x, y, z], got {value!r}")
    return q


def calibrate_tpose(
    person: str,
    recordings: Mapping[str, tuple[FloatArray, FloatArray | None]],
    bones: Mapping[str, str],
    *,
    facing_heading_deg: float,
    world_heading: str = "subject",
    window: int = 60,
    rest: Mapping[str, FloatArray] | None = None,
    max_spread_deg: float = MAX_TURN_DEG,
    max_acc_std: float = MAX_ACC_STD,
    own_heading: Mapping[str, float] | None = None,
    estimate_posture: bool = False,
    pose_hint: str = "t-pose",
) -> ImuCalibration:
    """T-pose calibration of every assigned sensor.

    Parameters
    ----------
    recordings : mapping of sensor id to (quat (n, 4), acc (n, 3) or None)
        Device-frame (ENU) orientations recorded while the subject held the T-pose.
    bones : mapping of sensor id to bone name
        From :func:`parse_assignment`; every assigned sensor must have a recording.
    facing_heading_deg : float
        Compass heading the subject faced (degrees clockwise from magnetic north).
    rest : mapping of bone name to quaternion (4,), optional
        Rest-pose world orientation of each bone (identity when absent: the T-pose rest skeleton).
    own_heading : mapping of sensor id to degrees, optional
        Sensors with a heading reference of their own (SlimeVR trackers) and their mounting yaw (0: on the front
        or back of the segment; +90: on the subject's left side): each gets a device heading δ (module docstring).
    estimate_posture : bool
        Take ``rest`` as a hint and estimate the posture held from the sensors' orientations
        (:func:`estimate_mounting`); False: every bone held ``rest`` exactly.
    pose_hint : str
        The hint's name, recorded in the calibration.

    Raises
    ------
    CalibrationError
        A sensor is missing or moved (the message names it).
    """
    missing = sorted(set(bones) - set(recordings))
    if missing:
        raise CalibrationError(f"no samples from assigned sensors {missing}")
    q_ig_tpose = heading_alignment(facing_heading_deg, world_heading="subject")
    unknown = sorted(set(own_heading or ()) - set(bones))
    if unknown:
        raise CalibrationError(f"own-heading sensors {unknown} are not in the assignment")
    q_ib: dict[str, FloatArray] = {}
    spread: dict[str, float] = {}
    headings: dict[str, float] = {}
    residual: dict[str, float] = {}
    pose: dict[str, FloatArray] = {}
    worn: dict[str, tuple[str, FloatArray, FloatArray]] = {}  # bone -> sensor id, S = R_ig·R_i, hinted posture
    for sid, bone in bones.items():
        quat, acc = recordings[sid]
        still = stillest_window(
            quat,
            acc,
            window,
            max_spread_deg=max_spread_deg,
            max_acc_std=max_acc_std,
            sensor=f"{sid} ({bone})",
        )
        q_rest = None if rest is None else rest.get(bone)
        q_i = still.mean
        if own_heading is not None and sid in own_heading:
            # Turn the sensor's frame about up so that its T-pose orientation twists by the mounting yaw; the
            # twist of (R_ig_T · R_i) adds to a turn about world up, which is a turn about device up.
            twist = twist_about_up_deg(quat_multiply(q_ig_tpose, q_i))
            delta = (own_heading[sid] - twist + 180.0) % 360.0 - 180.0
            headings[sid] = delta
            q_i = quat_multiply(device_heading_quat(delta), q_i)
        hint = np.array([1.0, 0.0, 0.0, 0.0]) if q_rest is None else np.asarray(q_rest, dtype=np.float64)
        worn[bone] = (sid, quat_multiply(q_ig_tpose, q_i), hint)
        spread[sid] = still.spread_deg
    flexion = knee_flexion(worn) if estimate_posture else {}
    for bone, (sid, q_sensor, hint) in worn.items():
        sigma = posture_sigma(bone) if estimate_posture else None
        est = estimate_mounting(q_sensor, hint, sigma, flexion=flexion.get(bone))
        q_ib[sid] = est.q_ib
        residual[sid] = est.residual_deg
        pose[bone] = est.q_pose
    q_ig = heading_alignment(facing_heading_deg, world_heading=world_heading)
    return ImuCalibration(person, facing_heading_deg, world_heading, q_ig, dict(bones), q_ib, spread, headings,
                          residual, posture_angles(pose), pose_hint)  # fmt: skip


def facing_heading_from_sensor(q_i: FloatArray, forward_axis: FloatArray) -> float:
    """Compass heading (degrees from north, clockwise) of a sensor axis known to point forward.

    Useful when the pelvis sensor's mounting is known roughly (e.g. its -z axis points forward on the back of
    the pelvis): the horizontal projection of that axis in ENU gives the subject's facing heading.
    """
    fwd = matrix_from_quat(np.asarray(q_i, dtype=np.float64)) @ np.asarray(forward_axis, dtype=np.float64)
    if np.hypot(fwd[0], fwd[1]) < 1e-3:
        raise CalibrationError("the forward axis is vertical: cannot derive a heading from it")
    return float(np.degrees(np.arctan2(fwd[0], fwd[1])) % 360.0)


# ------------------------------------------------------------------------------ the calibration posture
CALIBRATION_POSES = ("t-pose", "a-pose", "n-pose", "arms-down")
"""Posture hints: ``t-pose`` (arms horizontal), ``a-pose`` (upper arms 30° below horizontal), ``n-pose`` and its
older name ``arms-down`` (arms hanging at the sides, palms in). ``auto`` (with a take) tries them all."""
POSE_HINTS = ("t-pose", "a-pose", "n-pose")
"""The hints ``--pose auto`` tries, in this order."""
ARM_DROP_DEG = {"t-pose": 0.0, "a-pose": 30.0, "n-pose": 90.0, "arms-down": 90.0}
"""How far below horizontal each hint holds the upper arms (degrees); forearms and hands in line with them."""
_ARM_SIDE = {
    "LeftUpperArm": -1.0, "LeftLowerArm": -1.0, "LeftHand": -1.0,
    "RightUpperArm": 1.0, "RightLowerArm": 1.0, "RightHand": 1.0,
}  # fmt: skip


def rest_orientations(pose: str) -> dict[str, FloatArray] | None:
    """World orientation of each bone in a calibration posture hint, for :func:`calibrate_tpose` (None: the T-pose).

    ``"t-pose"`` is the solver's rest pose (arms horizontal); the others turn the upper arms, forearms and hands
    down about the body's forward axis (+Z) by :data:`ARM_DROP_DEG` (``"n-pose"``/``"arms-down"``: 90°, hanging
    at the sides, palms in).
    """
    if pose not in ARM_DROP_DEG:
        raise ConfigError(f"calibration pose must be one of {CALIBRATION_POSES} (or auto), got {pose!r}")
    drop = np.radians(ARM_DROP_DEG[pose])
    if drop == 0.0:
        return None
    # The left arm along +X in the T-pose, down (-Y) at the side: -90° about +Z; the right arm (-X): +90°.
    return {b: quat_from_rotvec(np.array([0.0, 0.0, s * drop])) for b, s in _ARM_SIDE.items()}


MOUNT_SIGMA_DEG = 8.0
"""How far (degrees, per axis) a strapped sensor's axes stray from its segment's axes: a sensor is put on with its
case along the segment (the long side along the bone, its face on the segment's surface), within a few degrees."""

POSTURE_SIGMA_DEG: dict[str, tuple[float, float, float]] = {
    # Bone-frame axes (x, y, z) of a perturbation of the hint: for the arms x runs along the arm (twist), y is the
    # forward swing (and the elbow's flexion), z the elevation in the frontal plane; for the legs x is the flexion
    # axis, y the twist about the bone, z the abduction. Bones not listed hold the hint exactly (pelvis, trunk,
    # head and feet: a person standing upright on flat feet).
    "UpperArm": (15.0, 12.0, 20.0),
    "LowerArm": (15.0, 20.0, 20.0),
    "Hand": (20.0, 20.0, 20.0),
    "UpperLeg": (5.0, 2.0, 2.0),
    "LowerLeg": (6.0, 2.0, 2.0),
}
"""How far (degrees, per bone-frame axis) a real person's still posture strays from the hint; from the realistic
calibration postures of docs/imu.md (upper arms 15-35° below horizontal, elbows 10-30° bent, knees 0-10° bent)."""


def _axis_aligned_rotations() -> FloatArray:
    """The 24 rotations that map the axes onto signed axes (quaternions, shape (24, 4))."""
    out = []
    for perm in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)):
        for signs in np.ndindex(2, 2, 2):
            m = np.zeros((3, 3))
            for row, (col, sign) in enumerate(zip(perm, signs, strict=True)):
                m[row, col] = -1.0 if sign else 1.0
            if np.linalg.det(m) > 0:
                out.append(quat_from_matrix(m))
    return np.array(out)


_AXIS_ALIGNED = _axis_aligned_rotations()


@dataclass(frozen=True, slots=True)
class MountEstimate:
    """One sensor's mounting with the posture its bone held, from :func:`estimate_mounting`."""

    q_ib: FloatArray  # (4,) the mounting R_ib
    q_pose: FloatArray  # (4,) the bone's world orientation in the calibration posture
    residual_deg: float  # the mounting's angle from the nearest case-along-the-segment mounting


def posture_sigma(bone: str) -> FloatArray | None:
    """:data:`POSTURE_SIGMA_DEG` of ``bone`` in radians, shape (3,); None for a bone that holds the hint."""
    for part, sigma in POSTURE_SIGMA_DEG.items():
        if bone.endswith(part):
            return np.radians(np.array(sigma, dtype=np.float64))
    return None


def estimate_mounting(
    q_sensor: FloatArray,
    q_hint: FloatArray,
    sigma: FloatArray | None,
    mount_sigma_deg: float = MOUNT_SIGMA_DEG,
    *,
    flexion: float | None = None,
) -> MountEstimate:
    """A sensor's mounting and its bone's posture from one still orientation, the posture hint and two priors.

    With ``S`` the sensor's world orientation (R_ig · R_i), ``R_pose`` the bone's (unknown) posture and ``M`` the
    (unknown) mounting, ``S = R_pose · M``. One orientation cannot split the two; the priors do. The posture is the
    hint turned by ``a`` (bone frame, per-axis spread ``sigma``); the mounting is the nearest case-along-the-segment
    mounting ``M0`` (:data:`_AXIS_ALIGNED`) turned by ``b`` (spread ``mount_sigma_deg`` on each axis). With
    ``exp(a)·exp(b) = R_hint⁻¹ · S · M0⁻¹ = D`` the most probable split gives each axis of ``log D`` to the posture
    in proportion to the variances: ``a = σ_a² / (σ_a² + σ_m²) · log D``. What gravity makes of the sensor's
    inclination thus becomes the bone's (an arm 25° below horizontal, a knee bent 8°) where the posture is uncertain,
    and the mounting keeps it where it is not (``sigma`` None: the hint held exactly, ``M = R_hint⁻¹ · S``).

    Parameters
    ----------
    q_sensor, q_hint : array, shape (4,)
        ``S`` and the hinted posture of the bone.
    sigma : array, shape (3,), or None
        The posture's spread about the hint (radians, bone-frame axes; :func:`posture_sigma`).
    flexion : float, optional
        The posture's turn about the bone-frame x axis (radians) when known from elsewhere (:func:`knee_flexion`).
    """
    nearest, d = mounting_discrepancy(q_sensor, q_hint)
    if sigma is None:
        a = np.zeros(3)
    else:
        var_m = np.radians(mount_sigma_deg) ** 2
        a = sigma**2 / (sigma**2 + var_m) * d
        if flexion is not None:
            a[0] = flexion
    q_pose = quat_canonical(quat_multiply(q_hint, quat_from_rotvec(a)))
    q_ib = quat_canonical(quat_multiply(quat_conjugate(q_pose), q_sensor))
    residual = float(np.degrees(quat_angle(q_ib, nearest)))
    return MountEstimate(q_ib, q_pose, residual)


def mounting_discrepancy(q_sensor: FloatArray, q_hint: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The case-along-the-segment mounting nearest to what the hint implies, ``M0`` (4,), and ``log D`` (3,):
    what the hint leaves over, split between posture and mounting by :func:`estimate_mounting`."""
    q_mount_hint = quat_multiply(quat_conjugate(q_hint), q_sensor)  # M if the hint were exact
    nearest = _AXIS_ALIGNED[int(np.argmax(np.abs(_AXIS_ALIGNED @ q_mount_hint)))]
    return nearest, rotvec_from_quat(quat_multiply(q_mount_hint, quat_conjugate(nearest)))


KNEE_SIGMA_DEG = 4.0
"""How far a thigh (and, the other way, its shank) leans from vertical standing with the knees a little bent."""


def knee_flexion(worn: Mapping[str, tuple[str, FloatArray, FloatArray]]) -> dict[str, float]:
    """The thighs' and shanks' flexion (radians, about the bone-frame x axis) in a still standing posture, from
    both sensors of a leg together.

    Standing on flat feet with a knee bent by ``k``, the thigh leans forward by ``k/2`` and the shank back by
    ``k/2`` (the ankle stays under the hip). Each sensor's discrepancy about x holds its bone's lean and its own
    mounting error; their half difference holds the lean once with half the mounting variance, which the prior
    :data:`KNEE_SIGMA_DEG` weighs. ``worn``: bone -> (sensor id, S, hinted posture) as in :func:`calibrate_tpose`.
    """
    out: dict[str, float] = {}
    var_k, var_m = np.radians(KNEE_SIGMA_DEG) ** 2, np.radians(MOUNT_SIGMA_DEG) ** 2
    for side in ("Left", "Right"):
        thigh, shank = worn.get(f"{side}UpperLeg"), worn.get(f"{side}LowerLeg")
        if thigh is None or shank is None:
            continue
        lean = (mounting_discrepancy(thigh[1], thigh[2])[1][0] - mounting_discrepancy(shank[1], shank[2])[1][0]) / 2
        a = var_k / (var_k + var_m / 2) * float(lean)
        out[f"{side}UpperLeg"], out[f"{side}LowerLeg"] = a, -a
    return out


def posture_angles(pose: Mapping[str, FloatArray]) -> dict[str, float]:
    """What a calibration posture (bone → world orientation) holds, in degrees: each upper arm's drop below
    horizontal, each elbow's and knee's bend (angle between the bones' long axes) where both bones are there."""
    out: dict[str, float] = {}

    def axis(bone: str, v: tuple[float, float, float]) -> FloatArray:
        return np.asarray(matrix_from_quat(pose[bone]) @ np.array(v), dtype=np.float64)

    for side, sign in (("Left", 1.0), ("Right", -1.0)):
        upper, lower = f"{side}UpperArm", f"{side}LowerArm"
        if upper in pose:
            along = axis(upper, (sign, 0.0, 0.0))
            out[f"{side.lower()}_upper_arm_drop"] = float(np.degrees(np.arcsin(np.clip(-along[1], -1.0, 1.0))))
            if lower in pose:
                out[f"{side.lower()}_elbow_bend"] = float(np.degrees(np.arccos(np.clip(
                    along @ axis(lower, (sign, 0.0, 0.0)), -1.0, 1.0))))  # fmt: skip
        thigh, shank = f"{side}UpperLeg", f"{side}LowerLeg"
        if thigh in pose and shank in pose:
            down = (0.0, -1.0, 0.0)
            out[f"{side.lower()}_knee_bend"] = float(np.degrees(np.arccos(np.clip(
                axis(thigh, down) @ axis(shank, down), -1.0, 1.0))))  # fmt: skip
    return {k: round(v, 1) for k, v in out.items()}


Samples = Mapping[str, tuple[FloatArray, FloatArray, FloatArray]]
"""Per sensor id: times (s, shape (n,)), orientations (n, 4) and accelerations (n, 3) of a recording."""


WINDOW_STEP_S = 0.05
"""Step between the still windows searched (s): fine enough that a window starting a moment after a movement is
found."""


def stillest_common_window(
    samples: Samples,
    window_s: float,
    span: tuple[float, float] | None,
    *,
    max_turn_deg: float = MAX_TURN_DEG,
    max_acc_std: float = MAX_ACC_STD,
) -> tuple[float, float]:
    """The ``window_s`` window (start, end in s) where the sensors are jointly stillest by every test a calibration
    window must pass: each sensor's largest turn from its window mean (against ``max_turn_deg``) and the std of its
    acceleration norm (against ``max_acc_std``), the worst ratio to its limit over sensors and tests smallest.
    Searched in steps of :data:`WINDOW_STEP_S` (at most a quarter window) over ``span`` (default: where every sensor
    recorded); the span's bounds are exact (a 1 s span holds a 1 s window).

    Every window is scored at once (:func:`_batched_scores`), with a bound on how far each score can be from the
    one :func:`_window_worst` computes; only the windows that can be the stillest by those bounds are scored again
    by :func:`_window_worst`, so the window chosen is exactly that of scoring every window one by one
    (:func:`_stillest_common_window_reference`), at a small part of its time.

    Raises
    ------
    CalibrationError
        The span is shorter than the window.
    """
    if not _batchable(samples, max_turn_deg, max_acc_std):
        return _stillest_common_window_reference(samples, window_s, span, max_turn_deg=max_turn_deg,
                                                 max_acc_std=max_acc_std)  # fmt: skip
    starts = _window_starts(samples, window_s, span)
    score = np.zeros(len(starts))
    bound = np.zeros(len(starts))
    for t, q, a in samples.values():
        s, b = _batched_scores(t, q, a, starts, window_s, max_turn_deg, max_acc_std)
        bound = np.maximum(bound, np.where(np.isfinite(s), b, 0.0))  # |max_k s_k - max_k s'_k| <= max_k b_k
        score = np.maximum(score, s)
    bound = np.where(np.isinf(score), 0.0, 2.0 * bound + 8.0 * _EPS * score)
    best_possible = float(np.min(score + bound))
    best: tuple[float, float] | None = None
    for start in starts[score - bound <= best_possible]:  # every window that can score the minimum, in order
        worst = _window_worst(samples, start, window_s, max_turn_deg, max_acc_std)
        if best is None or worst < best[0]:
            best = (worst, float(start))
    assert best is not None
    return best[1], best[1] + window_s


def _stillest_common_window_reference(
    samples: Samples,
    window_s: float,
    span: tuple[float, float] | None,
    *,
    max_turn_deg: float = MAX_TURN_DEG,
    max_acc_std: float = MAX_ACC_STD,
) -> tuple[float, float]:
    """:func:`stillest_common_window` by scoring every window one by one with :func:`_window_worst` (the definition
    the batched search must agree with exactly; also its path for inputs it does not bound: non-finite values,
    quaternions far from unit length, arrays not float64)."""
    starts = _window_starts(samples, window_s, span)
    best: tuple[float, float] | None = None
    for start in starts:
        worst = _window_worst(samples, start, window_s, max_turn_deg, max_acc_std)
        if best is None or worst < best[0]:
            best = (worst, float(start))
    assert best is not None
    return best[1], best[1] + window_s


def _window_starts(samples: Samples, window_s: float, span: tuple[float, float] | None) -> FloatArray:
    """The window starts searched (s, shape (n,)); raises :class:`CalibrationError` if the span is too short."""
    t_begin = max(float(t[0]) for t, _, _ in samples.values())
    t_end = min(float(t[-1]) for t, _, _ in samples.values())
    lo, hi = (t_begin, t_end) if span is None else (max(t_begin, span[0]), min(t_end, span[1]))
    if hi - lo < window_s - _TIME_EPS:
        raise CalibrationError(
            f"the calibration span {lo:.3f}-{hi:.3f} s is shorter than the {window_s:g} s window (all sensors must "
            "record through it)"
        )
    step = min(WINDOW_STEP_S, window_s / 4)
    starts = lo + step * np.arange(int(np.floor((hi - window_s - lo) / step + _TIME_EPS)) + 1)
    starts[-1] = min(starts[-1], hi - window_s)
    return np.asarray(starts, dtype=np.float64)


def _window_worst(samples: Samples, start: float, window_s: float, max_turn_deg: float, max_acc_std: float) -> float:
    """The score of the window at ``start``: the worst ratio of a sensor's turn or |acc| std to its limit (inf
    where a sensor has fewer than two samples in it)."""
    worst = 0.0
    for t, q, a in samples.values():
        i, j = np.searchsorted(t, [start - _TIME_EPS, start + window_s - _TIME_EPS])
        if j - i < 2:
            return np.inf
        turn = float(np.degrees(quat_angle(q[i:j], quat_average(q[i:j])).max()))
        acc = float(np.std(np.linalg.norm(a[i:j], axis=1)))
        worst = max(worst, turn / max_turn_deg, acc / max_acc_std if np.isfinite(acc) else 0.0)
    return worst


_EPS = float(np.finfo(np.float64).eps)
_BATCH = 512
"""Windows scored together by :func:`_batched_scores` (bounds its memory: 512 windows of 1 s at 100 Hz)."""


def _batchable(samples: Samples, max_turn_deg: float, max_acc_std: float) -> bool:
    """Whether :func:`_batched_scores` bounds its error on these inputs: float64 arrays, finite values, quaternions
    near unit length and finite positive limits."""
    if not (np.isfinite(max_turn_deg) and max_turn_deg > 0 and np.isfinite(max_acc_std) and max_acc_std > 0):
        return False
    for t, q_in, a_in in samples.values():
        q, a = np.asarray(q_in), np.asarray(a_in)
        if q.dtype != np.float64 or a.dtype != np.float64 or q.ndim != 2 or a.ndim != 2 or len(q) != len(t):
            return False
        if len(a) != len(t) or not (np.isfinite(q).all() and np.isfinite(a).all()):
            return False
        if np.any(np.abs(np.linalg.norm(q, axis=1) - 1.0) > 0.1) or np.any(np.abs(a) > 1e6):
            return False
    return True


def _batched_scores(
    t: FloatArray, q: FloatArray, a: FloatArray, starts: FloatArray, window_s: float, max_turn_deg: float,
    max_acc_std: float,
) -> tuple[FloatArray, FloatArray]:  # fmt: skip
    """One sensor's score (as in :func:`_window_worst`) of every window, computed together, and a bound on its
    difference from :func:`_window_worst`'s (floating point: other summation orders).

    Returns scores and bounds, each shape (len(starts),); a window with fewer than two samples scores inf (bound 0).
    The mean orientation is the top eigenvector of Σ q qᵀ (:func:`quat_average`); by Davis-Kahan it moves by at
    most ‖ΔM‖ / gap (gap: its eigenvalue minus the next), which bounds the cosine of each turn and through
    arccos's modulus of continuity the turn; the |acc| std moves by at most the error of its mean.
    """
    i_all = np.searchsorted(t, starts - _TIME_EPS)
    j_all = np.searchsorted(t, starts + window_s - _TIME_EPS)
    score, bound = np.empty(len(starts)), np.empty(len(starts))
    acc_norm = np.linalg.norm(a, axis=1)
    unit = q / np.linalg.norm(q, axis=1)[:, None]
    for k in range(0, len(starts), _BATCH):
        i, n = i_all[k : k + _BATCH], (j_all - i_all)[k : k + _BATCH]
        width = max(int(n.max()), 2)
        idx = np.minimum(i[:, None] + np.arange(width), len(t) - 1)  # (w, width)
        inside = np.arange(width) < n[:, None]
        qw = np.where(inside[..., None], q[idx], 0.0)  # (w, width, 4)
        vals, vecs = np.linalg.eigh(np.swapaxes(qw, 1, 2) @ qw)
        mean = vecs[..., -1]  # (w, 4), unit
        cos = np.where(inside, np.abs(np.einsum("wki,wi->wk", unit[idx], mean)), 1.0).min(axis=1)
        turn = np.degrees(2.0 * np.arccos(np.clip(cos, 0.0, 1.0)))  # the largest turn: arccos decreases
        gap = vals[:, -1] - vals[:, -2]
        with np.errstate(divide="ignore", invalid="ignore"):  # 0/0 only in windows of no samples
            d_cos = 64.0 * _EPS + 64.0 * (width + 16) * _EPS * np.abs(vals[:, -1]) / np.where(gap > 0, gap, 0.0)
        d_turn = np.where(d_cos < 1.0, np.degrees(2.0 * np.arccos(np.clip(1.0 - d_cos, -1.0, 1.0))), np.inf)
        x = np.where(inside, acc_norm[idx], 0.0)
        m = x.sum(axis=1) / np.maximum(n, 1)
        std = np.sqrt(np.where(inside, (x - m[:, None]) ** 2, 0.0).sum(axis=1) / np.maximum(n, 1))
        d_std = 4.0 * (width + 16) * _EPS * np.abs(x).max(axis=1)
        short = n < 2
        score[k : k + _BATCH] = np.where(short, np.inf, np.maximum(turn / max_turn_deg, std / max_acc_std))
        bound[k : k + _BATCH] = np.where(short, 0.0, np.maximum(d_turn / max_turn_deg, d_std / max_acc_std))
    return score, bound


_TIME_EPS = 1e-6
"""Seconds: bounds typed in decimals (``0.517:1.517``) are not exact binary fractions."""


def window_samples(t: FloatArray, start: float, end: float) -> slice:
    """The samples of times ``t`` (s, sorted) in ``[start, end)``, with bounds exact to :data:`_TIME_EPS`."""
    i, j = np.searchsorted(t, [start - _TIME_EPS, end - _TIME_EPS])
    return slice(int(i), int(j))


def common_grid(samples: Samples, sensors: list[str]) -> tuple[FloatArray, dict[str, FloatArray]]:
    """The sensors' orientations on one time grid: the first sensor's sample times where all recorded, every other
    sensor's nearest sample (one recording shares a time base).

    Returns times (s, shape (n,)) and per sensor its orientations (n, 4).
    """
    t_all = [samples[s][0] for s in sensors]
    t = t_all[0][(t_all[0] >= max(x[0] for x in t_all)) & (t_all[0] <= min(x[-1] for x in t_all))]
    dt = float(np.median(np.diff(t))) if t.size > 1 else 0.0
    out = {}
    for sid in sensors:
        ts, qs, _ = samples[sid]
        out[sid] = qs[np.clip(np.searchsorted(ts, t - dt / 2), 0, len(ts) - 1)]
    return t, out


def has_step_sensors(bones: Mapping[str, str]) -> bool:
    """Whether an assignment (sensor → bone) lets :func:`facing_heading_from_steps` work: one leg wears both a
    thigh and a shank sensor."""
    worn = set(bones.values())
    return any({f"{side}UpperLeg", f"{side}LowerLeg"} <= worn for side in ("Left", "Right"))


def facing_heading_from_steps(samples: Samples, bones: Mapping[str, str], window: tuple[float, float]) -> float | None:
    """The compass heading (degrees clockwise from north) the subject faced during ``window`` (s), from the way the
    knees bent in the take (:func:`mocapd.core.plausibility.facing_from_knees`); None when no leg wears both a
    thigh and a shank sensor, or the knees never bent (no steps)."""
    by_bone = {b: sid for sid, b in bones.items()}
    legs, still = [], []
    for side in ("Left", "Right"):
        thigh, shank = by_bone.get(f"{side}UpperLeg"), by_bone.get(f"{side}LowerLeg")
        if thigh is None or shank is None or thigh not in samples or shank not in samples:
            continue
        t, q = common_grid(samples, [thigh, shank])
        if t.size < 3:
            continue
        sel = (t >= window[0]) & (t < window[1])
        ref = quat_average(q[thigh][sel]) if sel.any() else q[thigh][0]
        ref_s = quat_average(q[shank][sel]) if sel.any() else q[shank][0]
        # The still window first: the knee's bend is measured from standing.
        legs.append((np.vstack([ref, q[thigh]]), np.vstack([ref_s, q[shank]])))
        still.append(ref)
    if not legs:
        return None
    forward = facing_from_knees(legs, still, np.array([0.0, 0.0, 1.0]))
    if forward is None:
        return None
    return float(np.degrees(np.arctan2(forward[0], forward[1])) % 360.0)


def calibration_hinges(
    samples: Samples, calib: ImuCalibration, options: PlausibilityOptions | None = None
) -> dict[str, HingeEvents]:
    """The knees and elbows over a recording, as the calibration makes its sensors measure them (no solve): the
    hinges with both bones measured and their wrong-way events (:mod:`mocapd.core.plausibility`)."""
    sensors = sorted(sid for sid in calib.bones if sid in samples)
    if not sensors:
        return {}
    t, q = common_grid(samples, sensors)
    orientations = {calib.bones[sid]: bone_orientation(calib.q_ig, q[sid], calib.q_ib[sid]) for sid in sensors}
    return check_bone_orientations(orientations, t, options)


ARM_THROUGH_BODY_COS = -0.7
"""An upper arm points into the body when its direction's component along the trunk's outward side axis is below
this (more than about 45° past the body's midplane, toward the other side: through the chest)."""


def arms_through_body(samples: Samples, calib: ImuCalibration) -> dict[str, float]:
    """Seconds each calibrated upper arm points into the body over a recording (:data:`ARM_THROUGH_BODY_COS`),
    measured against the pelvis (or sternum) sensor's bone: what a calibration posture turned by 90° makes of arms
    that hang or swing (an arms-down hint for a T-pose, or the reverse), where no elbow bends the wrong way. Empty
    without a trunk sensor."""
    by_bone = {b: sid for sid, b in calib.bones.items() if sid in samples}
    trunk = by_bone.get("Hips") or by_bone.get("Spine3")
    out: dict[str, float] = {}
    if trunk is None:
        return out
    for side, sign in (("left", 1.0), ("right", -1.0)):
        arm = by_bone.get(f"{side.capitalize()}UpperArm")
        if arm is None:
            continue
        t, q = common_grid(samples, [trunk, arm])
        if t.size < 2:
            continue
        axis = np.array([sign, 0.0, 0.0])  # the arm's direction and the trunk's outward side, bone frames
        along = matrix_from_quat(bone_orientation(calib.q_ig, q[arm], calib.q_ib[arm])) @ axis
        side_axis = matrix_from_quat(bone_orientation(calib.q_ig, q[trunk], calib.q_ib[trunk])) @ axis
        inward = np.einsum("ij,ij->i", along, side_axis) < ARM_THROUGH_BODY_COS
        out[f"{side}_upper_arm"] = float(inward.sum() * np.median(np.diff(t)))
    return out


def calibrate_recording(
    person: str,
    samples: Samples,
    bones: Mapping[str, str],
    *,
    facing_heading_deg: float | None = None,
    facing_from: tuple[str, FloatArray] | None = None,
    world_heading: str = "subject",
    window_s: float = 1.0,
    span: tuple[float, float] | None = None,
    pose: str = "t-pose",
    estimate_posture: bool = True,
    max_turn_deg: float = MAX_TURN_DEG,
    max_acc_std: float = MAX_ACC_STD,
) -> tuple[ImuCalibration, tuple[float, float]]:
    """:func:`calibrate_tpose` on the stillest moment of a recording where every assigned sensor stands still.

    The posture held there is ``pose`` (:func:`rest_orientations`): a hint the sensors refine with
    ``estimate_posture`` (:func:`estimate_mounting`), or exact without. The window is chosen by, and must pass, both
    stillness limits (:func:`stillest_common_window`). Exactly one of ``facing_heading_deg`` and
    ``facing_from`` (sensor id, unit axis in the sensor frame that points forward) gives the heading. Returns the
    calibration and the window used (s).

    Raises
    ------
    CalibrationError, ConfigError
        A sensor missing or moving, no facing direction, a bad pose.
    """
    if (facing_heading_deg is None) == (facing_from is None):
        raise ConfigError("give the facing direction: a compass heading or a sensor axis that points forward")
    missing = sorted(set(bones) - set(samples))
    if missing:
        raise CalibrationError(f"assigned sensor(s) {missing} have no samples")
    start, end = stillest_common_window(
        {s: samples[s] for s in bones}, window_s, span, max_turn_deg=max_turn_deg, max_acc_std=max_acc_std
    )
    chunks = {}
    for sid in bones:
        t, q, a = samples[sid]
        sel = window_samples(t, start, end)
        chunks[sid] = (q[sel], a[sel])
    n = min(len(q) for q, _ in chunks.values())
    if facing_from is not None:
        sid, axis = facing_from
        if sid not in samples:
            raise ConfigError(f"--facing-from: no samples from sensor {sid}")
        t, q, _ = samples[sid]
        facing_heading_deg = facing_heading_from_sensor(quat_average(q[window_samples(t, start, end)]), axis)
    assert facing_heading_deg is not None
    calib = calibrate_tpose(
        person,
        {sid: (q[:n], a[:n]) for sid, (q, a) in chunks.items()},
        bones,
        facing_heading_deg=facing_heading_deg,
        world_heading=world_heading,
        window=n,
        rest=rest_orientations(pose),
        max_spread_deg=max_turn_deg,
        max_acc_std=max_acc_std,
        estimate_posture=estimate_posture,
        pose_hint=pose,
    )
    return calib, (start, end)
