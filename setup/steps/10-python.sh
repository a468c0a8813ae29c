#!/usr/bin/env bash
# profile: demo
# Creates .venv/ (Python >= 3.11) and installs mocapd in editable mode: `-e .` alone for the demo profile (the
# daemon's runtime dependencies), `-e ".[dev,train]"` for the test profile (the dev tools, and the [train] extra's
# CPU PyTorch for the learned-fusion training test; the daemon itself never imports it).
# The stamp .venv/.mocapd-installed records pyproject.toml's sha256 and the profile installed ("<sha256> <profile>";
# a stamp with the sha256 alone is from before the profiles, which always installed the test extras). Re-installs
# when pyproject.toml changed, or when a venv made for the demo is now wanted for the tests; a test venv serves the
# demo as it is.
# MOCAPD_SETUP_PLAN=1: print the pip requirement this run would install (nothing when the venv is current) and
# change nothing (tests/test_setup_profiles.py).
set -euo pipefail
profile="${MOCAPD_PROFILE:-test}"
case "$profile" in
    demo) spec="-e ." ;;
    test) spec="-e .[dev,train]" ;;
    *)
        echo "10-python.sh: unknown profile '$profile' (demo or test)" >&2
        exit 2
        ;;
esac
stamp=.venv/.mocapd-installed
sha="$(sha256sum pyproject.toml | cut -d' ' -f1)"
have_sha="" have_profile=""
if [ -f "$stamp" ]; then
    read -r have_sha have_profile < "$stamp" || true
fi
have_profile="${have_profile:-test}"
current=0
if [ -x .venv/bin/python ] && [ "${have_sha:-}" = "$sha" ] \
        && { [ "$have_profile" = test ] || [ "$profile" = demo ]; }; then
    current=1
fi
if [ "${MOCAPD_SETUP_PLAN:-0}" = 1 ]; then
    if [ "$current" = 0 ]; then
        echo "$spec"
    fi
    exit 0
fi
if [ "$current" = 1 ]; then
    exit 0
fi
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
.venv/bin/python -m pip install -q --upgrade pip >/dev/null
# shellcheck disable=SC2086  # $spec is "-e <requirement>": two words on purpose
.venv/bin/python -m pip install -q $spec
echo "$sha $profile" > "$stamp"
