#!/usr/bin/env bash
# Runs the set-up steps in setup/steps/ of one profile, in lexical order. Each step is idempotent and cheap when
# its work is already done, so `make demo` and `make test` can call this every time on a fresh machine.
# A step that fails stops the set-up with its name, so the technician sees which part is missing.
#
#   bash setup/setup.sh [demo|test]        run the profile's steps (default: test, everything)
#   bash setup/setup.sh --list [demo|test] print the profile's steps, one file name a line, and run nothing
#
# Profiles: `demo` is what the daemon and `mocapd demo` need (mocapd and its runtime dependencies, Aravis, the
# Pose2Sim demo videos, the detector models); `test` is all of it plus the test stack (dev tools, the [train]
# extra's PyTorch, Pose2Sim, Chromium, Node.js, Mono, Blender's bpy...). Each step names its profile in a
# `# profile: demo` or `# profile: test` line; a step without one belongs to `test`. The profile reaches the
# steps as $MOCAPD_PROFILE (10-python.sh installs the dev and train extras only for `test`).
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
list=0
if [ "${1:-}" = "--list" ]; then
    list=1
    shift
fi
profile="${1:-test}"
case "$profile" in
    demo | test) ;;
    *)
        echo "mocapd set-up: unknown profile '$profile' (demo or test)" >&2
        exit 2
        ;;
esac

# The profile a step declares (demo or test).
step_profile() {
    local declared
    declared="$(sed -n 's/^# profile: *\([a-z]*\).*/\1/p' "$1" | head -n 1)"
    echo "${declared:-test}"
}

selected=()
for step in "$here"/steps/*.sh; do
    # `test` takes every step; `demo` only the steps that declare it.
    if [ "$profile" = test ] || [ "$(step_profile "$step")" = demo ]; then
        selected+=("$step")
    fi
done
if [ "$list" = 1 ]; then
    for step in "${selected[@]}"; do
        basename "$step"
    done
    exit 0
fi
cd "$here/.."
export MOCAPD_PROFILE="$profile"
for step in "${selected[@]}"; do
    if ! bash "$step"; then
        echo "mocapd set-up: step $(basename "$step") failed" >&2
        exit 1
    fi
done
