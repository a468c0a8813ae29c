#!/usr/bin/env bash
# profile: demo
# Fetches the Pose2Sim demo data (videos, calibration images and Calib.qca.txt of four real cameras) used by
# the camera tests and benchmarks (issue 5). Source: the `pose2sim` wheel on PyPI, BSD-3-Clause licence
# (copyright David Pagnon; the licence text is unpacked beside the data as LICENSE). Nothing is committed to
# the repository: the wheel and its unpacked demo folders live in mocapd's cache directory
# (~/.cache/mocapd/pose2sim/, or $MOCAPD_CACHE/pose2sim/: mocapd.io.model_cache).
set -euo pipefail
version=0.10.49
dest="$(.venv/bin/python -c 'from mocapd.io.model_cache import cache_dir; print(cache_dir() / "pose2sim")')"
stamp="$dest/.unpacked-$version"
if [ -f "$stamp" ]; then
    exit 0
fi
mkdir -p "$dest"
wheel="$dest/pose2sim-$version-py3-none-any.whl"
if [ ! -f "$wheel" ]; then
    echo "downloading pose2sim $version demo data (wheel, ~50 MB)" >&2
    .venv/bin/python -m pip download -q --no-deps "pose2sim==$version" -d "$dest"
fi
.venv/bin/python - "$wheel" "$dest" <<'PY'
import sys
import zipfile
from pathlib import Path

wheel, dest = Path(sys.argv[1]), Path(sys.argv[2])
with zipfile.ZipFile(wheel) as z:
    for name in z.namelist():
        if name.startswith(("Pose2Sim/Demo_SinglePerson/", "Pose2Sim/Demo_MultiPerson/")):
            z.extract(name, dest)
        elif name.endswith("dist-info/licenses/LICENSE"):
            (dest / "LICENSE").write_bytes(z.read(name))
PY
touch "$stamp"
