#!/usr/bin/env bash
# profile: test
# The GigE Vision discovery tests (issue 13) put fake cameras behind veth pairs inside private network
# namespaces (`unshare -rn`). A user namespace cannot load kernel modules itself on every kernel: where veth is
# a module that is not loaded yet, load it here (as root). Nothing to do where veth pairs can already be made.
set -euo pipefail
if unshare -rn ip link add mocapd-probe0 type veth peer name mocapd-probe1 2>/dev/null; then
    exit 0  # the namespace, and the pair with it, is gone again
fi
if [ "$(id -u)" = 0 ] && command -v modprobe >/dev/null && modprobe veth 2>/dev/null; then
    echo "loaded the veth kernel module (GigE discovery tests)" >&2
    exit 0
fi
echo "warning: veth pairs cannot be made in a private network namespace here; tests/test_gige_discovery.py will fail" >&2
