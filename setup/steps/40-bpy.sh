#!/usr/bin/env bash
# profile: test
# Creates .venv-bpy/ with Blender as a Python module (the `bpy` wheel from PyPI), for the tests only (issue 16):
# the glTF/BVH exports are imported into real Blender, and the Blender live-link add-on runs in it against a
# running daemon. bpy is not a runtime dependency of mocapd. It lives in a venv of its own because every bpy wheel
# pins numpy < 2 while mocapd's venv has numpy 2; the tests run Blender as a separate process, as a user does.
# bpy 4.5 is Blender's 4.5 LTS; its wheel is cp311 (manylinux_2_28 x86_64), the Python of .venv.
set -euo pipefail
want="bpy==4.5.15"
venv=.venv-bpy
py="${PYTHON:-python3}"
if [ -x "$venv/bin/python" ] && [ "$(cat "$venv/.mocapd-installed" 2>/dev/null)" = "$want" ]; then
    exit 0
fi
if ! "$py" -c 'import sys; assert sys.version_info[:2] == (3, 11)' 2>/dev/null; then
    echo "the bpy wheel needs Python 3.11 (found: $("$py" --version 2>&1)); set PYTHON=python3.11" >&2
    exit 1
fi
rm -rf "$venv"
"$py" -m venv "$venv"
echo "installing $want into $venv (Blender as a Python module, for the tests)" >&2
"$venv/bin/python" -m pip install -q "$want"
# The wheel's libraries need a few X/GL client libraries even headless (no display is opened).
if ! "$venv/bin/python" -c 'import bpy' 2>/dev/null; then
    echo "installing Debian packages for bpy: libxi6 libxxf86vm1 libxfixes3 libxrender1 libxkbcommon0 libsm6 libgl1 libegl1" >&2
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libxi6 libxxf86vm1 libxfixes3 libxrender1 libxkbcommon0 \
        libsm6 libgl1 libegl1 >/dev/null
    "$venv/bin/python" -c 'import bpy'
fi
echo "$want" > "$venv/.mocapd-installed"
