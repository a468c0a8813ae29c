"""The ``[imu]`` section: serial Xsens devices, the sensor-to-bone assignment, the bridge input and the
experimental Awinda station. The io layer's :class:`~mocapd.io.xsens_serial.XsensPortConfig` (one per port) and
the protocol layer's :class:`~mocapd.protocols.awinda.AwindaConfig` are built from it."""

from __future__ import annotations

import ipaddress
from collections.abc import Mapping
from typing import TYPE_CHECKING, Annotated, Literal, Self

from pydantic import AfterValidator, Field, model_validator

from mocapd.core.body_dims import LIMITS, BodySpec
from mocapd.core.imu_calibration import MAX_SUIT_SENSORS, is_per_person, parse_assignment, parse_person_assignment
from mocapd.core.skeleton import REFERENCE_HEIGHT
from mocapd.errors import ConfigError
from mocapd.protocols.awinda import AwindaConfig
from mocapd.protocols.slimevr import PORT
from mocapd.protocols.xsens_session import MAX_RATE_HZ, MIN_RATE_HZ
from mocapd.service.config.schema import PathStr, RuleError, Section, Seq, Text, unique

if TYPE_CHECKING:  # the devices' modules (asyncio, serial ports, sockets): imported when their options are built
    from mocapd.io.slimevr import SlimeVrConfig
    from mocapd.io.xsens_serial import XsensPortConfig

MAX_PORTS = 64
"""Serial devices one daemon opens at most (4 suits of 13 sensors, cabled, and then some)."""
MAX_BUFFER = 8192
"""Most samples kept per sensor: 68 s at 120 Hz, ~1.3 MB per sensor (each slot is stored twice, 80 bytes)."""


def _assignment(mapping: dict[str, str | dict[str, str]]) -> dict[str, str | dict[str, str]]:
    """Ids upper-cased; a bad id, an unknown or repeated bone is an error. Per-person tables
    (``[imu.assignment.alice]``) are one suit each; a sensor entry beside them, a bad person name or a sensor of
    two persons is an error."""
    try:
        if is_per_person(mapping):
            return dict(parse_person_assignment(mapping))
        return dict(parse_assignment(_flat(mapping)))
    except ConfigError as exc:
        raise ValueError(str(exc).removeprefix("imu assignment: ")) from None


def _flat(table: Mapping[str, str | dict[str, str]]) -> dict[str, str]:
    """The sensor entries of an assignment table (all of a flat one, none of a per-person one)."""
    return {k: v for k, v in table.items() if isinstance(v, str)}


def _per_person(table: Mapping[str, str | dict[str, str]]) -> dict[str, dict[str, str]]:
    """The person tables of an assignment table (none of a flat one)."""
    return {k: v for k, v in table.items() if isinstance(v, dict)}


def _sensors_of(table: Mapping[str, str | dict[str, str]]) -> dict[str, str]:
    """Every sensor's bone in an assignment table, flat or per person."""
    return {**_flat(table), **{s: b for t in _per_person(table).values() for s, b in t.items()}}


#: ``[imu.assignment]`` and ``[imu.slimevr.assignment]``: sensor id -> bone (one suit), or person -> such a table
#: (a suit each)
Assignment = Annotated[
    dict[Text, Text | Annotated[dict[Text, Text], Field(max_length=MAX_SUIT_SENSORS)]],
    Field(max_length=64),
    AfterValidator(_assignment),
]


Port = Annotated[PathStr, Field(min_length=1)]


class BridgeConfig(Section):
    """``[imu.bridge]``: the UDP msgpack input for vendor-SDK forwarders."""

    enabled: bool = False
    host: Literal["127.0.0.1", "::1", "localhost"] = "127.0.0.1"
    """The bridge listens on loopback only."""
    port: int = Field(9773, ge=1, le=65535)


class AwindaSection(Section):
    """``[imu.awinda]``: the EXPERIMENTAL Awinda station path (:class:`~mocapd.protocols.awinda.AwindaConfig`)."""

    experimental: bool = False
    path: PathStr = ""
    radio_channel: int = Field(19, ge=11, le=25)
    update_rate_hz: int = Field(60, ge=1, le=120)
    update_rate_mid: int = Field(0x04, ge=0, le=254)
    """Xbus message id that sets the update rate; the reply is id + 1, so at most 254."""
    delta_q_scale: float | None = Field(None, gt=0.0, le=1.0)
    """Radians per SDI delta-q unit: not publicly documented, no default."""
    delta_v_scale: float | None = Field(None, gt=0.0, le=1.0)
    """m/s per SDI delta-v unit: not publicly documented, no default."""

    @model_validator(mode="after")
    def _complete_when_enabled(self) -> Self:
        if self.experimental:
            for key in ("path", "delta_q_scale", "delta_v_scale"):
                if getattr(self, key) in ("", None):
                    raise RuleError(
                        "{0} needs {1}: set it (the scale factors are not publicly documented, see docs/imu.md)",
                        "experimental",
                        key,
                        values=(True, getattr(self, key)),
                    )
        return self

    def options(self) -> AwindaConfig:
        return AwindaConfig(
            experimental=self.experimental,
            path=self.path,
            radio_channel=self.radio_channel,
            update_rate_hz=self.update_rate_hz,
            update_rate_mid=self.update_rate_mid,
            delta_q_scale=self.delta_q_scale,
            delta_v_scale=self.delta_v_scale,
        )


def _ip_literal(host: str) -> str:
    try:
        ipaddress.ip_address("127.0.0.1" if host == "localhost" else host)
    except ValueError:
        raise ValueError(
            'must be an IP address literal ("127.0.0.1" keeps it on this machine; trackers on the network need '
            'this machine\'s address or "0.0.0.0")'
        ) from None
    return host


def _slimevr_assignment(mapping: dict[str, str | dict[str, str]]) -> dict[str, str | dict[str, str]]:
    parsed = _assignment(mapping)
    xsens = sorted(s for s in _sensors_of(parsed) if "/" not in s)
    if xsens:
        raise ValueError(
            f'{xsens} are Xsens ids; SlimeVR sensors are "<MAC>/<sensor index>", e.g. "AA:BB:CC:DD:EE:FF/0"'
        )
    return parsed


class SlimeVrSection(Section):
    """``[imu.slimevr]``: mocapd as the SlimeVR server of SlimeVR trackers on the local network (UDP)."""

    enabled: bool = False
    host: Annotated[Text, AfterValidator(_ip_literal)] = "127.0.0.1"
    """Listening address: loopback unless set; trackers on the network need this machine's address or 0.0.0.0."""
    port: int = Field(PORT, ge=0, le=65535)
    assignment: Annotated[Assignment, AfterValidator(_slimevr_assignment)] = Field(default_factory=dict)
    """``"<MAC>/<sensor index>"`` -> bone, or person -> such a table."""
    reset_taps: int = Field(2, ge=0, le=5)
    """Taps on the chest (or hips) tracker that ask for a heading reset, as in the SlimeVR server (0: off)."""
    reset_delay_s: float = Field(1.0, ge=0.0, le=10.0)
    """A reset asked on a tracker (taps, its button) happens this long after: the hand goes back down first."""

    def options(self) -> SlimeVrConfig:
        from mocapd.io.slimevr import SlimeVrConfig

        return SlimeVrConfig(enabled=self.enabled, host=self.host, port=self.port, assignment=self.sensors)

    @property
    def sensors(self) -> dict[str, str]:
        """Every assigned SlimeVR sensor's bone, of every person."""
        return _sensors_of(self.assignment)


_Segment = Annotated[float | None, Field(ge=LIMITS[0], le=LIMITS[1])]


class BodyConfig(Section):
    """``[imu.body]``: the suit wearer's body, when no camera measures it (:mod:`mocapd.core.body_dims`)."""

    height_m: float = Field(REFERENCE_HEIGHT, ge=0.5, le=2.6)
    """Sizes every segment not given below."""
    hip_width_m: _Segment = None
    thigh_m: _Segment = None
    shank_m: _Segment = None
    foot_m: _Segment = None
    ankle_height_m: _Segment = None
    torso_m: _Segment = None
    shoulder_width_m: _Segment = None
    upper_arm_m: _Segment = None
    forearm_m: _Segment = None

    def spec(self) -> BodySpec:
        given = {k.removesuffix("_m"): v for k, v in self.model_dump().items() if k != "height_m" and v is not None}
        return BodySpec(self.height_m, given)


class ImuConfig(Section):
    """``[imu]``: everything mocapd needs to know about its IMUs."""

    ordered = (("reconnect_min_s", "<=", "reconnect_max_s"),)

    ports: Annotated[Seq[Port], Field(max_length=MAX_PORTS), AfterValidator(unique)] = ()
    """Serial device paths, one per Xsens device."""
    rate_hz: int = Field(100, ge=MIN_RATE_HZ, le=MAX_RATE_HZ)
    baudrate: int = Field(921_600, ge=1200, le=4_000_000)
    response_timeout_s: float = Field(0.5, gt=0.0, le=60.0)
    attempts: int = Field(3, ge=1, le=100)
    reconnect_min_s: float = Field(0.2, gt=0.0, le=600.0)
    reconnect_max_s: float = Field(5.0, gt=0.0, le=3600.0)
    stall_timeout_s: float = Field(2.0, gt=0.0, le=600.0)
    imu_set: Literal["", "13", "6", "lower"] = ""
    """The sensor set the assignment must form ("" = no check)."""
    calibration_dir: PathStr = "calibration"
    buffer_capacity: int = Field(512, ge=16, le=MAX_BUFFER)
    assignment: Assignment = Field(default_factory=dict)
    """Sensor id (8 hex digits, stored upper-case) -> bone (one suit), or person -> such a table (a suit each)."""
    bridge: BridgeConfig = Field(default_factory=BridgeConfig)
    awinda: AwindaSection = Field(default_factory=AwindaSection)
    slimevr: SlimeVrSection = Field(default_factory=SlimeVrSection)
    body: BodyConfig = Field(default_factory=BodyConfig)

    @property
    def persons(self) -> dict[str, dict[str, str]]:
        """Each person's sensors and bones where the assignment is written per person (``[imu.assignment.alice]``,
        ``[imu.slimevr.assignment.alice]``, merged): one suit each. Empty for the flat form (one suit)."""
        out: dict[str, dict[str, str]] = {}
        for table in (self.assignment, self.slimevr.assignment):
            for person, sensors in _per_person(table).items():
                out.setdefault(person, {}).update(sensors)
        return out

    @property
    def sensors(self) -> dict[str, str]:
        """Every sensor's bone, whatever carries it (Xsens ``assignment`` and ``slimevr.assignment``) and whoever
        wears it: the sensors the daemon opens and keeps. One suit in the flat form; with per-person tables a bone
        appears once per person (:attr:`persons` says whose)."""
        return {**_sensors_of(self.assignment), **self.slimevr.sensors}

    def suit_sensors(self, person: str) -> dict[str, str]:
        """The sensors ``mocapd calibrate imu --person`` calibrates: the person's table, or every sensor (flat form).

        Raises
        ------
        ConfigError
            The assignment is per person and ``person`` has no table (the message names those who have one).
        """
        persons = self.persons
        if not persons:
            return self.sensors
        if person not in persons:
            raise ConfigError(
                f"--person {person!r} has no table in [imu.assignment]: the assignment is per person, with tables "
                f"for {', '.join(persons)}"
            )
        return persons[person]

    def sources(self) -> list[str]:
        """The IMU inputs this section opens, one phrase each (empty: no IMU source): what ``check-config`` says a
        rig without cameras runs on."""
        ports = self.ports
        many = f"{len(ports)} Xsens serial ports ({ports[0]} ... {ports[-1]})" if len(ports) > 2 else ""
        out = [many] if many else [f"Xsens serial port {p}" for p in ports]
        if self.awinda.experimental:
            out.append(f"Awinda station {self.awinda.path} (experimental)")
        if self.slimevr.enabled:
            out.append(f"SlimeVR server on udp {self.slimevr.host}:{self.slimevr.port}")
        if self.bridge.enabled:
            out.append(f"IMU bridge on udp {self.bridge.host}:{self.bridge.port}")
        return out

    @model_validator(mode="after")
    def _one_bone_per_sensor(self) -> Self:
        """A sensor in both tables, two sensors (of either transport) on one bone of one suit, or one table per
        person beside a flat one, is an error."""
        xsens, slime = self.assignment, self.slimevr.assignment
        both = sorted(set(_sensors_of(xsens)) & set(_sensors_of(slime)))
        problem = f"both name {both} (a sensor in both tables)" if both else ""
        if not problem and (_flat(xsens) or _flat(slime)) and (_per_person(xsens) or _per_person(slime)):
            problem = "one is written per person and the other is not: write both per person ([...assignment.NAME])"
        if not problem:
            for person, table in (self.persons or {"": self.sensors}).items():
                try:
                    parse_assignment(table)
                except ConfigError as exc:
                    problem = (f"{person}'s tables: " if person else "") + str(exc).removeprefix("imu assignment: ")
                    break
        if problem:
            raise RuleError("{0} and {1}: " + problem.replace("{", "{{").replace("}", "}}"), "assignment",
                            "slimevr.assignment", values=(self.assignment, self.slimevr.assignment))  # fmt: skip
        return self

    @model_validator(mode="after")
    def _assignment_forms_the_set(self) -> Self:
        if self.imu_set:
            for person, table in (self.persons or {"": self.sensors}).items():
                try:
                    parse_assignment(table, imu_set=self.imu_set)
                except ConfigError as exc:
                    whose = f" ({person}'s table)" if person else ""
                    raise RuleError(
                        f"{{0}}{whose} does not form {{1}}: {str(exc).removeprefix('imu assignment ')}",
                        "assignment",
                        "imu_set",
                        values=(table, self.imu_set),
                    ) from None
        return self

    def port_configs(self) -> tuple[XsensPortConfig, ...]:
        """One :class:`XsensPortConfig` per entry of ``ports``, each with this section's settings."""
        from mocapd.io.xsens_serial import XsensPortConfig

        return tuple(
            XsensPortConfig(
                path=p,
                baudrate=self.baudrate,
                rate_hz=self.rate_hz,
                response_timeout_s=self.response_timeout_s,
                attempts=self.attempts,
                reconnect_min_s=self.reconnect_min_s,
                reconnect_max_s=self.reconnect_max_s,
                stall_timeout_s=self.stall_timeout_s,
            )
            for p in self.ports
        )
