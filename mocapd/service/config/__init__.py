"""``config.toml``: read once at start-up into one frozen, typed :class:`Config`; unknown keys and bad values rejected.

Every section is a :class:`~mocapd.service.config.schema.Section` model whose fields are the keys of its table,
with each key's type, range and the rules across keys declared beside it. Every error names the dotted key, the
value and what is allowed (:mod:`mocapd.service.config.schema`). The models convert to the plain option
dataclasses of the layers below (``.options()``, ``SolverConfig.cost``): core, pipeline and io know nothing of
pydantic or of the file. This module owns ``[solver]`` and the file itself (:func:`load_config`).

The rig's tables (``[[cameras]]``, ``[calibration]``, ``[synthetic]``) are in :mod:`.cameras`; relative paths of
the rig are resolved from the config file's folder when it is read (:func:`resolve_paths`).
"""

from __future__ import annotations

import functools
import stat
import tomllib
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, Self

from pydantic import Field, model_validator

from mocapd.core.loss import CauchyLoss, HuberLoss, Loss, TrivialLoss
from mocapd.errors import ConfigError
from mocapd.service.config.cameras import (
    CalibrationConfig,
    CameraConfig,
    ImagesCamera,
    SyntheticConfig,
    UvcCamera,
    VideoCamera,
    ZenohCamera,
    parse_cameras,
)
from mocapd.service.config.daemon import DaemonConfig
from mocapd.service.config.detector import DetectorSection
from mocapd.service.config.fusion import FusionConfig
from mocapd.service.config.imu import ImuConfig
from mocapd.service.config.record import RecordConfig
from mocapd.service.config.schema import PathStr, RuleError, Section, Seq, validate
from mocapd.service.config.tracking import TrackingConfig
from mocapd.service.config.udp import UdpConfig
from mocapd.service.config.web import WebConfig
from mocapd.service.config.websocket import WebSocketConfig, is_loopback
from mocapd.service.config.zenoh import ZenohConfig, is_loopback_endpoint

# The solver's modules load NumBa and its kernels (a second of CPU): they are imported where a default the file left
# out or an option is built, not by reading the schema (`mocapd check-config`, and every `mocapd` command).
if TYPE_CHECKING:
    from mocapd.core.lm import LMOptions
    from mocapd.core.terms import CostOptions

DEFAULT_CONFIG = Path(str(resources.files("mocapd").joinpath("config.toml")))
"""The shipped config.toml (inside the package, so an installed wheel has it): every key, documented."""

MAX_FILE_BYTES = 1 << 20
"""A config file is a few KB of text; anything above this is refused unread (a device, a log, a wrong file)."""

LossName = Literal["trivial", "cauchy", "huber"]
_LOSSES: dict[str, type[TrivialLoss | CauchyLoss | HuberLoss]] = {
    "trivial": TrivialLoss,
    "cauchy": CauchyLoss,
    "huber": HuberLoss,
}


class TermConfig(Section):
    """``[solver.terms.<name>]``: one cost term. Keys left out keep ``CostOptions``' default for that term."""

    enabled: bool = True
    weight: float = Field(1.0, ge=0.0, le=1e6)
    """λ of the term."""
    loss: LossName = "cauchy"
    loss_scale: float = Field(1.0, gt=0.0, le=1e6)
    """a of the robust loss, in the units of sqrt(λ w) · residual (unused with loss = "trivial")."""

    def loss_function(self) -> Loss:
        if self.loss == "trivial":
            return TrivialLoss()
        return CauchyLoss(self.loss_scale) if self.loss == "cauchy" else HuberLoss(self.loss_scale)


TUNED_WEIGHTS = {"orientation": 100.0, "acceleration": 1e-4}
"""λ_R and λ_A as tuned on the accuracy harness's development split (docs/accuracy.md "Tuning"): the config's
defaults, where ``CostOptions`` keeps the seed's values (with which the solver is worse than triangulation)."""


@functools.cache
def _cost() -> CostOptions:
    from mocapd.core.terms import CostOptions

    return CostOptions()


@functools.cache
def _lm() -> LMOptions:
    from mocapd.core.lm import LMOptions

    return LMOptions()


def _term_defaults(name: str) -> dict[str, Any]:
    """The keys of ``[solver.terms.<name>]`` when the file leaves them out: ``CostOptions``' defaults but the
    tuned weights (the shipped config.toml's values)."""
    d = _cost()
    loss = getattr(d, f"loss_{name}")
    kind = next(k for k, cls in _LOSSES.items() if isinstance(loss, cls))
    return {
        "enabled": getattr(d, f"use_{name}"),
        "weight": TUNED_WEIGHTS.get(name, getattr(d, f"lambda_{name}")),
        "loss": kind,
        "loss_scale": getattr(loss, "scale", 1.0),
    }


def _term(name: str) -> Any:
    return Field(default_factory=lambda: TermConfig(**_term_defaults(name)))


class TermsConfig(Section):
    """``[solver.terms]``: one table per cost term (seed 003 §3.2)."""

    position: TermConfig = _term("position")
    orientation: TermConfig = _term("orientation")
    acceleration: TermConfig = _term("acceleration")
    prior_projection: TermConfig = _term("prior_projection")
    prior_deviation: TermConfig = _term("prior_deviation")
    floor: TermConfig = _term("floor")

    @model_validator(mode="before")
    @classmethod
    def _fill_term_defaults(cls, data: Any) -> Any:
        """A term's table that leaves keys out gets that term's defaults, not the generic TermConfig ones."""
        if not isinstance(data, dict):
            return data
        every = TermConfig.model_fields.keys()  # a table that gives them all needs no default (nor the solver)
        return {
            k: {**_term_defaults(k), **v} if k in cls.model_fields and isinstance(v, dict) and v.keys() < every else v
            for k, v in data.items()
        }


class LmConfig(Section):
    """``[solver.lm]``: Levenberg–Marquardt settings (:class:`~mocapd.core.lm.LMOptions`)."""

    ordered = (
        ("min_trust_region_radius", "<=", "initial_trust_region_radius"),
        ("initial_trust_region_radius", "<=", "max_trust_region_radius"),
        ("min_lm_diagonal", "<=", "max_lm_diagonal"),
    )

    max_iterations: int = Field(default_factory=lambda: _lm().max_iterations, ge=1, le=1000)
    function_tolerance: float = Field(default_factory=lambda: _lm().function_tolerance, ge=0.0, le=1.0)
    gradient_tolerance: float = Field(default_factory=lambda: _lm().gradient_tolerance, ge=0.0, le=1e6)
    parameter_tolerance: float = Field(default_factory=lambda: _lm().parameter_tolerance, ge=0.0, le=1.0)
    initial_trust_region_radius: float = Field(
        default_factory=lambda: _lm().initial_trust_region_radius, gt=0.0, le=1e32
    )
    max_trust_region_radius: float = Field(default_factory=lambda: _lm().max_trust_region_radius, gt=0.0, le=1e32)
    min_trust_region_radius: float = Field(default_factory=lambda: _lm().min_trust_region_radius, ge=0.0, le=1e32)
    min_relative_decrease: float = Field(default_factory=lambda: _lm().min_relative_decrease, ge=0.0, lt=1.0)
    min_lm_diagonal: float = Field(default_factory=lambda: _lm().min_lm_diagonal, ge=0.0, le=1e64)
    max_lm_diagonal: float = Field(default_factory=lambda: _lm().max_lm_diagonal, gt=0.0, le=1e64)

    def options(self) -> LMOptions:
        from mocapd.core.lm import LMOptions

        return self.build(LMOptions)


class SolverConfig(Section):
    """The ``[solver]`` section."""

    backend: Literal["compiled", "numpy"] = "compiled"
    floor_radius: float = Field(default_factory=lambda: _cost().floor_radius, ge=0.0, le=1.0)
    """Collision radius of the floor term's targets (m)."""
    floor_height: float = Field(default_factory=lambda: _cost().floor_height, ge=-100.0, le=100.0)
    """World y of the floor (m)."""
    acceleration_min_views: int = Field(default_factory=lambda: _cost().acceleration_min_views, ge=0, le=64)
    prior: PathStr = Field("default", min_length=1)
    """Pose prior: "default" (the shipped CMU prior, mocapd/data/prior_cmu.npz), "none" or a .npz path."""
    terms: TermsConfig = Field(default_factory=TermsConfig)
    lm: LmConfig = Field(default_factory=LmConfig)

    @property
    def cost(self) -> CostOptions:
        """The cost terms' weights, losses and switches as the solver takes them."""
        from mocapd.core.solver import TERM_NAMES
        from mocapd.core.terms import CostOptions

        per_term: dict[str, Any] = {}
        for name in TERM_NAMES:
            term: TermConfig = getattr(self.terms, name)
            per_term |= {
                f"use_{name}": term.enabled,
                f"lambda_{name}": term.weight,
                f"loss_{name}": term.loss_function(),
            }
        return CostOptions(
            **per_term,
            floor_radius=self.floor_radius,
            floor_height=self.floor_height,
            acceleration_min_views=self.acceleration_min_views,
        )


MAX_CAMERAS = 64
"""More cameras than one daemon can detect and solve; a rig this large needs camera hosts (docs/scaling.md)."""

_PORT_CLASH = "{0} and {1} are one loopback port: the status server and the WebSocket server cannot share it"


class Config(Section):
    """The whole of ``config.toml``: every section, each with its defaults when the file leaves it out."""

    solver: SolverConfig = Field(default_factory=SolverConfig)
    imu: ImuConfig = Field(default_factory=ImuConfig)
    tracking: TrackingConfig = Field(default_factory=TrackingConfig)
    detector: DetectorSection = Field(default_factory=DetectorSection)
    daemon: DaemonConfig = Field(default_factory=DaemonConfig)
    udp: UdpConfig = Field(default_factory=UdpConfig)
    record: RecordConfig = Field(default_factory=RecordConfig)
    websocket: WebSocketConfig = Field(default_factory=WebSocketConfig)
    web: WebConfig = Field(default_factory=WebConfig)
    cameras: Seq[CameraConfig] = Field((), max_length=MAX_CAMERAS)
    """``[[cameras]]``: validated entry by entry against each one's ``source`` kind (:func:`parse_config`)."""
    calibration: CalibrationConfig = Field(default_factory=CalibrationConfig)
    synthetic: SyntheticConfig = Field(default_factory=SyntheticConfig)
    zenoh: ZenohConfig = Field(default_factory=ZenohConfig)
    fusion: FusionConfig = Field(default_factory=FusionConfig)

    @model_validator(mode="after")
    def _ports_apart(self) -> Self:
        """Two servers of one daemon on one port: the second would fail at start-up, after everything opened."""
        ws, d = self.websocket, self.daemon
        if ws.enabled and d.http_port != 0 and ws.port == d.http_port and (is_loopback(ws.host) or _any(ws.host)):
            raise RuleError(_PORT_CLASH, "daemon.http_port", "websocket.port", values=(d.http_port, ws.port))
        bridge = self.imu.bridge
        if bridge.enabled:
            for stream in ("mvn", "vmc", "rokoko"):
                s = getattr(self.udp, stream)
                if s.enabled and any(dst.port == bridge.port and is_loopback(dst.host) for dst in s.destinations):
                    raise RuleError(
                        "{0} is a destination of {1}: mocapd would receive its own poses as IMU data",
                        "imu.bridge.port",
                        f"udp.{stream}.destinations",
                        values=(bridge.port, [str(x) for x in s.destinations]),
                    )
        return self


def _any(host: str) -> bool:
    return host in ("0.0.0.0", "::")


def load_config(path: str | Path | None = None) -> Config:
    """Read and validate a config file (default: the shipped ``config.toml``).

    Raises
    ------
    ConfigError
        One line naming the file and what is wrong with it (missing, a directory or device, unreadable, too
        large, binary, not UTF-8, not TOML), or one line per bad key.
    """
    p = Path(path) if path is not None else DEFAULT_CONFIG
    config = resolve_paths(parse_config(read_toml(p)), p.resolve().parent)
    if path is None:
        return config  # the shipped file: its suits are calibrated where mocapd is run, not in the package
    # A rig's suits travel with its config, as its camera calibration does: `mocapd run --config ~/suit.toml`
    # started from anywhere (a service's working directory is /) finds what `calibrate imu --config` wrote.
    folder = config.imu.calibration_dir
    if Path(folder).is_absolute():
        return config
    imu = config.imu.model_copy(update={"calibration_dir": str(p.resolve().parent / folder)})
    return config.model_copy(update={"imu": imu})


def read_toml(p: Path) -> dict[str, Any]:
    """The TOML document of config file ``p``, or ConfigError saying in one line why it is not one."""
    try:
        mode = p.stat().st_mode  # before opening: opening a FIFO would wait for a writer
        if stat.S_ISDIR(mode):
            raise ConfigError(f"{p}: is a directory, not a config file")
        if not stat.S_ISREG(mode):
            raise ConfigError(f"{p}: not a regular file (a device, pipe or socket), not a config file")
        with p.open("rb") as fh:
            data = fh.read(MAX_FILE_BYTES + 1)
    except FileNotFoundError:
        raise ConfigError(f"config file not found: {p}") from None
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read: {exc.strerror or exc}") from None
    if len(data) > MAX_FILE_BYTES:
        raise ConfigError(f"{p}: larger than {MAX_FILE_BYTES >> 10} KiB; a config file is a few KB of TOML text")
    # A UTF-8 byte order mark (Windows Notepad writes one) is no text: TOML readers stumbled on it at "line 1,
    # column 1" (issue 45). It is left out.
    data = data.removeprefix(b"\xef\xbb\xbf")
    if b"\x00" in data:
        line, col = _position(data, data.index(b"\x00"))
        raise ConfigError(f"{p}: a binary file, not TOML text (a NUL byte at line {line}, column {col})")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line, col = _position(data, exc.start)
        start = data.rfind(b"\n", 0, exc.start) + 1
        before = data[start : exc.start].decode("utf-8", errors="replace")
        raise ConfigError(
            f"{p}: line {line}, column {col}: byte 0x{data[exc.start]:02x} is not UTF-8 "
            f"(TOML files are UTF-8 text), after {before[-60:]!r}"
        ) from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: not valid TOML: {exc}") from None
    except RecursionError:
        raise ConfigError(f"{p}: not valid TOML: arrays or tables nested too deeply") from None


def _position(data: bytes, offset: int) -> tuple[int, int]:
    """1-based line and column of byte ``offset``."""
    line = data.count(b"\n", 0, offset) + 1
    return line, offset - (data.rfind(b"\n", 0, offset) + 1) + 1


def _hosts_identified(config: Config) -> None:
    """A solver host reached off loopback admits each camera host by its identity (issue 34): without one, any peer
    holding valid credentials could publish as any host. (Here, not in :class:`Config`: the cameras join it after.)"""
    z = config.zenoh
    hosts = sorted({c.host for c in config.cameras if isinstance(c, ZenohCamera)})
    remote = [e for e in (*z.listen, *z.connect) if not is_loopback_endpoint(e)]
    missing = [h for h in hosts if h not in z.identities]
    if not (hosts and missing and (remote or z.identities)):
        return
    example = f'e.g. {missing[0]} = "user:{missing[0]}" (docs/scaling.md)'
    if remote:
        err = RuleError("{0} is not loopback: each camera host's identity must be in {1} (missing: "
                        f"{', '.join(missing)}), {example}", "zenoh.listen" if z.listen else "zenoh.connect",
                        "zenoh.identities", values=(remote, dict(z.identities)))  # fmt: skip
    else:  # some identities: the session admits nobody else, a host left out would be cut off without a word
        err = RuleError(f"{{0}} leaves out camera host(s) {', '.join(missing)}: the session admits only the hosts "
                        f"it names, {example}", "zenoh.identities", values=(dict(z.identities),))  # fmt: skip
    raise ConfigError(str(err))


def parse_config(data: object) -> Config:
    """A parsed config (a TOML document, or a session manifest's copy of one) as :class:`Config`.

    ``[[cameras]]`` entries are validated one by one against the model of their ``source`` kind (a message
    names ``cameras[i].key``, and an unknown kind lists the kinds), then the rest of the document.
    """
    if not isinstance(data, dict):
        raise ConfigError(f"a config is a TOML table of sections, got {type(data).__name__}")
    cameras = parse_cameras(data.get("cameras", []))
    config = validate(Config, {k: v for k, v in data.items() if k != "cameras"})
    config = config.model_copy(update={"cameras": cameras})
    _hosts_identified(config)
    return config


def resolve_paths(config: Config, base: Path) -> Config:
    """``config`` with the rig's relative file paths (calibration file, replayed videos and image folders, a
    webcam given as a file, the viewer's avatar) made absolute from ``base``, the config file's folder: a config and
    the files it names travel together, whatever the working directory."""

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
    z = config.zenoh
    keys = ("password_file", "users_file", "tls_root_ca", "tls_cert", "tls_key")
    zenoh = z.model_copy(update={k: absolute(getattr(z, k)) for k in keys})
    f = config.fusion
    fusion = f if f.model == "default" else f.model_copy(update={"model": absolute(f.model)})
    websocket = config.websocket.model_copy(update={"avatar": absolute(config.websocket.avatar)})
    return config.model_copy(
        update={"cameras": tuple(cameras), "calibration": calibration, "zenoh": zenoh, "fusion": fusion,
                "websocket": websocket}
    )  # fmt: skip


def config_document(config: Config) -> dict[str, Any]:
    """``config`` as a JSON-able document that :func:`parse_config` reads back to an equal Config (sessions
    record the configuration they ran with)."""
    return config.model_dump(mode="json", exclude_none=True)
