"""The IMU suits the daemon fuses: one per ``<person>.imu.json`` written by ``mocapd calibrate imu``.

Every calibration file in ``[imu] calibration_dir`` is a suit (its id is the person's name in the file). A file
that cannot be read is a start-up error naming it — running on without a suit the technician calibrated would be
a silent wrong answer. A missing directory means no suits (cameras only).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from mocapd.core.imu_calibration import ImuCalibration
from mocapd.core.skeleton import Skeleton
from mocapd.errors import CalibrationError, ConfigError
from mocapd.io.input_files import read_input_text
from mocapd.pipeline.scheduler import Suit
from mocapd.service.config.imu import ImuConfig

log = logging.getLogger(__name__)


def load_suits(config: ImuConfig, skeleton: Skeleton, base: Path | None = None) -> list[Suit]:
    """Suits from ``config.calibration_dir`` (relative paths from ``base``, default the working directory).

    Raises
    ------
    ConfigError
        A calibration file is unreadable or malformed, two files name the same person, or one sensor is in two
        suits.
    """
    folder = Path(config.calibration_dir)
    if not folder.is_absolute() and base is not None:
        folder = base / folder
    if not folder.is_dir():
        return []
    suits: list[Suit] = []
    owner: dict[str, str] = {}
    persons = config.persons  # per-person tables: a suit's sensors are its person's table's
    for path in sorted(folder.glob("*.imu.json")):
        try:
            text = read_input_text(path, "IMU calibration", max_bytes=16 << 20, errors="strict", error=ConfigError)
            calibration = ImuCalibration.from_json_dict(json.loads(text))
        except ConfigError:
            raise
        except (OSError, ValueError, CalibrationError) as exc:
            raise ConfigError(f"IMU calibration {path}: {exc}") from exc
        if any(s.id == calibration.person for s in suits):
            raise ConfigError(f"IMU calibration {path}: person {calibration.person!r} is calibrated twice")
        for sensor in calibration.bones:
            if sensor in owner:
                raise ConfigError(f"IMU calibration {path}: sensor {sensor} is already in suit {owner[sensor]!r}")
            owner[sensor] = calibration.person
        assigned = persons.get(calibration.person, {}) if persons else config.sensors
        where = f"[imu.assignment.{calibration.person}]" if persons else "[imu.assignment]"
        unassigned = sorted(set(calibration.bones) - set(assigned)) if config.sensors else []
        if unassigned:
            log.warning("suit %s: sensors %s are not in %s", calibration.person, unassigned, where)
        suits.append(Suit.from_calibration(calibration.person, calibration, skeleton))
    return suits


RESIDUAL_NOTE_DEG = 20.0
"""A sensor whose mounting residual is above this (degrees) is named as one to check: a mounting that far from a case
along its segment is a sensor strapped askew, a posture far from the hint, or a hinge that moved about more than
one axis."""


def calibration_line(suit: Suit) -> str:
    """What the console says of a suit's calibration at start (and after a live calibration): the posture found,
    and the sensors' residuals (median, and the worst sensor named)."""
    calib = suit.calibration
    summary = calib.summary()
    posture = ", ".join(f"{k.replace('_', ' ')} {v:g}" for k, v in calib.posture.items())
    line = f"suit {suit.id}: calibrated with the {calib.pose_hint} hint"
    line += f" (posture found, deg: {posture})" if posture else ""
    residuals = list(calib.residuals().values())
    worst = summary["worst"]
    if not residuals or not isinstance(worst, dict):
        return line + "; no mounting residuals in its file"
    line += (f"; mounting residual median {float(np.median(residuals)):.1f} deg, worst {worst['residual_deg']:.1f} "
             f"deg ({worst['sensor']}, {worst['bone']})")  # fmt: skip
    if calib.hinge_misfit_deg:
        line += f"; hinge axes from motion for {len(calib.hinge_misfit_deg)} sensors"
    if calib.gravity_misfit_deg:
        worst_g = max(calib.gravity_misfit_deg, key=lambda s: calib.gravity_misfit_deg[s])
        line += (f"; gravity from stances for {len(calib.gravity_misfit_deg)} sensors (misfit worst "
                 f"{calib.gravity_misfit_deg[worst_g]:.1f} deg, {calib.bones[worst_g]})")  # fmt: skip
    if float(worst["residual_deg"]) > RESIDUAL_NOTE_DEG:
        line += f": above {RESIDUAL_NOTE_DEG:g} deg, check how that sensor sits and calibrate again"
    return line
