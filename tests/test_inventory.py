"""The config snippet and listings of ``mocapd devices`` from an inventory of every kind of device: the TOML
parses with the project's config loaders, names are valid and unique, each camera is opened the right way."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path
from typing import Any

from mocapd.io.aravis_devices import AravisDevice
from mocapd.io.gige_discovery import GigECamera, InterfaceAddress
from mocapd.io.v4l_devices import VideoDevice
from mocapd.io.xsens_probe import ProbeResult, SerialPort
from mocapd.protocols.gvcp import DiscoveryAck, IpConfig
from mocapd.protocols.xsens_session import DeviceInfo
from mocapd.service.cli.devices import render_tables
from mocapd.service.config import parse_config
from mocapd.service.config.cameras import AravisCamera, UvcCamera, parse_cameras
from mocapd.service.inventory import Inventory, camera_name, config_snippet, inventory_json
from tests.config_support import check_config

ETH1 = InterfaceAddress("eth1", "192.168.10.1", "255.255.255.0", "192.168.10.255")


def _gige(serial: str, ip: str, current: IpConfig, user_name: str = "") -> GigECamera:
    ack = DiscoveryAck(
        ack_id=1, spec_version=(2, 0), device_mode=1 << 31 | 1, mac="00:30:53:11:ab:cd",
        ip_config_supported=IpConfig(7), ip_config_current=current, ip=ip, subnet="255.255.255.0",
        gateway="0.0.0.0", manufacturer="Basler", model="acA1920-155um", device_version="106755-11",
        manufacturer_info="none", serial=serial, user_name=user_name,
    )  # fmt: skip
    return GigECamera(ack, ip, ETH1)


def _inventory() -> Inventory:
    usb = AravisDevice("USB3Vision", "Basler-acA1920-40um-22334455", "Basler", "acA1920-40um", "22334455", "2-1")
    return Inventory(
        aravis=[usb, AravisDevice("Fake", "Fake_1", "Aravis", "Fake", "1", "Fake_1")],
        gige=[
            _gige("40012345", "192.168.10.11", IpConfig.PERSISTENT),
            _gige("40012346", "169.254.3.7", IpConfig.LLA),
            _gige("40012347", "192.168.10.13", IpConfig.DHCP, user_name="left cam #2"),
        ],
        gige_counters={"eth1": {"acks": 3}},
        uvc=[
            VideoDevice(
                "/dev/video0", "HD Pro Webcam C920", "/dev/v4l/by-id/usb-046d_C920_AB-video-index0", "046d:082d", "AB"
            ),
            VideoDevice("/dev/video2", "HD Pro Webcam C920", "", "046d:082d", ""),
        ],
        serial=[
            ProbeResult(
                SerialPort("/dev/ttyUSB0", "/dev/serial/by-id/usb-Xsens_MTi-630-if00", "2639:0300", ""),
                DeviceInfo(0x00B40042, "MTi-630", "1.12.3"),
            ),
            ProbeResult(SerialPort("/tmp/imu1", "", "", ""), DeviceInfo(0x00B421E6, 'MTw2-3A7G6 "x"', "4.6.0")),
            ProbeResult(SerialPort("/dev/ttyUSB3", "", "2639:0300", ""), None, "no Xsens device answered"),
        ],
        problems=["serial /dev/ttyUSB3: no Xsens device answered"],
    )


def _cameras_by_name(snippet: str) -> dict[str, Any]:
    data = tomllib.loads(snippet)
    return {c.name: c for c in parse_cameras(data["cameras"])}


def test_snippet_parses_and_opens_each_camera_the_right_way() -> None:
    snippet = config_snippet(_inventory())
    cams = _cameras_by_name(snippet)
    assert list(cams) == ["acA1920-40um-22334455", "Fake-1", "acA1920-155um-40012345", "acA1920-155um-40012346",
                          "left_cam_2-40012347", "HD_Pro_Webcam_C920-AB", "HD_Pro_Webcam_C920"]  # fmt: skip
    usb = cams["acA1920-40um-22334455"]
    assert isinstance(usb, AravisCamera) and (usb.serial, usb.interface, usb.address) == ("22334455", "", "")
    assert cams["Fake-1"].device_id == "Fake_1"
    fixed = cams["acA1920-155um-40012345"]  # persistent IP: opened by address, no broadcast
    assert (fixed.address, fixed.serial, fixed.interface) == ("192.168.10.11", "", "")
    for name in ("acA1920-155um-40012346", "left_cam_2-40012347"):  # link-local / DHCP: found by serial on eth1
        assert (cams[name].address, cams[name].interface) == ("", "eth1")
    assert cams["left_cam_2-40012347"].serial == "40012347"
    webcam = cams["HD_Pro_Webcam_C920-AB"]
    assert isinstance(webcam, UvcCamera) and webcam.device == "/dev/v4l/by-id/usb-046d_C920_AB-video-index0"
    assert cams["HD_Pro_Webcam_C920"].device == "/dev/video2"
    # The other way to open each GigE camera is there, commented out.
    assert '# serial = "40012345"\n# interface = "eth1"' in snippet
    assert '# address = "169.254.3.7"' in snippet


def test_check_config_accepts_the_snippet(tmp_path: Path) -> None:
    # check-config also checks that a named interface exists on this machine: the inventory's "eth1" stands in
    # for a camera network card, so it is renamed to the loopback interface every machine has.
    snippet = config_snippet(_inventory()).replace('interface = "eth1"', 'interface = "lo"')
    code, printed = check_config(snippet, tmp_path)
    assert code == 0, printed
    assert "7 camera(s)" in printed and "2 serial IMU port(s)" in printed


def test_snippet_imu_section_loads_with_the_config_loader() -> None:
    snippet = config_snippet(_inventory())
    config = parse_config(tomllib.loads(snippet))  # the whole snippet, [[cameras]] and [imu]
    assert list(config.imu.ports) == ["/dev/serial/by-id/usb-Xsens_MTi-630-if00", "/tmp/imu1"]
    assert len(config.cameras) == 7
    assert config.imu.assignment == {}  # placeholders are comments until the user picks the bones
    assert '# "00B40042" = "<bone>"' in snippet and '# "00B421E6" = "<bone>"' in snippet
    # Uncommenting a placeholder with a bone gives a valid assignment.
    filled = snippet.replace('# "00B40042" = "<bone>"', '"00B40042" = "Hips"')
    assert parse_config({"imu": tomllib.loads(filled)["imu"]}).imu.assignment == {"00B40042": "Hips"}


def test_what_devices_say_cannot_inject_config_or_terminal_escapes() -> None:
    evil = AravisDevice("USB3Vision", "id", "Evil\n[daemon]\nrig = 'x'", "M\x1b[2J", "S\n1", "1-1")
    inv = Inventory(aravis=[evil])
    cams = _cameras_by_name(config_snippet(inv))
    assert set(tomllib.loads(config_snippet(inv))) == {"cameras"}
    assert [c.serial for c in cams.values()] == ["S\n1"]  # the value itself is escaped, not altered
    table = render_tables(inv)
    assert "\x1b" not in table and "Evil?[daemon]?rig" in table


def test_nothing_found() -> None:
    snippet = config_snippet(Inventory())
    assert "no cameras or Xsens devices found" in snippet and tomllib.loads(snippet) == {}


def test_camera_names() -> None:
    assert camera_name("acA1920-155um", "40012345") == "acA1920-155um-40012345"
    assert camera_name("HD Pro Webcam C920", "") == "HD_Pro_Webcam_C920"
    assert camera_name("Ünïcode / model", "S/N 7") == "Unicode_model-S_N_7"
    assert camera_name("", "  ") == "camera"
    long = camera_name("A very long camera model name indeed", "SERIAL-0123456789")
    assert long == "A_very_long_ca-SERIAL-0123456789" and len(long) == 32
    assert camera_name("m", "x" * 40) == "x" * 32


def test_json_has_every_device_and_the_snippet() -> None:
    out = inventory_json(_inventory())
    json.dumps(out)  # plain JSON values only
    assert [g["serial"] for g in out["gige"]] == ["40012345", "40012346", "40012347"]
    assert out["gige"][1]["ip_config"] == "lla" and out["gige"][0]["device_id"] == "Basler-acA1920-155um-40012345"
    assert out["serial"][0]["device_id"] == "00B40042" and out["serial"][2]["error"] == "no Xsens device answered"
    assert out["uvc"][0]["usb_id"] == "046d:082d" and out["aravis"][0]["protocol"] == "USB3Vision"
    assert out["snippet"] == config_snippet(_inventory())


def test_tables_list_every_device_and_say_none_for_empty_kinds() -> None:
    table = render_tables(_inventory(), searched=("eth1", "eth2"))
    lines = table.splitlines()
    assert lines[0].startswith("Aravis cameras (USB3 Vision")
    assert "USB3Vision  Basler-acA1920-40um-22334455  Basler" in table
    gige = lines.index("GigE Vision cameras on eth1:")
    assert lines[gige + 2].split()[:5] == ["192.168.10.11", "00:30:53:11:ab:cd", "Basler", "acA1920-155um", "40012345"]
    assert lines[lines.index("GigE Vision cameras on eth2:") + 1] == "  none"
    assert any(line.split()[:3] == ["/dev/video0", "HD", "Pro"] for line in lines)
    assert any(line.split()[:4] == ["/dev/ttyUSB0", "00B40042", "MTi-630", "1.12.3"] for line in lines)
    assert any("/dev/ttyUSB3" in line and "no answer: no Xsens device answered" in line for line in lines)
    empty = render_tables(Inventory())
    assert empty.count("  none") == 3 and "GigE Vision cameras on" not in empty
