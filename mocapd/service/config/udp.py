"""The ``[udp]`` section of config.toml (MVN, VMC and VRChat OSC trackers streams), parsed into frozen dataclasses
(:mod:`mocapd.service.outputs.udp` turns it into pose sinks).

Destinations come only from here. They must be loopback addresses unless ``udp.allow_remote = true``: streaming
poses to another machine is an explicit choice, never a default or a typo. Hosts are IPv4 literals (or
"localhost"); names are not resolved, so what the file says is where datagrams go.
"""

from __future__ import annotations

import ipaddress
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from mocapd.errors import ConfigError
from mocapd.protocols.vrchat import ROLES

MIN_DATAGRAM = 256
MAX_DATAGRAM = 65507  # the largest UDP payload over IPv4
RELEASE_AFTER_S = 2.0  # an automatic character id / avatar is freed after this long without its subject


@dataclass(frozen=True, slots=True)
class Destination:
    """A UDP destination (IPv4 literal, port)."""

    host: str
    port: int

    def __str__(self) -> str:
        return f"{self.host}:{self.port}"


@dataclass(frozen=True, slots=True)
class MvnStreamConfig:
    """``[udp.mvn]``: MVN network streaming (``MXTP02`` datagrams)."""

    enabled: bool = False
    destinations: tuple[Destination, ...] = (Destination("127.0.0.1", 9763),)
    """Every destination receives every streamed character."""
    rate_divisor: int = 1
    """Send every n-th output frame (60 Hz output / 2 = 30 Hz)."""
    subjects: tuple[str, ...] | None = None
    """Identities to stream (``suit:<id>``, ``track:<k>``); None: everyone."""
    character_ids: tuple[tuple[str, int], ...] = ()
    """Pinned character ids (identity, 0..255); other subjects get the lowest free id in order of appearance."""
    max_datagram_bytes: int = 1472
    """Split a character over several datagrams above this size (bytes, header included)."""


@dataclass(frozen=True, slots=True)
class VmcStreamConfig:
    """``[udp.vmc]``: VMC protocol (OSC bundles), one avatar per destination."""

    enabled: bool = False
    destinations: tuple[Destination, ...] = (Destination("127.0.0.1", 39539),)
    """Destination k is the avatar driven by subject k."""
    rate_divisor: int = 1
    subjects: tuple[str, ...] | None = None
    """``subjects[k]`` drives ``destinations[k]`` (same length); None: subjects take avatars in order of appearance."""
    max_datagram_bytes: int = 1472
    """Split a frame over several bundles above this size (bytes)."""


@dataclass(frozen=True, slots=True)
class VrChatStreamConfig:
    """``[udp.vrchat]``: VRChat OSC trackers (:mod:`mocapd.protocols.vrchat`) for one subject."""

    enabled: bool = False
    destination: Destination = Destination("127.0.0.1", 9000)
    """VRChat's OSC input port (9000) on the machine running VRChat."""
    subject: str | None = None
    """The identity streamed (``suit:<id>``, ``track:<k>``); None: the first subject to appear."""
    trackers: tuple[str, ...] = ("hip", "chest", "left_foot", "right_foot", "left_knee", "right_knee", "left_elbow",
                                 "right_elbow", "head")  # fmt: skip
    """Which trackers to send (VRChat's documentation: fewer, e.g. hip and feet, can work better)."""
    user_height_m: float | None = None
    """The user's real height; positions are scaled by it over the solved skeleton's height (None: 1)."""
    rate_divisor: int = 1


@dataclass(frozen=True, slots=True)
class UdpConfig:
    """The ``[udp]`` section."""

    allow_remote: bool = False
    """Allow non-loopback destinations."""
    mvn: MvnStreamConfig = field(default_factory=MvnStreamConfig)
    vmc: VmcStreamConfig = field(default_factory=VmcStreamConfig)
    vrchat: VrChatStreamConfig = field(default_factory=VrChatStreamConfig)


def parse_udp_config(table: Mapping[str, Any]) -> UdpConfig:
    """Build a :class:`UdpConfig` from the ``udp`` table of a parsed config.toml.

    Raises
    ------
    ConfigError
        Unknown keys, wrong types or values, or a non-loopback destination without ``allow_remote`` (the message
        names the key, the value and what is allowed).
    """
    _reject_unknown(table, {"allow_remote", "mvn", "vmc", "vrchat"}, "udp")
    allow_remote = _bool(table.get("allow_remote", False), "udp.allow_remote")
    mvn_t = _subtable(table, "mvn")
    vmc_t = _subtable(table, "vmc")
    common = {"enabled", "destinations", "rate_divisor", "subjects", "max_datagram_bytes"}
    _reject_unknown(mvn_t, common | {"character_ids"}, "udp.mvn")
    _reject_unknown(vmc_t, common, "udp.vmc")
    d_mvn, d_vmc = MvnStreamConfig(), VmcStreamConfig()
    mvn = MvnStreamConfig(
        enabled=_bool(mvn_t.get("enabled", d_mvn.enabled), "udp.mvn.enabled"),
        destinations=_destinations(mvn_t, "udp.mvn", d_mvn.destinations, allow_remote),
        rate_divisor=_int(mvn_t.get("rate_divisor", 1), "udp.mvn.rate_divisor", 1, 1000),
        subjects=_subjects(mvn_t.get("subjects", "all"), "udp.mvn.subjects"),
        character_ids=_character_ids(mvn_t.get("character_ids", {})),
        max_datagram_bytes=_int(mvn_t.get("max_datagram_bytes", 1472), "udp.mvn.max_datagram_bytes", MIN_DATAGRAM,
                                MAX_DATAGRAM),
    )  # fmt: skip
    vmc = VmcStreamConfig(
        enabled=_bool(vmc_t.get("enabled", d_vmc.enabled), "udp.vmc.enabled"),
        destinations=_destinations(vmc_t, "udp.vmc", d_vmc.destinations, allow_remote),
        rate_divisor=_int(vmc_t.get("rate_divisor", 1), "udp.vmc.rate_divisor", 1, 1000),
        subjects=_subjects(vmc_t.get("subjects", "all"), "udp.vmc.subjects"),
        max_datagram_bytes=_int(vmc_t.get("max_datagram_bytes", 1472), "udp.vmc.max_datagram_bytes", MIN_DATAGRAM,
                                MAX_DATAGRAM),
    )  # fmt: skip
    if vmc.subjects is not None and len(vmc.subjects) != len(vmc.destinations):
        raise ConfigError(
            f"udp.vmc.subjects = {list(vmc.subjects)!r} has {len(vmc.subjects)} entries for "
            f'{len(vmc.destinations)} destination(s); allowed: "all" or one identity per destination'
        )
    vrchat = _vrchat(_subtable(table, "vrchat"), allow_remote)
    return UdpConfig(allow_remote=allow_remote, mvn=mvn, vmc=vmc, vrchat=vrchat)


def _vrchat(t: Mapping[str, Any], allow_remote: bool) -> VrChatStreamConfig:
    w = "udp.vrchat"
    _reject_unknown(t, {"enabled", "destination", "subject", "trackers", "user_height_m", "rate_divisor"}, w)
    d = VrChatStreamConfig()
    destination = d.destination
    if "destination" in t:
        destination = _destination(t["destination"], f"{w}.destination", allow_remote)
    subject = t.get("subject", "")
    if not isinstance(subject, str) or subject == "all":
        raise ConfigError(f'{w}.subject = {subject!r}; allowed: "" (the first subject seen) or an identity such as '
                          '"suit:suit0"')  # fmt: skip
    trackers = t.get("trackers", list(d.trackers))
    if (not isinstance(trackers, list) or not trackers or not all(isinstance(x, str) and x in ROLES for x in trackers)
            or len(set(trackers)) != len(trackers)):  # fmt: skip
        raise ConfigError(f"{w}.trackers = {trackers!r}; allowed: a non-empty list of distinct names of {list(ROLES)}")
    height = t.get("user_height_m", 0.0)
    if isinstance(height, bool) or not isinstance(height, int | float) or not (height == 0 or 0.5 <= height <= 2.5):
        raise ConfigError(f"{w}.user_height_m = {height!r}; allowed: 0 (no scaling) or metres in 0.5..2.5")
    return VrChatStreamConfig(
        enabled=_bool(t.get("enabled", False), f"{w}.enabled"),
        destination=destination,
        subject=subject or None,
        trackers=tuple(trackers),
        user_height_m=float(height) or None,
        rate_divisor=_int(t.get("rate_divisor", 1), f"{w}.rate_divisor", 1, 1000),
    )


def _reject_unknown(t: Mapping[str, Any], allowed: set[str], where: str) -> None:
    unknown = sorted(set(t) - allowed)
    if unknown:
        raise ConfigError(f"unknown key(s) {unknown} in [{where}]; allowed: {sorted(allowed)}")


def _subtable(t: Mapping[str, Any], key: str) -> Mapping[str, Any]:
    value = t.get(key, {})
    if not isinstance(value, Mapping):
        raise ConfigError(f"udp.{key} = {value!r}; allowed: a table ([udp.{key}])")
    return value


def _bool(value: object, key: str) -> bool:
    if not isinstance(value, bool):
        raise ConfigError(f"{key} = {value!r}; allowed: true or false")
    return value


def _int(value: object, key: str, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
        raise ConfigError(f"{key} = {value!r}; allowed: an integer in {lo}..{hi}")
    return value


def _destination(value: object, key: str, allow_remote: bool) -> Destination:
    allowed = '"host:port" with an IPv4 address (or "localhost") and a port in 1..65535'
    if not isinstance(value, str) or value.count(":") != 1:
        raise ConfigError(f"{key} entry {value!r}; allowed: {allowed}")
    host, port_s = value.split(":")
    if host == "localhost":
        host = "127.0.0.1"
    try:
        addr = ipaddress.IPv4Address(host)
        port = int(port_s)
    except ValueError:
        raise ConfigError(f"{key} entry {value!r}; allowed: {allowed}") from None
    if not 1 <= port <= 65535:
        raise ConfigError(f"{key} entry {value!r}: port {port}; allowed: {allowed}")
    if addr.is_multicast or addr.is_unspecified or str(addr) == "255.255.255.255":
        raise ConfigError(f"{key} entry {value!r}: broadcast, multicast and 0.0.0.0 are not allowed; {allowed}")
    if not addr.is_loopback and not allow_remote:
        raise ConfigError(
            f"{key} entry {value!r} is not a loopback address; poses go to another machine only when "
            "udp.allow_remote = true (allowed without it: 127.0.0.0/8)"
        )
    return Destination(str(addr), port)


def _destinations(t: Mapping[str, Any], where: str, default: tuple[Destination, ...],
                  allow_remote: bool) -> tuple[Destination, ...]:  # fmt: skip
    key = f"{where}.destinations"
    if "destinations" not in t:
        return default
    raw = t["destinations"]
    if not isinstance(raw, list) or not raw:
        raise ConfigError(f'{key} = {raw!r}; allowed: a non-empty list of "host:port" strings')
    out = tuple(_destination(v, key, allow_remote) for v in raw)
    if len(set(out)) != len(out):
        raise ConfigError(f"{key} = {raw!r} lists a destination twice; allowed: distinct destinations")
    return out


def _subjects(value: object, key: str) -> tuple[str, ...] | None:
    if value == "all":
        return None
    if (not isinstance(value, list) or not value
            or not all(isinstance(s, str) and s and s != "all" for s in value)):  # fmt: skip
        raise ConfigError(f'{key} = {value!r}; allowed: "all" or a non-empty list of identities such as "suit:suit0"')
    if len(set(value)) != len(value):
        raise ConfigError(f"{key} = {value!r} names a subject twice; allowed: distinct identities")
    return tuple(value)


def _character_ids(value: object) -> tuple[tuple[str, int], ...]:
    key = "udp.mvn.character_ids"
    if not isinstance(value, Mapping):
        raise ConfigError(f'{key} = {value!r}; allowed: a table identity = id, e.g. {{ "suit:suit0" = 0 }}')
    out = []
    for ident, cid in value.items():
        out.append((str(ident), _int(cid, f"{key}.{ident!r}", 0, 255)))
    ids = [c for _, c in out]
    if len(set(ids)) != len(ids):
        raise ConfigError(f"{key} = {dict(value)!r} gives two subjects the same id; allowed: distinct ids 0..255")
    return tuple(out)
