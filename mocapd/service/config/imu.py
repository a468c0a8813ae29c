"""The ``[imu]`` section of config.toml, parsed once into frozen dataclasses (unknown keys are errors)."""

from __future__ import annotations

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
    general = {"ports", "imu_set", "calibration_dir", "buffer_capacity", "assignment", "bridge", "awinda"}
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
    assignment = parse_assignment(t.get("assignment", {}), imu_set=imu_set)
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
    )
