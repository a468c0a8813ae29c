#!/usr/bin/env bash
# profile: test
# Installs Pose2Sim 0.10.49 (BSD-3-Clause) into .venv for `mocapd eval video` (docs/accuracy-video.md), from the
# wheel step 21 downloaded, without its dependencies: they would replace the headless OpenCV (opencv-python,
# opencv-contrib-python) and pull in opensim, PySide6, rtmlib, openvino and caliscope, none of which the steps the
# evaluation runs (person association, triangulation, filtering) import. What those steps import is the [eval]
# extra of pyproject.toml, installed with the dev tools by step 10.
set -euo pipefail
version=0.10.49
if .venv/bin/python -c "import importlib.metadata as m, sys; sys.exit(m.version('pose2sim') != '$version')" 2>/dev/null; then
    exit 0
fi
wheel="$(.venv/bin/python -c 'from mocapd.io.model_cache import cache_dir; print(cache_dir() / "pose2sim")')/pose2sim-$version-py3-none-any.whl"
if [ ! -f "$wheel" ]; then
    echo "pose2sim wheel $wheel missing (setup/steps/21-pose2sim-demo.sh downloads it)" >&2
    exit 1
fi
echo "installing pose2sim $version (no dependencies) for mocapd eval video" >&2
.venv/bin/python -m pip install -q --no-deps "$wheel"
