#!/usr/bin/env bash
# Runs every set-up step in setup/steps/ in lexical order. Each step is idempotent and cheap when its
# work is already done, so `make test` and `make demo` can call this every time on a fresh machine.
# A step that fails stops the set-up with its name, so the technician sees which part is missing.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
cd "$here/.."
for step in "$here"/steps/*.sh; do
    if ! bash "$step"; then
        echo "mocapd set-up: step $(basename "$step") failed" >&2
        exit 1
    fi
done
