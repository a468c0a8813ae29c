"""The real MTw walk with Vicon truth through the commands a suit owner runs (issue 42): ``eval ground``'s row.

``import mtw --height H`` of the Neura sparse S02 walk's seven lower-body sensors -> ``calibrate imu --from`` (the
facing from the steps; further options as given) -> ``resolve`` -> ``export --resolved --csv``, each called as the
command line calls it (:func:`mocapd.service.cli.main`, its JSON captured); the resolved poses, resampled to Vicon's
100 Hz, are measured by :func:`mocapd.eval.ground_optical.measure`. ``mocapd eval ground --parts optical`` prints it
beside the library path's rows (the issue's target: "``eval ground`` measures exactly that path"), and
``tools/optical_walk_cli.py`` runs it alone with other heights and calibration options. It lives in the service
layer because it runs the commands; :mod:`mocapd.eval.ground_optical` keeps the measures.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from mocapd.errors import InputError


def through_commands(data: Path, work: Path, height: float, calibrate_args: list[str]) -> dict[str, Any]:
    """Run the commands on the take under ``data`` (the gaittoolbox ``data/sample`` layout) in ``work`` (emptied
    first) and measure the resolved poses against Vicon; JSON-able."""
    from mocapd.core.motion import resample_poses
    from mocapd.core.skeleton import Skeleton
    from mocapd.eval.ground_optical import RATE_HZ, SENSORS, TRIAL, measure, read_vicon
    from mocapd.io.session import RESOLVED, open_session
    from mocapd.service.cli import main as cli

    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    files = [str(data / "rawimu" / f"{TRIAL}-000_{sid}.txt") for sid in SENSORS]
    assign = [a for sid, bone in SENSORS.items() for a in ("--assign", f"{sid}={bone}")]
    session = work / "take"
    said = io.StringIO()
    # The commands print their JSON reports and, on a refusal, one line on stderr: that line is the error here.
    refused = io.StringIO()
    calibration: dict[str, Any] = {}
    with contextlib.redirect_stdout(said), contextlib.redirect_stderr(refused):
        steps: list[tuple[str, list[str]]] = [
            ("mocapd import mtw", ["import", "mtw", *files, "-o", str(session), "--height", f"{height:g}", *assign]),
            ("mocapd calibrate imu", ["calibrate", "imu", "--from", str(session), *calibrate_args]),
            ("mocapd resolve", ["resolve", str(session)]),
            ("mocapd export", ["export", str(session), "--resolved", "--csv", str(work / "t.csv")]),
        ]
        for name, argv in steps:
            start = said.tell()
            if cli(argv) != 0:
                raise InputError(f"{name} failed on {data}: {refused.getvalue().strip()}")
            if name == "mocapd calibrate imu":
                calibration = json.loads(said.getvalue()[start:])
    with open(work / "t.csv", newline="") as fh:
        rows = sum(1 for _ in csv.DictReader(fh))
    opened = open_session(session)
    theta = np.array([f.people[0].theta for f in opened.poses(RESOLVED)])
    m = opened.manifest["skeleton"]
    skeleton = Skeleton(np.array(m["offsets"]), m["root_height"], m["height"])
    result = measure(resample_poses(theta, 60.0, RATE_HZ), skeleton, read_vicon(data / "vicon" / f"{TRIAL}.mat"))
    return {"commands": [name for name, _ in steps], "height_m": height,
            "calibrate": calibrate_args, "calibration_window_s": calibration["window_s"],
            "facing_heading_deg": calibration["facing_heading_deg"], "posture": calibration.get("posture"),
            "posture_deg": calibration.get("posture_deg"), "poses": len(theta),
            "csv_rows": rows, **result}  # fmt: skip


__all__ = ["through_commands"]
