"""The real MTw walk with Vicon truth through the commands a user runs (issue 42), scored against Vicon.

``import mtw --height H`` of the Neura sparse S02 walk's seven lower-body sensors -> ``calibrate imu --from`` (the
facing from the steps, the options given after the height) -> ``resolve`` -> ``export --resolved --csv``; the resolved
poses, resampled to Vicon's 100 Hz, are measured by :func:`mocapd.eval.ground_optical.measure` (path length, root
height, knee and hip flexion). Prints one JSON line. The data are GPL-3.0 and not shipped
(:func:`mocapd.eval.ground_optical.missing_message` says how to get them)::

    python tools/optical_walk_cli.py DATA_DIR WORK_DIR 1.70 [--pose auto ...]
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import shutil
import sys
from pathlib import Path

import numpy as np

from mocapd.core.motion import resample_poses
from mocapd.core.skeleton import Skeleton
from mocapd.eval.ground_optical import RATE_HZ, SENSORS, TRIAL, measure, read_vicon
from mocapd.io.session import RESOLVED, open_session
from mocapd.service.cli import main as cli


def run(data: Path, work: Path, height: float, calibrate_args: list[str]) -> dict[str, object]:
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    files = [str(data / "rawimu" / f"{TRIAL}-000_{sid}.txt") for sid in SENSORS]
    assign = [a for sid, bone in SENSORS.items() for a in ("--assign", f"{sid}={bone}")]
    session = work / "take"
    said = io.StringIO()
    with contextlib.redirect_stdout(said):
        if cli(["import", "mtw", *files, "-o", str(session), "--height", str(height), *assign]) != 0:
            raise SystemExit("import failed")
        start = said.tell()
        if cli(["calibrate", "imu", "--from", str(session), *calibrate_args]) != 0:
            raise SystemExit("calibrate failed")
        calibration = json.loads(said.getvalue()[start:])
        if cli(["resolve", str(session)]) != 0 or cli(
            ["export", str(session), "--resolved", "--csv", str(work / "t.csv")]
        ):
            raise SystemExit("resolve or export failed")
    with open(work / "t.csv", newline="") as fh:
        rows = sum(1 for _ in csv.DictReader(fh))
    opened = open_session(session)
    theta = np.array([f.people[0].theta for f in opened.poses(RESOLVED)])
    m = opened.manifest["skeleton"]
    skeleton = Skeleton(np.array(m["offsets"]), m["root_height"], m["height"])
    result = measure(resample_poses(theta, 60.0, RATE_HZ), skeleton, read_vicon(data / "vicon" / f"{TRIAL}.mat"))
    return {"height_m": height, "calibrate": calibrate_args, "facing_heading_deg": calibration["facing_heading_deg"],
            "posture": calibration.get("posture"), "posture_deg": calibration.get("posture_deg"), "csv_rows": rows,
            "poses": len(theta), **result}  # fmt: skip


if __name__ == "__main__":
    print(json.dumps(run(Path(sys.argv[1]), Path(sys.argv[2]), float(sys.argv[3]), sys.argv[4:])))
