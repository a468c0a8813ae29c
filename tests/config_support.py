"""Shared by the ``mocapd devices`` tests: does ``mocapd check-config`` accept a printed config snippet?"""

from __future__ import annotations

import contextlib
import io
import tomllib
from pathlib import Path

import numpy as np

from mocapd.io.calibration_files import CalibrationSet, CameraCalibration, write_mocapd_toml
from mocapd.service.cli import main


def check_config(snippet: str, folder: Path) -> tuple[int, str]:
    """Run ``mocapd check-config`` on ``snippet`` plus a ``[calibration]`` that has every camera it names (as the
    user's calibration would), in ``folder``; returns the exit status and what it printed."""
    names = [c["name"] for c in tomllib.loads(snippet).get("cameras", [])]
    K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
    calibration = CalibrationSet(tuple(CameraCalibration(n, (640, 480), K) for n in names))
    write_mocapd_toml(calibration, folder / "calibration.toml")
    path = folder / "rig.toml"
    path.write_text(f'{snippet}\n[calibration]\nfile = "{folder / "calibration.toml"}"\n', encoding="utf-8")
    out, err = io.StringIO(), io.StringIO()
    # IMU calibrations are looked for in ./calibration: the folder, not wherever the tests run.
    with contextlib.chdir(folder), contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(["check-config", str(path)])
    return code, out.getvalue() + err.getvalue()
