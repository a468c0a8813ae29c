"""The real MTw walk with Vicon truth through the commands a user runs (issue 42), scored against Vicon.

``import mtw --height H`` of the Neura sparse S02 walk's seven lower-body sensors -> ``calibrate imu --from`` (the
facing from the steps, the options given after the height) -> ``resolve`` -> ``export --resolved --csv``; the resolved
poses, resampled to Vicon's 100 Hz, are measured by :func:`mocapd.eval.ground_optical.measure` (path length, root
height, knee and hip flexion, the facing against Vicon's pelvis). Prints one JSON line. ``mocapd eval ground --parts
optical`` runs the same (:func:`mocapd.service.cli.optical_walk.through_commands`) at 1.70 m. The data are GPL-3.0
and not shipped (:func:`mocapd.eval.ground_optical.missing_message` says how to get them)::

    python tools/optical_walk_cli.py DATA_DIR WORK_DIR 1.70 [--pose auto ...]
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from mocapd.service.cli.optical_walk import through_commands

if __name__ == "__main__":
    print(json.dumps(through_commands(Path(sys.argv[1]), Path(sys.argv[2]), float(sys.argv[3]), sys.argv[4:])))
