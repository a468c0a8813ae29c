"""The shipped systemd unit: Type=notify, a dedicated user, restart on failure, watchdog and hardening."""

from __future__ import annotations

import re
from pathlib import Path

UNIT = Path(__file__).resolve().parents[1] / "systemd" / "mocapd.service"


def _entries() -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    section = ""
    for raw in UNIT.read_text().splitlines():
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        if line.startswith("["):
            section = line.strip("[]")
            continue
        key, _, value = line.partition("=")
        out.setdefault(f"{section}.{key}", []).append(value)
    return out


def test_unit_is_a_hardened_notify_service() -> None:
    e = _entries()
    assert e["Service.Type"] == ["notify"]
    assert e["Service.User"] == ["mocapd"] and e["Service.Group"] == ["mocapd"]
    assert e["Service.Restart"] == ["on-failure"]
    assert e["Service.ExecStart"][0].endswith("mocapd run --config /etc/mocapd/config.toml")
    assert "check-config" in e["Service.ExecStartPre"][0]
    assert int(e["Service.WatchdogSec"][0]) > 0
    for key in ("NoNewPrivileges", "ProtectHome", "PrivateTmp", "ProtectKernelTunables", "RestrictSUIDSGID"):
        assert e[f"Service.{key}"] == ["yes"], key
    assert e["Service.ProtectSystem"] == ["strict"]
    assert e["Service.CapabilityBoundingSet"] == [""]
    assert e["Install.WantedBy"] == ["multi-user.target"]


def test_unit_lets_the_daemon_reach_real_devices_and_nothing_else() -> None:
    """Serial IMUs, webcams (V4L2) and USB3 Vision cameras (libusb): allowed by class, everything else closed."""
    e = _entries()
    assert e["Service.DevicePolicy"] == ["closed"]
    assert set(e["Service.DeviceAllow"]) == {"char-ttyUSB rw", "char-ttyACM rw", "char-video4linux rw",
                                             "char-usb_device rw"}  # fmt: skip
    assert set(e["Service.SupplementaryGroups"][0].split()) == {"dialout", "video"}


def test_udev_rules_give_those_groups_the_devices() -> None:
    """Each rule line is key-op-value pairs udev parses; Xsens (vendor 2639) to dialout, USB3 Vision to video."""
    rules = UNIT.with_name("99-mocapd.rules").read_text(encoding="utf-8")
    lines = [line for line in rules.splitlines() if line.strip() and not line.startswith("#")]
    assert lines
    for line in lines:
        for pair in (p.strip() for p in line.split(", ")):
            key, op, value = re.match(r'^([A-Z_]+(?:\{[^}]+\})?)(==|!=|\+=|=)"(.*)"$', pair).groups()  # type: ignore[union-attr]
            assert key and op and value is not None, pair
    assert any('ATTRS{idVendor}=="2639"' in line and 'GROUP="dialout"' in line for line in lines)
    assert any("ef0500" in line and 'GROUP="video"' in line for line in lines)
