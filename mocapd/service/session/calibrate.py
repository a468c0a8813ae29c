"""``mocapd calibrate imu --from SESSION``: calibrate a suit from the stillest standing moment of a recording.

The calibration is :func:`mocapd.core.imu_calibration.calibrate_recording`: every assigned sensor's mounting
``R_ib`` from one still window, during which every bone is assumed to be at its **rest orientation**. The solver's
rest pose is the **T-pose** (DESIGN.md: arms horizontal, legs straight, feet flat, facing +Z), so by default the
subject must stand in a T-pose; ``pose="arms-down"`` assumes instead that the arms hang at the sides (palms in:
upper arms, forearms and hands turned 90° down about the body's forward axis), the usual posture at the start of
a take. For a suit without arm sensors the two are the same: standing straight.

The window is the one where *all* assigned sensors are jointly stillest (the largest turn of any sensor from its
window mean is smallest), searched in steps of a quarter window over the whole recording or over
``START:END`` seconds; a window where a sensor turns more than 2° or its acceleration norm varies by more than
0.3 m/s² is refused with the sensor named, as for a live calibration. The heading comes from ``--facing-heading``
or from a sensor axis that points forward (``--facing-from SENSOR:AXIS``).

The result is written into the session's manifest (its ``suits``: what ``mocapd resolve`` solves with) and as a
calibration file (``<calibration_dir>/<person>.imu.json``).
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mocapd.core.imu_calibration import ImuCalibration, calibrate_recording, parse_assignment
from mocapd.errors import CalibrationError, ConfigError
from mocapd.io.session import MANIFEST, Session, write_json_atomic

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class SessionCalibration:
    calibration: ImuCalibration
    window_s: tuple[float, float]
    """Start and end of the window used, seconds from the session's first sample."""
    pose: str


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
) -> SessionCalibration:
    """Calibrate the session's assigned sensors (see the module docstring).

    ``assignment`` defaults to the session's ``[imu.assignment]`` (an imported session has it). Exactly one of
    ``facing_heading_deg`` and ``facing_from`` (sensor id, unit axis in the sensor frame) must be given.
    """
    imu_cfg = session.manifest.get("config", {}).get("imu", {})
    bones = parse_assignment(assignment if assignment is not None else imu_cfg.get("assignment", {}))
    if not bones:
        raise ConfigError(f"{session.path}: no sensor is assigned to a bone ([imu.assignment] of its config)")
    calib, window = calibrate_recording(
        person, session_samples(session), bones, facing_heading_deg=facing_heading_deg, facing_from=facing_from,
        world_heading=world_heading, window_s=window_s, span=span, pose=pose,
    )  # fmt: skip
    return SessionCalibration(calib, window, pose)


def store_in_session(session: Session, suit: str, calib: ImuCalibration, info: dict[str, Any]) -> None:
    """Put the calibration into the session's manifest as suit ``suit`` (replacing one of that name)."""
    m = dict(session.manifest)
    suits = [s for s in m.get("suits", []) if s.get("id") != suit]
    suits.append({"id": suit, "sensors": sorted(calib.bones), "calibration": calib.to_json_dict()})
    m["suits"] = suits
    m.setdefault("calibrations", {})[suit] = info
    write_json_atomic(session.path / MANIFEST, m)
    session.manifest = m
