"""``config.toml``: parsed once at start-up into frozen, typed objects; unknown keys and bad values rejected.

Every error names the key (dotted path), the value and what is allowed. Sections are validated by the module
that owns them; this module owns ``[solver]``. Sections another part of mocapd documents in the shipped file
are listed in ``KNOWN_SECTIONS`` until their loaders exist, so a typo in a section name is still an error.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field, fields, replace
from importlib import resources
from pathlib import Path
from typing import Any

from mocapd.core.loss import CauchyLoss, HuberLoss, Loss, TrivialLoss
from mocapd.core.solver import TERM_NAMES, LMOptions
from mocapd.core.terms import CostOptions
from mocapd.errors import ConfigError
from mocapd.pipeline.detector_config import DetectorConfig, detector_config_from_mapping
from mocapd.service.config.cameras import (
    CalibrationConfig,
    CameraConfig,
    ImagesCamera,
    SyntheticConfig,
    UvcCamera,
    VideoCamera,
    parse_cameras,
)
from mocapd.service.config.daemon import DaemonConfig, parse_daemon_config
from mocapd.service.config.imu import ImuConfig, parse_imu_config
from mocapd.service.config.record import RecordConfig, parse_record_config
from mocapd.service.config.schema import validate
from mocapd.service.config.tracking import TrackingConfig, parse_tracking_config
from mocapd.service.config.udp import UdpConfig, parse_udp_config
from mocapd.service.config.websocket import WebSocketConfig, parse_websocket_config

DEFAULT_CONFIG = Path(str(resources.files("mocapd").joinpath("config.toml")))
"""The shipped config.toml (inside the package, so an installed wheel has it): every key, documented."""

_LOSSES = ("trivial", "cauchy", "huber")
_TERM_KEYS = {"enabled", "weight", "loss", "loss_scale"}
_BACKENDS = ("compiled", "numpy")


@dataclass(frozen=True)
class SolverConfig:
    """The ``[solver]`` section."""

    cost: CostOptions = field(default_factory=CostOptions)
    lm: LMOptions = field(default_factory=LMOptions)
    backend: str = "compiled"
    prior: str = "default"
    """Pose prior: "default" (the shipped CMU prior, mocapd/data/prior_cmu.npz), "none" or a .npz path."""


@dataclass(frozen=True)
class Config:
    solver: SolverConfig = field(default_factory=SolverConfig)
    imu: ImuConfig = field(default_factory=ImuConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    detector: DetectorConfig = field(default_factory=DetectorConfig)
    daemon: DaemonConfig = field(default_factory=DaemonConfig)
    udp: UdpConfig = field(default_factory=UdpConfig)
    record: RecordConfig = field(default_factory=RecordConfig)
    websocket: WebSocketConfig = field(default_factory=WebSocketConfig)
    cameras: tuple[CameraConfig, ...] = ()
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)
    synthetic: SyntheticConfig = field(default_factory=SyntheticConfig)
    source: Path | None = None
    """The file this config was read from (None: built in code); relative paths in it were resolved from its
    folder."""
    raw: dict[str, Any] = field(default_factory=dict, repr=False)
    """The whole parsed file, for sections whose loaders live elsewhere."""


KNOWN_SECTIONS = {"solver", "imu", "tracking", "detector", "daemon", "udp", "record", "websocket", "cameras",
                  "calibration", "synthetic"}  # fmt: skip


def load_config(path: str | Path | None = None) -> Config:
    """Read and validate a config file (default: the shipped ``config.toml``)."""
    p = Path(path) if path is not None else DEFAULT_CONFIG
    try:
        with p.open("rb") as fh:
            data = tomllib.load(fh)
    except FileNotFoundError as exc:
        raise ConfigError(f"config file not found: {p}") from exc
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: not valid TOML: {exc}") from exc
    return replace(resolve_paths(parse_config(data), p.resolve().parent), source=p)


def parse_config(data: dict[str, Any]) -> Config:
    unknown = set(data) - KNOWN_SECTIONS
    if unknown:
        raise ConfigError(f"unknown section(s) {sorted(unknown)}; allowed: {sorted(KNOWN_SECTIONS)}")
    return Config(
        solver=_parse_solver(_table(data, "solver")),
        imu=parse_imu_config(_table(data, "imu")),
        tracking=parse_tracking_config(_table(data, "tracking")),
        detector=detector_config_from_mapping(_table(data, "detector")),
        daemon=parse_daemon_config(_table(data, "daemon")),
        udp=parse_udp_config(_table(data, "udp")),
        record=parse_record_config(_table(data, "record")),
        websocket=parse_websocket_config(_table(data, "websocket")),
        cameras=parse_cameras(data.get("cameras", [])),
        calibration=validate(CalibrationConfig, data.get("calibration", {}), "calibration"),
        synthetic=validate(SyntheticConfig, data.get("synthetic", {}), "synthetic"),
        raw=data,
    )


def resolve_paths(config: Config, base: Path) -> Config:
    """``config`` with the rig's relative file paths (calibration file, replayed videos and image folders, a
    webcam given as a file) made absolute from ``base``, the config file's folder: a config and the files it
    names travel together, whatever the working directory."""

    def absolute(path: str) -> str:
        return path if not path or Path(path).is_absolute() else str(base / path)

    cameras: list[CameraConfig] = []
    for cam in config.cameras:
        if isinstance(cam, VideoCamera | ImagesCamera):
            cameras.append(cam.model_copy(update={"path": absolute(cam.path)}))
        elif isinstance(cam, UvcCamera) and isinstance(cam.device, str) and not cam.device.startswith("/dev/"):
            cameras.append(cam.model_copy(update={"device": absolute(cam.device)}))
        else:
            cameras.append(cam)
    calibration = config.calibration.model_copy(update={"file": absolute(config.calibration.file)})
    return replace(config, cameras=tuple(cameras), calibration=calibration)


def _table(data: dict[str, Any], key: str, prefix: str = "") -> dict[str, Any]:
    value = data.get(key, {})
    if not isinstance(value, dict):
        raise ConfigError(f"{prefix}{key} must be a table, got {value!r}")
    return value


def _parse_solver(t: dict[str, Any]) -> SolverConfig:
    _reject_unknown(
        t, {"backend", "floor_radius", "floor_height", "acceleration_min_views", "terms", "lm", "prior"}, "solver"
    )
    prior = t.get("prior", "default")
    if not isinstance(prior, str) or not prior:
        raise ConfigError(f'solver.prior = {prior!r}; allowed: "default", "none" or a path to a .npz prior')
    backend = t.get("backend", "compiled")
    if backend not in _BACKENDS:
        raise ConfigError(f"solver.backend = {backend!r}; allowed: {list(_BACKENDS)}")
    cost = CostOptions()
    updates: dict[str, Any] = {}
    for key in ("floor_radius", "floor_height"):
        if key in t:
            updates[key] = _number(t[key], f"solver.{key}", minimum=0.0 if key == "floor_radius" else None)
    if "acceleration_min_views" in t:
        v = t["acceleration_min_views"]
        if not isinstance(v, int) or isinstance(v, bool) or v < 0:
            raise ConfigError(f"solver.acceleration_min_views = {v!r}; allowed: an integer >= 0")
        updates["acceleration_min_views"] = v
    terms = _table(t, "terms", "solver.")
    _reject_unknown(terms, set(TERM_NAMES), "solver.terms")
    for name in TERM_NAMES:
        updates.update(_parse_term(name, _table(terms, name, "solver.terms.")))
    cost = replace(cost, **updates)
    return SolverConfig(cost=cost, lm=_parse_lm(_table(t, "lm", "solver.")), backend=str(backend), prior=prior)


def _parse_term(name: str, t: dict[str, Any]) -> dict[str, Any]:
    where = f"solver.terms.{name}"
    _reject_unknown(t, _TERM_KEYS, where)
    out: dict[str, Any] = {}
    if "enabled" in t:
        if not isinstance(t["enabled"], bool):
            raise ConfigError(f"{where}.enabled = {t['enabled']!r}; allowed: true or false")
        out[f"use_{name}"] = t["enabled"]
    if "weight" in t:
        out[f"lambda_{name}"] = _number(t["weight"], f"{where}.weight", minimum=0.0)
    if "loss" in t or "loss_scale" in t:
        kind = t.get("loss", "cauchy")
        if kind not in _LOSSES:
            raise ConfigError(f"{where}.loss = {kind!r}; allowed: {list(_LOSSES)}")
        scale = _number(t.get("loss_scale", 1.0), f"{where}.loss_scale", minimum=1e-12)
        loss: Loss = TrivialLoss() if kind == "trivial" else CauchyLoss(scale) if kind == "cauchy" else HuberLoss(scale)
        out[f"loss_{name}"] = loss
    return out


def _parse_lm(t: dict[str, Any]) -> LMOptions:
    allowed = {f.name for f in fields(LMOptions)}
    _reject_unknown(t, allowed, "solver.lm")
    updates: dict[str, Any] = {}
    for key, value in t.items():
        if key == "max_iterations":
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ConfigError(f"solver.lm.max_iterations = {value!r}; allowed: an integer >= 1")
            updates[key] = value
        else:
            updates[key] = _number(value, f"solver.lm.{key}", minimum=0.0)
    return replace(LMOptions(), **updates)


def _number(value: object, key: str, minimum: float | None = None) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ConfigError(f"{key} = {value!r}; allowed: a number")
    v = float(value)
    if minimum is not None and not v >= minimum:
        raise ConfigError(f"{key} = {value!r}; allowed: a number >= {minimum}")
    return v


def _reject_unknown(t: dict[str, Any], allowed: set[str], where: str) -> None:
    unknown = set(t) - allowed
    if unknown:
        raise ConfigError(f"unknown key(s) {sorted(unknown)} in [{where}]; allowed: {sorted(allowed)}")
