"""GigE Vision discovery on one named interface, against real Aravis fake cameras behind veth links in a private
network namespace (tests/gige_netns.py), and the names Aravis gives cameras.

Every packet that could be broadcast stays in namespaces these tests create: the end-to-end run is under
``unshare -rn``, and the tests here in the host namespace only read interface tables.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tomllib
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from mocapd.errors import DeviceError
from mocapd.io.gige_discovery import (
    GigECamera,
    InterfaceAddress,
    aravis_device_id,
    aravis_names,
    discover,
    find_camera,
    interface_ipv4,
)
from mocapd.protocols.gvcp import DiscoveryAck, parse_discovery_ack
from mocapd.service.config.cameras import parse_cameras
from tests.config_support import check_config

ROOT = Path(__file__).resolve().parents[1]
ACK = parse_discovery_ack((ROOT / "tests" / "data" / "gvcp" / "aravis_fake_discovery_ack.bin").read_bytes())


@pytest.fixture(scope="module")
def netns(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    out = tmp_path_factory.mktemp("gige_netns")
    proc = subprocess.run(
        ["unshare", "-rn", sys.executable, "-m", "tests.gige_netns", str(out)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    result: dict[str, Any] = json.loads(proc.stdout.strip().splitlines()[-1])
    return result


def _ack(**kw: Any) -> DiscoveryAck:
    assert isinstance(ACK, DiscoveryAck)
    return replace(ACK, **kw)


def test_discovery_finds_the_cameras_of_its_link_and_sends_nothing_elsewhere(netns: dict[str, Any]) -> None:
    one, two = netns["discover_gige1"], netns["discover_gige2"]
    assert one["cameras"] == [["CAM-A", "10.77.1.2", "Aravis-Fake-CAM-A"], ["CAM-B", "10.77.1.3", "Aravis-Fake-CAM-B"]]
    assert two["cameras"] == [["CAM-C", "10.77.2.2", "Aravis-Fake-CAM-C"]]
    # Two commands went out of the named link (plus ARP at most), not one packet out of the other.
    assert 2 <= one["sent"]["gige1"] <= 3 and one["sent"]["gige2"] == 0
    assert 2 <= two["sent"]["gige2"] <= 3 and two["sent"]["gige1"] == 0
    # Each camera answered both commands: counted once, the second as a duplicate. CAM-LO (a program on this
    # host) heard the broadcast too and answered: its answers are in the counters, not among the cameras.
    assert one["counters"]["duplicates"] == one["counters"]["acks"] == 3
    assert one["counters"]["truncated"] == one["counters"]["malformed"] == one["counters"]["unknown_id"] == 0


def test_the_fake_network_is_made_only_in_a_fresh_namespace(netns: dict[str, Any]) -> None:
    assert netns["network"] == [
        {"link": "gige1", "serial": "CAM-A", "address": "10.77.1.2"},
        {"link": "gige1", "serial": "CAM-B", "address": "10.77.1.3"},
        {"link": "gige2", "serial": "CAM-C", "address": "10.77.2.2"},
    ]
    assert "must run in a fresh private network namespace" in netns["second_network"]
    assert "['gige1', 'gige2']" in netns["second_network"]


def test_the_checks_could_fail_aravis_own_discovery_finds_everything(netns: dict[str, Any]) -> None:
    assert netns["aravis_own_discovery"] == [f"Aravis-Fake-CAM-{c}" for c in ("A", "B", "C", "LO")]


def test_open_camera_by_serial_or_device_id_on_its_interface(netns: dict[str, Any]) -> None:
    assert netns["open_by_serial"] == {"serial": "CAM-B", "address": "10.77.1.3:3956"}
    assert netns["open_by_device_id"] == {"serial": "CAM-C", "address": "10.77.2.2:3956"}
    assert netns["open_fake_usb"] == {"serial": "1", "address": None}  # non-GigE: Aravis' own lookup
    wrong = netns["open_on_wrong_link"]["error"]
    assert "no GigE Vision camera with serial 'CAM-C' answered discovery on gige1" in wrong
    assert "Aravis-Fake-CAM-A at 10.77.1.2" in wrong and "CAM-LO" not in wrong
    assert "no network interface 'nope0' (there are: gige1, gige2, lo)" in netns["open_unknown_interface"]["error"]


def test_open_camera_without_interface_never_broadcasts(netns: dict[str, Any]) -> None:
    by_serial, by_id = netns["open_without_interface"]
    assert "no USB3 Vision device with serial 'CAM-A'" in by_serial["error"]
    assert "'Aravis-Fake-CAM-LO' not found" in by_id["error"]
    assert netns["open_without_interface_sent"] == {"lo": 0, "gige1": 0, "gige2": 0}


def test_devices_command_without_interface_lists_usb_only_and_sends_nothing(netns: dict[str, Any]) -> None:
    plain = netns["cli_plain"]
    assert plain["code"] == 0 and plain["sent"] == {"lo": 0, "gige1": 0, "gige2": 0}
    listed = plain["json"]
    assert [(d["protocol"], d["device_id"], d["serial"]) for d in listed["aravis"]] == [("Fake", "Fake_1", "1")]
    assert listed["gige"] == [] and listed["problems"] == []
    cameras = parse_cameras(_snippet_cameras(listed["snippet"]))
    assert [(c.name, c.source, getattr(c, "device_id", None)) for c in cameras] == [("Fake-1", "aravis", "Fake_1")]


def test_devices_command_with_interfaces_lists_each_link(netns: dict[str, Any], tmp_path: Path) -> None:
    gige = netns["cli_gige"]
    assert gige["code"] == 0
    assert gige["sent"]["gige1"] >= 2 and gige["sent"]["gige2"] >= 2
    found = [(c["interface"], c["serial"], c["address"], c["device_id"]) for c in gige["json"]["gige"]]
    assert found == [
        ("gige1", "CAM-A", "10.77.1.2", "Aravis-Fake-CAM-A"),
        ("gige1", "CAM-B", "10.77.1.3", "Aravis-Fake-CAM-B"),
        ("gige2", "CAM-C", "10.77.2.2", "Aravis-Fake-CAM-C"),
    ]
    assert gige["json"]["gige_counters"]["gige1"]["local_answers"] == 1
    code, printed = check_config(gige["json"]["snippet"], tmp_path)
    assert code == 0, printed
    cameras = parse_cameras(_snippet_cameras(gige["json"]["snippet"]))
    assert [(c.name, getattr(c, "address", "")) for c in cameras] == [
        ("Fake-1", ""), ("Fake-CAM-A", "10.77.1.2"), ("Fake-CAM-B", "10.77.1.3"), ("Fake-CAM-C", "10.77.2.2")
    ]  # fmt: skip
    bad = netns["cli_bad_interface"]
    assert bad["code"] == 1
    assert bad["problems"] == ["gige nope0: no network interface 'nope0' (there are: gige1, gige2, lo)"]


def _snippet_cameras(snippet: str) -> list[Any]:
    cameras: list[Any] = tomllib.loads(snippet)["cameras"]
    return cameras


def test_aravis_names_of_a_camera() -> None:
    ack = _ack(manufacturer="The Imaging Source Europe GmbH", model="DFK 33GX\x01", serial="123", user_name="left")
    assert aravis_device_id(ack) == "The Imaging Source Europe GmbH-DFK 33GX-123"
    assert aravis_names(ack) == {
        "The Imaging Source Europe GmbH-DFK 33GX-123",
        "The Imaging Source Europe GmbH-123",
        "TIS-123",
        "left",
        "00:00:00:00:00:00",
    }
    nameless = _ack(serial="", mac="00:30:53:11:ab:cd")
    assert aravis_device_id(nameless) == "Aravis-Fake-00:30:53:11:ab:cd"  # Aravis: the MAC stands in


def test_camera_matching() -> None:
    lo = InterfaceAddress("lo", "127.0.0.1", "255.0.0.0", "")
    cam = GigECamera(_ack(serial=" 40012345 "), "192.168.10.11", lo)
    assert cam.matches(serial="40012345") and not cam.matches(serial="4001234")
    assert cam.matches(device_id="Aravis-Fake- 40012345 ") and not cam.matches(device_id="nothing")
    assert not cam.matches()
    assert cam.address == "127.0.0.1"  # the address it reports
    assert GigECamera(_ack(ip="0.0.0.0"), "192.168.10.11", lo).address == "192.168.10.11"  # else where it spoke


def test_bad_arguments_and_interfaces_fail_before_sending() -> None:
    with pytest.raises(DeviceError, match="no network interface 'no-such-if0'"):
        interface_ipv4("no-such-if0")
    with pytest.raises(ValueError, match="timeout_s > 0"):
        discover("lo", 0.0)
    with pytest.raises(ValueError, match="exactly one of serial, device_id"):
        find_camera("lo", serial="a", device_id="b")
