#!/usr/bin/env bash
# Downloads the pose2sim wheel (BSD-3-Clause) into .cache/pose2sim/ when no wheel is there: its demo videos
# and calibration are the real-video test data of the detector. Never committed; the camera set-up step may
# have fetched the same wheel into the same place already, in which case this does nothing.
set -euo pipefail
dir=.cache/pose2sim
if compgen -G "$dir/pose2sim-*.whl" >/dev/null; then
    exit 0
fi
mkdir -p "$dir"
.venv/bin/python -m pip download -q --disable-pip-version-check --no-deps -d "$dir" "pose2sim==0.10.49"
