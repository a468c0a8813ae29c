#!/usr/bin/env bash
# profile: test
# Installs the Node.js example client's dependencies (issue 9: tools/clients/node, ws + @msgpack/msgpack from
# the committed package-lock.json) with `npm ci`, only when node_modules is missing or the lock file changed.
# Node.js >= 18 and npm come from Debian where missing (the tests run the client against the daemon).
set -euo pipefail
if ! command -v node >/dev/null || ! command -v npm >/dev/null; then
    echo "installing Debian packages: nodejs npm" >&2
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq nodejs npm >/dev/null
fi
cd tools/clients/node
stamp=node_modules/.mocapd-lock
want="$(sha256sum package-lock.json | cut -d' ' -f1)"
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
    echo "installing the Node.js client's packages (npm ci)" >&2
    npm ci --no-audit --no-fund --loglevel=error >/dev/null
    echo "$want" > "$stamp"
fi
