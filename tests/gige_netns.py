"""Runs inside a private network namespace (``unshare -rn python -m tests.gige_netns OUT_DIR``): a camera network
of fake GigE Vision cameras, discovery and ``mocapd devices`` against it. Prints one JSON object of what happened
for tests/test_gige_discovery.py to check.

Network (:class:`mocapd.sim.gige_network.FakeGigENetwork`): link ``gige1`` with cameras CAM-A (10.77.1.2) and
CAM-B (10.77.1.3), link ``gige2`` with CAM-C (10.77.2.2), and CAM-LO on 127.0.0.1 in this namespace itself. Every
packet counted is a packet this namespace sent out of an interface.
"""

from __future__ import annotations

import contextlib
import functools
import io
import json
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from mocapd.errors import DeviceError
from mocapd.io.aravis_camera import AravisCameraConfig, load_aravis, open_camera
from mocapd.io.gige_discovery import discover
from mocapd.service.cli import main as cli_main
from mocapd.sim.fake_gige import server_command
from mocapd.sim.gige_network import FakeGigENetwork

LINKS = {"gige1": ["CAM-A", "CAM-B"], "gige2": ["CAM-C"]}
COUNTED = ("lo", "gige1", "gige2")


def _video(folder: Path) -> Path:
    path = folder / "tiny.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), 10, (64, 48))
    for i in range(2):
        writer.write(np.full((48, 64, 3), 60 * i, np.uint8))
    writer.release()
    return path


def _sent_during(action: Callable[[], Any]) -> tuple[Any, dict[str, int]]:
    before = {link: FakeGigENetwork.tx_packets(link) for link in COUNTED}
    result = action()
    return result, {link: FakeGigENetwork.tx_packets(link) - before[link] for link in COUNTED}


def _open(**kw: str) -> dict[str, Any]:
    """Open a camera as configured and say which one answered, or the error."""
    try:
        camera = open_camera(AravisCameraConfig("cam", **kw))  # type: ignore[arg-type]
    except DeviceError as exc:
        return {"error": str(exc)}
    device = camera.get_device()
    address = device.get_device_address().to_string() if camera.is_gv_device() else None
    return {"serial": camera.get_device_serial_number(), "address": address}


def _cli(*args: str) -> tuple[int, dict[str, Any]]:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        code = cli_main(["devices", *args, "--json"])
    return code, json.loads(out.getvalue())


def main(out_dir: Path) -> dict[str, Any]:
    video = _video(out_dir)
    result: dict[str, Any] = {}
    aravis = load_aravis()
    aravis.enable_interface("Fake")  # stands in for a USB3 Vision camera
    with FakeGigENetwork(video, LINKS) as net:
        lo_cam = subprocess.Popen(
            server_command(video, "127.0.0.1", 2, "Mono8", serial="CAM-LO", size="64x48"),
            stdout=subprocess.PIPE,
            text=True,
        )
        try:
            assert lo_cam.stdout is not None and '"ready": true' in lo_cam.stdout.readline()
            result["network"] = [{"link": c.link, "serial": c.serial, "address": c.address} for c in net.cameras]
            try:
                FakeGigENetwork(video, {"gige3": ["CAM-D"]}).start()
                result["second_network"] = "started"
            except DeviceError as exc:
                result["second_network"] = str(exc)
            for link in LINKS:
                found, sent = _sent_during(functools.partial(discover, link, 0.5))
                result[f"discover_{link}"] = {
                    "cameras": sorted((c.ack.serial, c.address, c.device_id) for c in found.cameras),
                    "counters": found.counters.as_dict(),
                    "sent": sent,
                }
            result["open_by_serial"] = _open(serial="CAM-B", interface="gige1")
            result["open_by_device_id"] = _open(device_id="Aravis-Fake-CAM-C", interface="gige2")
            result["open_on_wrong_link"] = _open(serial="CAM-C", interface="gige1")
            result["open_unknown_interface"] = _open(serial="CAM-A", interface="nope0")
            result["open_without_interface"], result["open_without_interface_sent"] = _sent_during(
                lambda: (_open(serial="CAM-A"), _open(device_id="Aravis-Fake-CAM-LO"))
            )
            result["open_fake_usb"] = _open(device_id="Fake_1")
            (code, listed), sent = _sent_during(_cli)
            result["cli_plain"] = {"code": code, "json": listed, "sent": sent}
            (code, listed), sent = _sent_during(lambda: _cli("--gige-interface", "gige1", "--gige-interface", "gige2"))
            result["cli_gige"] = {"code": code, "json": listed, "sent": sent}
            code, listed = _cli("--gige-interface", "nope0", "--timeout", "0.2")
            result["cli_bad_interface"] = {"code": code, "problems": listed["problems"]}
            # What Aravis' own discovery would do: broadcast on every interface here and find every camera. Shows
            # that the checks above (nothing found, nothing sent without an interface) could fail.
            aravis.enable_interface("GigEVision")
            aravis.update_device_list()
            result["aravis_own_discovery"] = sorted(
                aravis.get_device_id(i) for i in range(aravis.get_n_devices()) if "Fake_" not in aravis.get_device_id(i)
            )
            aravis.disable_interface("GigEVision")
        finally:
            lo_cam.terminate()
            lo_cam.wait(timeout=10)
            if lo_cam.stdout is not None:
                lo_cam.stdout.close()
    return result


if __name__ == "__main__":
    print(json.dumps(main(Path(sys.argv[1]))), flush=True)
