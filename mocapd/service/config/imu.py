"""The ``[imu]`` section of config.toml, parsed once into frozen dataclasses (unknown keys are errors)."""

from __future__ import annotations

import ipaddress
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from typing import Any

from mocapd.core.imu_calibration import parse_assignment
from mocapd.errors import ConfigError
from mocapd.io.slimevr import SlimeVrConfig
from mocapd.io.xsens_serial import XsensPortConfig
from mocapd.protocols.awinda import AwindaConfig

_PORT_KEYS = {f.name for f in fields(XsensPortConfig)} - {"path", "precision"}


@dataclass(frozen=True, slots=True)
class BridgeConfig:
    """``[imu.bridge]``: the UDP msgpack input for vendor-SDK forwarders."""

    enabled: bool = False
    host: str = "127.0.0.1"
    port: int = 9773


@dataclass(frozen=True, slots=True)
class ImuConfig:
    """Everything mocapd needs to know about its IMUs."""

    ports: tuple[XsensPortConfig, ...] = ()
    assignment: dict[str, str] = field(default_factory=dict)
    imu_set: str | None = None
    calibration_dir: str = "calibration"
    buffer_capacity: int = 512
    bridge: BridgeConfig = field(default_factory=BridgeConfig)
    awinda: AwindaConfig = field(default_factory=AwindaConfig)
    slimevr: SlimeVrConfig = field(default_factory=SlimeVrConfig)


def _take(table: Mapping[str, Any], allowed: set[str], where: str) -> dict[str, Any]:
    unknown = sorted(set(table) - allowed)
    if unknown:
        raise ConfigError(f"[{where}]: unknown keys {unknown}; allowed: {sorted(allowed)}")
    return dict(table)


def parse_imu_config(table: Mapping[str, Any]) -> ImuConfig:
    """Build an :class:`ImuConfig` from the ``imu`` table of a parsed config.toml.

    Raises
    ------
    ConfigError
        Unknown keys, wrong types or values (the message names the key).
    """
    general = {"ports", "imu_set", "calibration_dir", "buffer_capacity", "assignment", "bridge", "awinda", "slimevr"}
    t = _take(table, general | _PORT_KEYS, "imu")
    port_opts = {k: t[k] for k in _PORT_KEYS if k in t}
    ports_raw = t.get("ports", [])
    if not isinstance(ports_raw, list) or not all(isinstance(p, str) for p in ports_raw):
        raise ConfigError(f"imu.ports must be a list of device paths, got {ports_raw!r}")
    try:
        ports = tuple(XsensPortConfig(path=p, **port_opts) for p in ports_raw)
        # Validate the shared options even when no port is listed (e.g. bridge-only set-ups).
        XsensPortConfig(path="", **port_opts)
    except TypeError as exc:
        raise ConfigError(f"imu: {exc}") from exc
    imu_set = str(t.get("imu_set", "")) or None
    slimevr = _slimevr(t.get("slimevr", {}))
    xsens = t.get("assignment", {})
    if not isinstance(xsens, Mapping):
        raise ConfigError(f"imu.assignment must be a table of sensor id = bone, got {xsens!r}")
    both = {str(k).upper() for k in xsens} & set(slimevr.assignment)
    if both:
        raise ConfigError(f"imu: sensors {sorted(both)} are in both [imu.assignment] and [imu.slimevr.assignment]")
    # One assignment for calibration, suits and the set check, whatever transport each sensor uses.
    assignment = parse_assignment({**xsens, **slimevr.assignment}, imu_set=imu_set)
    bridge = BridgeConfig(**_take(t.get("bridge", {}), {f.name for f in fields(BridgeConfig)}, "imu.bridge"))
    if bridge.host not in ("127.0.0.1", "::1", "localhost"):
        raise ConfigError(f"imu.bridge.host={bridge.host!r}: the bridge listens on loopback only")
    awinda = AwindaConfig(**_take(t.get("awinda", {}), {f.name for f in fields(AwindaConfig)}, "imu.awinda"))
    capacity = t.get("buffer_capacity", 512)
    if not isinstance(capacity, int) or capacity < 16:
        raise ConfigError(f"imu.buffer_capacity must be an integer >= 16, got {capacity!r}")
    return ImuConfig(
        ports=ports,
        assignment=assignment,
        imu_set=imu_set,
        calibration_dir=str(t.get("calibration_dir", "calibration")),
        buffer_capacity=capacity,
        bridge=bridge,
        awinda=awinda,
        slimevr=slimevr,
    )


def _slimevr(table: object) -> SlimeVrConfig:
    if not isinstance(table, Mapping):
        raise ConfigError(f"imu.slimevr must be a table, got {table!r}")
    t = _take(table, {f.name for f in fields(SlimeVrConfig)}, "imu.slimevr")
    enabled = t.get("enabled", False)
    if not isinstance(enabled, bool):
        raise ConfigError(f"imu.slimevr.enabled = {enabled!r}; allowed: true or false")
    host = t.get("host", "127.0.0.1")
    try:
        ipaddress.ip_address(host if host != "localhost" else "127.0.0.1")
    except (ValueError, TypeError):
        raise ConfigError(
            f'imu.slimevr.host = {host!r}; allowed: an IP address literal ("127.0.0.1" keeps it on this machine; '
            'trackers on the network need this machine\'s address or "0.0.0.0")'
        ) from None
    port = t.get("port", 6969)
    if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
        raise ConfigError(f"imu.slimevr.port = {port!r}; allowed: an integer 0..65535 (6969: SlimeVR's port)")
    raw = t.get("assignment", {})
    if not isinstance(raw, Mapping):
        raise ConfigError(f'imu.slimevr.assignment must be a table of "<MAC>/<sensor>" = bone, got {raw!r}')
    assignment = parse_assignment(raw)
    xsens_ids = sorted(s for s in assignment if "/" not in s)
    if xsens_ids:
        raise ConfigError(
            f'imu.slimevr.assignment: {xsens_ids} are Xsens ids; SlimeVR sensors are "<MAC>/<sensor index>", '
            'e.g. "AA:BB:CC:DD:EE:FF/0"'
        )
    return SlimeVrConfig(enabled=enabled, host=str(host), port=port, assignment=assignment)
