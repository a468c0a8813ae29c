"""Asking a serial port what Xsens device is on it: simulated devices on real pseudo-terminals, a silent port, a
missing one."""

from __future__ import annotations

import os
import tty
from collections.abc import Iterator
from pathlib import Path

import pytest
from serial.tools.list_ports_common import ListPortInfo

from mocapd.errors import DeviceError, DeviceTimeout
from mocapd.io.xsens_probe import SerialPort, port_for_path, probe_ports, probe_xsens, xsens_ports
from mocapd.protocols.xsens_session import DeviceInfo
from mocapd.sim import xsens as xsens_sim


@pytest.fixture
def sim(tmp_path: Path) -> Iterator[xsens_sim.XsensSimulator]:
    device = xsens_sim.SimDevice(xsens_sim.synthetic_motion(device_id=0x00B40042), product_code="MTi-630",
                                 firmware=(1, 12, 3))  # fmt: skip
    started = xsens_sim.XsensSimulator(tmp_path / "imu0", device).start()
    yield started
    started.stop()


@pytest.fixture
def silent_pty() -> Iterator[str]:
    """A pseudo-terminal nobody answers on (a port with something else, or nothing, behind it)."""
    master, slave = os.openpty()
    tty.setraw(slave)
    yield os.ttyname(slave)
    os.close(master)
    os.close(slave)


@pytest.mark.asyncio
async def test_a_streaming_device_says_what_it_is_and_stays_in_config_mode(sim: xsens_sim.XsensSimulator) -> None:
    info = await probe_xsens(str(sim.link), response_timeout_s=0.5)
    assert info == DeviceInfo(0x00B40042, "MTi-630", "1.12.3")
    assert info.serial == "00B40042"
    asked = sim.device.stats.requests
    assert {"GOTO_CONFIG", "REQ_DID", "REQ_PRODUCT_CODE", "REQ_FW_REV"} <= set(asked)
    assert "SET_OUTPUT_CONFIGURATION" not in asked and "GOTO_MEASUREMENT" not in asked
    assert not sim.device.measuring


@pytest.mark.asyncio
async def test_silent_and_missing_ports_fail_with_the_reason(silent_pty: str, tmp_path: Path) -> None:
    with pytest.raises(DeviceTimeout, match="GoToConfig failed after 2 attempts"):
        await probe_xsens(silent_pty, response_timeout_s=0.05)
    with pytest.raises(DeviceError, match="cannot open serial port"):
        await probe_xsens(str(tmp_path / "nothing"))


@pytest.mark.asyncio
async def test_probing_several_ports_reports_each(sim: xsens_sim.XsensSimulator, silent_pty: str) -> None:
    ports = [port_for_path(str(sim.link)), port_for_path(silent_pty)]
    good, bad = await probe_ports(ports, response_timeout_s=0.1)
    assert good.info is not None and good.info.product_code == "MTi-630" and good.error == ""
    assert bad.info is None and "no Xsens device answered" in bad.error


def test_a_named_port_gets_its_stable_link(sim: xsens_sim.XsensSimulator, tmp_path: Path) -> None:
    by_id = tmp_path / "by-id"
    by_id.mkdir()
    (by_id / "usb-Xsens_MTi-630_DB8P7J9R-if00").symlink_to(os.path.realpath(sim.link))
    (by_id / "usb-gone-if00").symlink_to(tmp_path / "unplugged")  # dangling: ignored
    port = port_for_path(str(sim.link), by_id)
    assert port == SerialPort(str(sim.link), str(by_id / "usb-Xsens_MTi-630_DB8P7J9R-if00"), "", "")
    assert port_for_path(str(by_id / "usb-x"), by_id).stable == str(by_id / "usb-x")  # already stable
    assert port_for_path(str(tmp_path / "other"), by_id).stable == ""


def test_only_xsens_usb_ports_are_listed() -> None:
    def port(device: str, vid: int | None, pid: int | None, description: str = "") -> ListPortInfo:
        info = ListPortInfo(device, skip_link_detection=True)
        info.vid, info.pid, info.description = vid, pid, description
        return info

    ports = [port("/dev/ttyUSB1", 0x2639, 0x0300, "MTi-630"), port("/dev/ttyACM0", 0x0403, 0x6001),
             port("/dev/ttyS0", None, None), port("/dev/ttyUSB0", 0x2639, None, "Awinda Station")]  # fmt: skip
    stable = {"/dev/ttyUSB1": "/dev/serial/by-id/usb-Xsens_MTi-630-if00"}
    assert xsens_ports(ports, stable) == [
        SerialPort("/dev/ttyUSB0", "", "2639:", "Awinda Station"),
        SerialPort("/dev/ttyUSB1", "/dev/serial/by-id/usb-Xsens_MTi-630-if00", "2639:0300", "MTi-630"),
    ]
