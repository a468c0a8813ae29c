"""The ``[daemon]`` section of config.toml: output rate, latency, late-data limits, HTTP, time offsets, supervision,
and the synthetic rig (``[daemon.synthetic]``), parsed once into frozen dataclasses (unknown keys are errors)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from mocapd.core.heading import HeadingOptions
from mocapd.errors import ConfigError
from mocapd.pipeline.prediction import OUTPUTS, PredictionOptions
from mocapd.pipeline.scheduler import SchedulerOptions

_RIGS = ("synthetic",)


@dataclass(frozen=True, slots=True)
class SyntheticRigConfig:
    """``[daemon.synthetic]``: the rig ``mocapd demo --synthetic`` (and ``rig = "synthetic"``) runs."""

    cameras: int = 4
    people: int = 2
    suits: int = 1
    camera_rate_hz: float = 30.0
    detection_delay_s: float = 0.05
    noise_px: float = 1.0
    imu_rate_hz: int = 100
    seed: int = 0
    motion: str = "recorded"


@dataclass(frozen=True, slots=True)
class DaemonConfig:
    """``[daemon]``."""

    rig: str = "synthetic"
    output_rate_hz: float = 60.0
    latency_s: float = 0.15
    output: str = "delayed"
    heading_correction: bool = True
    max_catch_up_s: float = 0.05
    body_size_s: float = 2.0
    keypoint_max_age_s: float = 0.1
    keypoint_max_gap_s: float = 0.25
    match_px: float = 80.0
    http_host: str = "127.0.0.1"
    http_port: int = 8765
    restart_min_s: float = 0.5
    restart_max_s: float = 10.0
    shutdown_timeout_s: float = 1.5
    camera_offsets_s: dict[str, float] = field(default_factory=dict)
    imu_offsets_s: dict[str, float] = field(default_factory=dict)
    synthetic: SyntheticRigConfig = field(default_factory=SyntheticRigConfig)

    def scheduler_options(self, camera_names: list[str]) -> SchedulerOptions:
        """Scheduler options for a rig whose cameras have these names (offsets looked up by name)."""
        unknown = sorted(set(self.camera_offsets_s) - set(camera_names))
        if unknown:
            raise ConfigError(f"daemon.offsets.cameras: unknown camera(s) {unknown}; the rig has {camera_names}")
        return SchedulerOptions(
            rate_hz=self.output_rate_hz,
            latency_ns=round(self.latency_s * 1e9),
            keypoint_max_age_ns=round(self.keypoint_max_age_s * 1e9),
            keypoint_max_gap_ns=round(self.keypoint_max_gap_s * 1e9),
            match_px=self.match_px,
            camera_offsets_ns=tuple(round(self.camera_offsets_s.get(n, 0.0) * 1e9) for n in camera_names),
            imu_offsets_ns={k: round(v * 1e9) for k, v in self.imu_offsets_s.items()},
            body_size_frames=round(self.body_size_s * self.output_rate_hz),
            prediction=PredictionOptions(output=self.output),
            heading=HeadingOptions(enabled=self.heading_correction),
        )


def _reject_unknown(t: dict[str, Any], allowed: set[str], where: str) -> None:
    unknown = sorted(set(t) - allowed)
    if unknown:
        raise ConfigError(f"unknown key(s) {unknown} in [{where}]; allowed: {sorted(allowed)}")


def _num(
    t: dict[str, Any], key: str, where: str, default: float, lo: float, hi: float, *, integer: bool = False
) -> Any:
    v = t.get(key, default)
    ok_type = isinstance(v, int) if integer else isinstance(v, int | float)
    if isinstance(v, bool) or not ok_type or not lo <= v <= hi:
        kind = "an integer" if integer else "a number"
        raise ConfigError(f"{where}.{key} = {v!r}; allowed: {kind} in [{lo:g}, {hi:g}]")
    return v if integer else float(v)


def _choice(t: dict[str, Any], key: str, where: str, default: str, allowed: tuple[str, ...]) -> str:
    v = t.get(key, default)
    if v not in allowed:
        raise ConfigError(f"{where}.{key} = {v!r}; allowed: {list(allowed)}")
    return str(v)


def _bool(t: dict[str, Any], key: str, where: str, default: bool) -> bool:
    v = t.get(key, default)
    if not isinstance(v, bool):
        raise ConfigError(f"{where}.{key} = {v!r}; allowed: true or false")
    return v


def _offsets(t: object, where: str) -> dict[str, float]:
    if not isinstance(t, dict):
        raise ConfigError(f"{where} must be a table of name = seconds, got {t!r}")
    out = {}
    for k, v in t.items():
        if isinstance(v, bool) or not isinstance(v, int | float) or not -1.0 <= v <= 1.0:
            raise ConfigError(f"{where}.{k} = {v!r}; allowed: a number of seconds in [-1, 1]")
        out[str(k).upper() if where.endswith("imus") else str(k)] = float(v)
    return out


def parse_daemon_config(t: dict[str, Any]) -> DaemonConfig:
    """Build a :class:`DaemonConfig` from the ``daemon`` table of a parsed config.toml.

    Raises
    ------
    ConfigError
        Unknown keys, wrong types or values out of range (the message names the key, the value and what is
        allowed).
    """
    w = "daemon"
    keys = {f for f in DaemonConfig.__dataclass_fields__ if f not in ("camera_offsets_s", "imu_offsets_s")}
    _reject_unknown(t, keys | {"offsets"}, w)
    rig = t.get("rig", "synthetic")
    if rig not in _RIGS:
        raise ConfigError(
            f"daemon.rig = {rig!r}; allowed: {list(_RIGS)} "
            "(the camera rig runs as `mocapd demo`; a configured camera rig is not in this build)"
        )
    host = t.get("http_host", "127.0.0.1")
    if host not in ("127.0.0.1", "::1", "localhost"):
        raise ConfigError(f"daemon.http_host = {host!r}; allowed: a loopback address ('127.0.0.1', '::1')")
    offsets = t.get("offsets", {})
    if not isinstance(offsets, dict):
        raise ConfigError(f"daemon.offsets must be a table, got {offsets!r}")
    _reject_unknown(offsets, {"cameras", "imus"}, "daemon.offsets")
    restart_min = _num(t, "restart_min_s", w, 0.5, 0.01, 60.0)
    restart_max = _num(t, "restart_max_s", w, 10.0, 0.01, 600.0)
    if restart_max < restart_min:
        raise ConfigError(f"daemon.restart_max_s = {restart_max} must be >= daemon.restart_min_s = {restart_min}")
    return DaemonConfig(
        rig=rig,
        output_rate_hz=_num(t, "output_rate_hz", w, 60.0, 1.0, 500.0),
        latency_s=_num(t, "latency_s", w, 0.15, 0.0, 2.0),
        output=_choice(t, "output", w, "delayed", OUTPUTS),
        heading_correction=_bool(t, "heading_correction", w, True),
        max_catch_up_s=_num(t, "max_catch_up_s", w, 0.05, 0.0, 1.0),
        body_size_s=_num(t, "body_size_s", w, 2.0, 0.0, 60.0),
        keypoint_max_age_s=_num(t, "keypoint_max_age_s", w, 0.1, 0.0, 2.0),
        keypoint_max_gap_s=_num(t, "keypoint_max_gap_s", w, 0.25, 0.0, 5.0),
        match_px=_num(t, "match_px", w, 80.0, 1.0, 10000.0),
        http_host=host,
        http_port=_num(t, "http_port", w, 8765, 0, 65535, integer=True),
        restart_min_s=restart_min,
        restart_max_s=restart_max,
        shutdown_timeout_s=_num(t, "shutdown_timeout_s", w, 1.5, 0.1, 10.0),
        camera_offsets_s=_offsets(offsets.get("cameras", {}), "daemon.offsets.cameras"),
        imu_offsets_s=_offsets(offsets.get("imus", {}), "daemon.offsets.imus"),
        synthetic=_parse_synthetic(t.get("synthetic", {})),
    )


def _parse_synthetic(t: object) -> SyntheticRigConfig:
    w = "daemon.synthetic"
    if not isinstance(t, dict):
        raise ConfigError(f"{w} must be a table, got {t!r}")
    _reject_unknown(t, set(SyntheticRigConfig.__dataclass_fields__), w)
    people = _num(t, "people", w, 2, 1, 4, integer=True)
    suits = _num(t, "suits", w, 1, 0, 4, integer=True)
    if suits > people:
        raise ConfigError(f"{w}.suits = {suits}; allowed: at most daemon.synthetic.people = {people}")
    return SyntheticRigConfig(
        cameras=_num(t, "cameras", w, 4, 2, 16, integer=True),
        people=people,
        suits=suits,
        camera_rate_hz=_num(t, "camera_rate_hz", w, 30.0, 1.0, 240.0),
        detection_delay_s=_num(t, "detection_delay_s", w, 0.05, 0.0, 1.0),
        noise_px=_num(t, "noise_px", w, 1.0, 0.0, 50.0),
        imu_rate_hz=_num(t, "imu_rate_hz", w, 100, 60, 120, integer=True),
        seed=_num(t, "seed", w, 0, 0, 2**31, integer=True),
        motion=_motion(t.get("motion", "recorded"), w),
    )


def _motion(value: object, w: str) -> str:
    if value not in ("recorded", "procedural"):
        raise ConfigError(f"{w}.motion = {value!r}; allowed: 'recorded' or 'procedural'")
    return str(value)
