#!/usr/bin/env python3
"""Forward Xsens MTw Awinda sensors from the vendor SDK to mocapd's IMU bridge input (UDP, msgpack).

UNTESTED HERE: this script needs the proprietary Xsens Device API Python bindings (``xsensdeviceapi``, shipped
with MT Software Suite) and real hardware, neither of which the project can install or run in CI. It follows
the Awinda example that ships with the SDK; check the names against your SDK version. The receiving side
(format, listener) is tested in mocapd (``tests/test_imu_bridge.py``).

Usage (on the machine that has the Awinda station, next to mocapd)::

    python tools/xsens_sdk_bridge.py --rate 60 --channel 19 --port 9773

Each live packet becomes one record ``{"v": 1, "id", "t", "q", "a", "frame": "ENU", "pc"}`` (see
``mocapd/protocols/imu_bridge.py``), sent to 127.0.0.1 only.
"""

from __future__ import annotations

import argparse
import socket
import sys
import threading
import time
from typing import Any

import msgpack


def _record(device_id: str, packet: Any) -> dict[str, object] | None:
    if not (packet.containsOrientation() and packet.containsCalibratedAcceleration()):
        return None
    q = packet.orientationQuaternion()  # XsQuaternion: w, x, y, z, device frame ENU by default
    a = packet.calibratedAcceleration()
    record: dict[str, object] = {
        "v": 1,
        "id": device_id,
        "t": packet.sampleTimeFine() / 10_000.0 if packet.containsSampleTimeFine() else time.monotonic(),
        "q": [float(q[0]), float(q[1]), float(q[2]), float(q[3])],
        "a": [float(a[0]), float(a[1]), float(a[2])],
        "frame": "ENU",
    }
    if packet.containsPacketCounter():
        record["pc"] = int(packet.packetCounter())
    return record


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rate", type=int, default=60, help="Awinda update rate, Hz (60, 75, 80, 100, 120 ...)")
    ap.add_argument("--channel", type=int, default=19, help="radio channel 11..25")
    ap.add_argument("--port", type=int, default=9773, help="mocapd imu.bridge.port")
    ap.add_argument("--sensors", type=int, default=0, help="wait until this many MTws are connected")
    args = ap.parse_args(argv)

    import xsensdeviceapi as xda  # the vendor SDK; not installable from a public registry

    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    target = ("127.0.0.1", args.port)
    lock = threading.Lock()

    class Forwarder(xda.XsCallback):  # type: ignore[misc]
        def onLiveDataAvailable(self, dev: Any, packet: Any) -> None:  # noqa: N802 (SDK callback name)
            rec = _record(dev.deviceId().toXsString(), packet)
            if rec is not None:
                with lock:
                    sock.sendto(msgpack.packb(rec), target)

    control = xda.XsControl_construct()
    ports = xda.XsScanner_scanPorts()
    station = next((p for p in ports if p.deviceId().isWirelessMaster()), None)
    if station is None:
        print("no Awinda station found", file=sys.stderr)
        return 1
    if not control.openPort(station.portName(), station.baudrate()):
        print(f"cannot open {station.portName()}", file=sys.stderr)
        return 1
    master = control.device(station.deviceId())
    master.gotoConfig()
    master.setUpdateRate(args.rate)
    master.enableRadio(args.channel)
    print("switch the MTws on; waiting for them to connect ...", flush=True)
    while len(master.children()) < max(args.sensors, 1):
        time.sleep(0.5)
    forwarder = Forwarder()
    for child in master.children():
        child.addCallbackHandler(forwarder)
    master.gotoMeasurement()
    print(f"forwarding {len(master.children())} sensors to udp {target}", flush=True)
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    master.gotoConfig()
    master.disableRadio()
    control.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
