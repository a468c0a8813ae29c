#!/usr/bin/env bash
# profile: test
# The Zenoh TLS test (tests/test_camera_hosts.py) makes a throw-away CA and certificate with the openssl command.
set -euo pipefail
if ! command -v openssl >/dev/null; then
    echo "installing openssl (Zenoh TLS test certificates)" >&2
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends openssl >/dev/null
fi
