#!/usr/bin/env bash
# profile: test
# Installs Debian's Chromium (issue 9), only where missing: the live web viewer's tests load the page in real
# headless Chromium and drive it over the Chrome DevTools Protocol (tests/test_web_viewer.py).
set -euo pipefail
if [ ! -x /usr/bin/chromium ]; then
    echo "installing Debian package: chromium" >&2
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null
fi
