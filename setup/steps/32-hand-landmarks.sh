#!/usr/bin/env bash
# Fetches MediaPipe's hand landmark models (full, lite) for [detector] hands: the npm package @mediapipe/hands
# (Apache-2.0, pinned version; `npm pack` with the ordinary npm client), whose tarball's and models' sha256 are pinned
# in mocapd/io/hand_model_build.py. Writes ~/.cache/mocapd/models/hand_landmark_{full,lite}.tflite (+ sidecar JSON
# with the licence) when a file is missing or does not match its sidecar; LiteRT (ai-edge-litert, a mocapd
# dependency) runs them as they are. Needs npm (26-node-clients.sh installs it).
set -euo pipefail
if .venv/bin/python -c 'import sys
from mocapd.io.hand_model_build import VARIANTS, hand_model_is_current
from mocapd.io.model_cache import hand_model_path
sys.exit(0 if all(hand_model_is_current(hand_model_path(v), v) for v in VARIANTS) else 1)'; then
    exit 0
fi
echo "fetching the hand landmark models (@mediapipe/hands, ~13 MB)" >&2
.venv/bin/python - <<'PY'
from mocapd.io.hand_model_build import build_hand_models

build_hand_models()
PY
