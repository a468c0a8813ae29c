"""The shipped systemd unit: Type=notify, a dedicated user, restart on failure, watchdog and hardening."""

from __future__ import annotations

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
