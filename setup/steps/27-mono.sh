#!/usr/bin/env bash
# profile: test
# Installs Debian's Mono C# compiler and runtime (issue 33), only where missing: the Unity receiver in
# tools/clients/unity is compiled with mcs against a minimal stand-in for the UnityEngine types it uses and run under
# mono against the real daemon (tests/test_unity_client.py). Not a runtime dependency of mocapd.
# mono-mcs brings mono-runtime and the core class libraries; System.Runtime.Serialization holds the JSON reader the
# stand-in's JsonUtility uses.
set -euo pipefail
if ! command -v mcs >/dev/null 2>&1 || ! command -v mono >/dev/null 2>&1 \
        || [ ! -e /usr/lib/mono/4.5/System.Runtime.Serialization.dll ]; then
    echo "installing Debian packages: mono-mcs libmono-system-runtime-serialization4.0-cil" >&2
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends mono-mcs \
        libmono-system-runtime-serialization4.0-cil >/dev/null
fi
