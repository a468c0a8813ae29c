#!/usr/bin/env bash
# profile: demo
# Installs what mocapd's camera layer needs (issue 5), only where missing:
#  - Aravis 0.8 with its GObject-introspection typelib and tools (Debian packages);
#  - the headers PyGObject is built against (girepository-1.0, cairo, glib) and a C compiler;
#  - iproute2 (`ip`) and util-linux (`unshare`), used to give each fake GigE camera its own loopback address
#    inside a private network namespace;
#  - PyGObject < 3.51 into .venv (3.51+ needs girepository-2.0, which Debian 12 does not have).
set -euo pipefail
apt_pkgs=(gir1.2-aravis-0.8 aravis-tools libgirepository1.0-dev libcairo2-dev libglib2.0-dev pkg-config gcc
    python3-dev iproute2 util-linux)
missing=()
for p in "${apt_pkgs[@]}"; do
    if ! dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed"; then
        missing+=("$p")
    fi
done
if [ "${#missing[@]}" -gt 0 ]; then
    echo "installing Debian packages: ${missing[*]}" >&2
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi
if ! .venv/bin/python -c 'import gi; gi.require_version("Aravis", "0.8"); from gi.repository import Aravis' \
    2>/dev/null; then
    echo "installing PyGObject (<3.51) into .venv" >&2
    .venv/bin/python -m pip install -q "pygobject>=3.42,<3.51"
fi
# GigE Vision streams arrive as bursts of UDP packets: the receive buffer must hold several frames or a
# descheduled capture thread loses whole frames (Aravis and camera vendors recommend raising rmem_max).
# Raised here (until reboot) where we may; persistent installs: /etc/sysctl.d/ (see docs/cameras.md).
want_rmem=26214400
have_rmem=$(cat /proc/sys/net/core/rmem_max 2>/dev/null || echo 0)
if [ "$have_rmem" -lt "$want_rmem" ]; then
    if (echo "$want_rmem" > /proc/sys/net/core/rmem_max) 2>/dev/null; then
        echo "raised net.core.rmem_max from $have_rmem to $want_rmem (GigE Vision socket buffers)" >&2
    else
        echo "warning: net.core.rmem_max is $have_rmem and cannot be raised here; GigE cameras may lose frames" >&2
    fi
fi
