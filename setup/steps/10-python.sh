#!/usr/bin/env bash
# Creates .venv/ (Python >= 3.11) and installs mocapd in editable mode with its dev tools and the [train] extra
# (CPU PyTorch, for the learned-fusion training test; the daemon itself never imports it).
# Re-installs only when pyproject.toml changed since the last successful install.
set -euo pipefail
py="${PYTHON:-python3}"
if ! "$py" -c 'import sys; assert sys.version_info >= (3, 11)' 2>/dev/null; then
    echo "mocapd needs Python >= 3.11 (found: $("$py" --version 2>&1))" >&2
    exit 1
fi
if [ ! -x .venv/bin/python ]; then
    if ! "$py" -m venv .venv 2>/dev/null; then
        # Debian ships venv/ensurepip separately.
        rm -rf .venv
        echo "installing python3-venv (Debian)" >&2
        apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq python3-venv python3-dev >/dev/null
        "$py" -m venv .venv
    fi
fi
stamp=.venv/.mocapd-installed
want="$(sha256sum pyproject.toml | cut -d' ' -f1)"
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
    .venv/bin/python -m pip install -q --upgrade pip >/dev/null
    .venv/bin/python -m pip install -q -e ".[dev,train]"
    echo "$want" > "$stamp"
fi
