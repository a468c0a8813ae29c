"""The ``[udp]`` section of config.toml (MVN, VMC, VRChat and Rokoko streams); :mod:`mocapd.service.outputs.udp`
turns it into pose sinks.

Destinations come only from here. They must be loopback addresses unless ``udp.allow_remote = true``: streaming
poses to another machine is an explicit choice, never a default or a typo. Hosts are IPv4 literals (or
"localhost"); names are not resolved, so what the file says is where datagrams go.
"""

from __future__ import annotations

import ipaddress
from dataclasses import dataclass
from typing import Annotated, Literal, Self

from pydantic import (
    AfterValidator,
    BeforeValidator,
    Field,
    PlainSerializer,
    PlainValidator,
    WithJsonSchema,
    model_validator,
)

from mocapd.protocols.rokoko import DEFAULT_MAX_DATAGRAM as ROKOKO_MAX_DATAGRAM
from mocapd.protocols.rokoko import DEFAULT_PORT as ROKOKO_PORT
from mocapd.protocols.vrchat import DEFAULT_PORT as VRCHAT_PORT
from mocapd.protocols.vrchat import ROLES
from mocapd.service.config.schema import Allowed, RuleError, Section, Text, as_tuple, show, unique

MIN_DATAGRAM = 256
MAX_DATAGRAM = 65507  # the largest UDP payload over IPv4
RELEASE_AFTER_S = 2.0  # an automatic character id / avatar is freed after this long without its subject
MAX_DESTINATIONS = 64


@dataclass(frozen=True, slots=True)
class Destination:
    """A UDP destination (IPv4 literal, port)."""

    host: str
    port: int

    def __str__(self) -> str:
        return f"{self.host}:{self.port}"


_HOST_PORT = '"host:port" with an IPv4 address (or "localhost") and a port in 1..65535'


def _destination(value: object) -> Destination:
    """``"127.0.0.1:9763"`` (or a Destination) -> Destination; the loopback rule is UdpConfig's (allow_remote)."""
    text = str(value) if isinstance(value, Destination) else value
    if not isinstance(text, str) or text.count(":") != 1:
        raise ValueError(f"allowed: {_HOST_PORT}")
    host, port_s = text.split(":")
    if host == "localhost":
        host = "127.0.0.1"
    try:
        addr = ipaddress.IPv4Address(host)
        port = int(port_s) if port_s.isascii() and port_s.isdigit() and len(port_s) <= 5 else -1
    except ValueError:
        raise ValueError(f"allowed: {_HOST_PORT}") from None
    if not 1 <= port <= 65535:
        raise ValueError(f"port {port_s!r}; allowed: {_HOST_PORT}")
    if addr.is_multicast or addr.is_unspecified or str(addr) == "255.255.255.255":
        raise ValueError(f"broadcast, multicast and 0.0.0.0 are not allowed; allowed: {_HOST_PORT}")
    return Destination(str(addr), port)


def _identity(value: str) -> str:
    if value == "all":
        raise ValueError('"all" is not an identity: write subjects = "all" instead of a list')
    return value


def _subjects(value: object) -> object:
    """``"all"`` -> None (everyone); an array -> a tuple of identities."""
    if value == "all":
        return None
    return tuple(value) if isinstance(value, list) else value


def _subjects_out(value: tuple[str, ...] | None) -> object:
    return "all" if value is None else list(value)


def _distinct_ids(ids: dict[str, int]) -> dict[str, int]:
    if len(set(ids.values())) != len(ids):
        raise ValueError("gives two subjects the same id; allowed: distinct ids 0..255")
    return ids


Dest = Annotated[
    Destination,
    PlainValidator(_destination),
    PlainSerializer(str, return_type=str),
    WithJsonSchema({"type": "string", "maxLength": 32}),  # "255.255.255.255:65535" at most, as the file writes it
    Allowed(_HOST_PORT),
]
Destinations = Annotated[
    tuple[Dest, ...],
    BeforeValidator(as_tuple),
    Field(min_length=1, max_length=MAX_DESTINATIONS),
    AfterValidator(unique),
]
Identity = Annotated[Text, Field(min_length=1), AfterValidator(_identity)]
Subjects = Annotated[
    Annotated[tuple[Identity, ...], Field(min_length=1, max_length=MAX_DESTINATIONS), AfterValidator(unique)] | None,
    BeforeValidator(_subjects),
    PlainSerializer(_subjects_out),
    Allowed('"all" or a non-empty array of distinct identities such as "suit:suit0" or "track:3"'),
]
CharacterId = Annotated[int, Field(ge=0, le=255)]


class MvnStreamConfig(Section):
    """``[udp.mvn]``: MVN network streaming (``MXTP02`` datagrams)."""

    enabled: bool = False
    destinations: Destinations = (Destination("127.0.0.1", 9763),)
    """Every destination receives every streamed character."""
    rate_divisor: int = Field(1, ge=1, le=1000)
    """Send every n-th output frame (60 Hz output / 2 = 30 Hz)."""
    subjects: Subjects = None
    """Identities to stream (``suit:<id>``, ``track:<k>``); None ("all"): everyone."""
    character_ids: Annotated[dict[Identity, CharacterId], Field(max_length=256), AfterValidator(_distinct_ids)] = Field(
        default_factory=dict
    )
    """Pinned character ids (identity -> 0..255); other subjects get the lowest free id in order of appearance."""
    max_datagram_bytes: int = Field(1472, ge=MIN_DATAGRAM, le=MAX_DATAGRAM)
    """Split a character over several datagrams above this size (bytes, header included)."""


class VmcStreamConfig(Section):
    """``[udp.vmc]``: VMC protocol (OSC bundles), one avatar per destination."""

    enabled: bool = False
    destinations: Destinations = (Destination("127.0.0.1", 39539),)
    """Destination k is the avatar driven by subject k."""
    rate_divisor: int = Field(1, ge=1, le=1000)
    subjects: Subjects = None
    """``subjects[k]`` drives ``destinations[k]`` (same length); None ("all"): subjects take avatars in order of
    appearance."""
    max_datagram_bytes: int = Field(1472, ge=MIN_DATAGRAM, le=MAX_DATAGRAM)
    """Split a frame over several bundles above this size (bytes)."""

    @model_validator(mode="after")
    def _one_subject_per_avatar(self) -> Self:
        if self.subjects is not None and len(self.subjects) != len(self.destinations):
            raise RuleError(
                f"{{0}} has {len(self.subjects)} entries for the {len(self.destinations)} of {{1}}; "
                'allowed: "all" or one identity per destination',
                "subjects",
                "destinations",
                values=(list(self.subjects), [str(d) for d in self.destinations]),
            )
        return self


def _role(value: str) -> str:
    if value not in ROLES:
        raise ValueError(f"allowed: {', '.join(ROLES)}")
    return value


def _user_height(value: float) -> float:
    if value != 0 and not 0.5 <= value <= 2.5:
        raise ValueError("allowed: 0 (no scaling) or metres in [0.5, 2.5]")
    return value


class VrChatStreamConfig(Section):
    """``[udp.vrchat]``: VRChat's OSC trackers (:mod:`mocapd.protocols.vrchat`) for one subject."""

    enabled: bool = False
    destination: Dest = Destination("127.0.0.1", VRCHAT_PORT)
    """VRChat's OSC input port (9000) on the machine running VRChat."""
    subject: Annotated[Text, Allowed('"" (the first subject seen) or an identity such as "suit:suit0"')] = ""
    """The identity streamed; "": the first subject to appear."""
    trackers: Annotated[
        tuple[Annotated[Text, AfterValidator(_role)], ...],
        BeforeValidator(as_tuple),
        Field(min_length=1, max_length=len(ROLES)),
        AfterValidator(unique),
        Allowed(f"a non-empty array of distinct names of {', '.join(ROLES)}"),
    ] = ROLES
    """Which trackers to send (VRChat's documentation: fewer, e.g. hip and feet, can work better)."""
    user_height_m: Annotated[float, Field(ge=0.0, le=2.5), AfterValidator(_user_height)] = 0.0
    """The user's real height; positions are scaled by it over the solved skeleton's height (0: no scaling)."""
    rate_divisor: int = Field(1, ge=1, le=1000)

    @model_validator(mode="after")
    def _an_identity(self) -> Self:
        if self.subject == "all":
            raise RuleError('{0}: one subject drives the trackers, not "all"', "subject", values=(self.subject,))
        return self


def _distinct_names(names: dict[str, str]) -> dict[str, str]:
    if len(set(names.values())) != len(names):
        raise ValueError("gives two subjects the same actor name; allowed: distinct names")
    return names


ActorName = Annotated[Text, Field(min_length=1, max_length=64)]


class RokokoStreamConfig(Section):
    """``[udp.rokoko]``: Rokoko Studio Live JSON v3 (:mod:`mocapd.protocols.rokoko`), every subject an actor."""

    enabled: bool = False
    destinations: Destinations = (Destination("127.0.0.1", ROKOKO_PORT),)
    """Every destination receives the whole scene (14043: the plugins' default port)."""
    rate_divisor: int = Field(1, ge=1, le=1000)
    subjects: Subjects = None
    """Identities to stream; None ("all"): everyone (64 actors at most)."""
    actor_names: Annotated[dict[Identity, ActorName], Field(max_length=64), AfterValidator(_distinct_names)] = Field(
        default_factory=dict
    )
    """The actor name a subject has in the plugins (identity -> name); default: the identity itself."""
    compression: Literal["lz4", "none"] = "lz4"
    """``lz4``: an LZ4 frame per datagram (the Unity and Unreal plugins read only that); ``none``: plain JSON."""
    max_datagram_bytes: int = Field(ROKOKO_MAX_DATAGRAM, ge=1024, le=MAX_DATAGRAM)
    """Largest datagram (bytes); actors that would not fit are left out of that frame (32768: Unreal's buffer)."""


class UdpConfig(Section):
    """The ``[udp]`` section."""

    allow_remote: bool = False
    """Allow non-loopback destinations."""
    mvn: MvnStreamConfig = Field(default_factory=MvnStreamConfig)
    vmc: VmcStreamConfig = Field(default_factory=VmcStreamConfig)
    vrchat: VrChatStreamConfig = Field(default_factory=VrChatStreamConfig)
    rokoko: RokokoStreamConfig = Field(default_factory=RokokoStreamConfig)

    @model_validator(mode="after")
    def _loopback_unless_allowed(self) -> Self:
        if self.allow_remote:
            return self
        for stream in ("mvn", "vmc", "vrchat", "rokoko"):
            s = getattr(self, stream)
            dests: tuple[Destination, ...] = s.destinations if stream != "vrchat" else (s.destination,)
            for d in dests:
                if not ipaddress.IPv4Address(d.host).is_loopback:
                    raise RuleError(
                        f"{{0}}: {show(str(d))} is not a loopback address; poses go to another machine only when "
                        "{1} (allowed without it: 127.0.0.0/8)",
                        f"{stream}.destinations" if stream != "vrchat" else "vrchat.destination",
                        "allow_remote",
                        values=([str(x) for x in dests], True),
                    )
        return self


def describe_streams(udp: UdpConfig) -> list[str]:
    """One line per enabled UDP stream, where it goes: what ``mocapd run`` and the demos print at READY, so that a
    stream turned on in the config is seen to be on (and a receiver on another port is seen to be missed)."""

    def to(dests: tuple[Destination, ...]) -> str:
        return ", ".join(str(d) for d in dests)

    def who(subjects: tuple[str, ...] | None) -> str:
        return "every subject" if subjects is None else ", ".join(subjects)

    lines = []
    if udp.mvn.enabled:
        lines.append(f"MVN network stream (Xsens plugins) to {to(udp.mvn.destinations)}: {who(udp.mvn.subjects)}")
    if udp.vmc.enabled:
        avatars = "a subject per avatar" if udp.vmc.subjects is None else who(udp.vmc.subjects)
        lines.append(f"VMC (OSC) avatars to {to(udp.vmc.destinations)}: {avatars}")
    if udp.vrchat.enabled:
        lines.append(f"VRChat OSC trackers to {udp.vrchat.destination}: {udp.vrchat.subject or 'the first subject'}")
    if udp.rokoko.enabled:
        lines.append(f"Rokoko Studio Live ({udp.rokoko.compression}) to {to(udp.rokoko.destinations)}: "
                     f"{who(udp.rokoko.subjects)} as actors")  # fmt: skip
    return lines
