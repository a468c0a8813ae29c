#!/usr/bin/env bash
# Fetches the BlazePose GHUM landmark models (heavy, full) for [detector] landmarks: the npm package
# @mediapipe/pose (Apache-2.0, pinned version; `npm pack` with the ordinary npm client), whose tarball's and models'
# sha256 are pinned in mocapd/io/landmark_build.py. Writes ~/.cache/mocapd/models/pose_landmark_{heavy,full}.tflite
# (+ sidecar JSON with the licence) when a file is missing or does not match its sidecar; LiteRT (the PyPI package
# ai-edge-litert, a mocapd dependency) runs them as they are. Needs npm (26-node-clients.sh installs it).
set -euo pipefail
if .venv/bin/python -c 'import sys
from mocapd.io.landmark_build import VARIANTS, landmark_model_is_current
from mocapd.io.model_cache import landmark_model_path
sys.exit(0 if all(landmark_model_is_current(landmark_model_path(v), v) for v in VARIANTS) else 1)'; then
    exit 0
fi
echo "fetching the BlazePose landmark models (@mediapipe/pose, ~41 MB)" >&2
.venv/bin/python - <<'PY'
from mocapd.io.landmark_build import build_landmark_models

build_landmark_models()
PY
