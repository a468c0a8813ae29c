"""Zenoh sessions as ``[zenoh]`` describes them, and the key expressions of camera hosts.

What the session may do is decided here, once: it listens and connects only on the configured endpoints (a peer
left without ``listen`` endpoints would otherwise listen on every interface, ``tcp/[::]:0``), scouting is off
(multicast scouting sends on every interface; gossip would connect to peers of peers), user/password or TLS
when configured (the schema refuses endpoints off loopback without one of them); with a certificate of its own a
session uses mutual TLS (``enable_mtls``): as a listener it accepts only peers presenting a certificate signed by
``tls_root_ca``, as a connector it presents its own.
"""

from __future__ import annotations

import json
import socket
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Protocol

import zenoh

from mocapd.errors import ConfigError, DeviceError
from mocapd.io.input_files import read_input_text


class ZenohConfig(Protocol):
    """What the Zenoh adapters read of ``[zenoh]`` (the service's validated section,
    :class:`mocapd.service.config.zenoh.ZenohConfig`, has these keys; io does not import the service layer)."""

    @property
    def rig(self) -> str: ...
    @property
    def host(self) -> str: ...
    @property
    def mode(self) -> str: ...
    @property
    def listen(self) -> Sequence[str]: ...
    @property
    def connect(self) -> Sequence[str]: ...
    @property
    def user(self) -> str: ...
    @property
    def password_file(self) -> str: ...
    @property
    def users_file(self) -> str: ...
    @property
    def tls_root_ca(self) -> str: ...
    @property
    def tls_cert(self) -> str: ...
    @property
    def tls_key(self) -> str: ...
    @property
    def lost_after_s(self) -> float: ...
    @property
    def status_period_s(self) -> float: ...
    @property
    def clock_period_s(self) -> float: ...
    @property
    def clock_timeout_s(self) -> float: ...
    @property
    def clock_window(self) -> int: ...
    @property
    def clock_drift_ppm(self) -> float: ...


def detections_key(rig: str, camera: str) -> str:
    return f"mocapd/{rig}/{camera}/detections"


def status_key(rig: str, host: str) -> str:
    return f"mocapd/{rig}/hosts/{host}/status"


def clock_key(rig: str, host: str) -> str:
    return f"mocapd/{rig}/hosts/{host}/clock"


def host_name(z: ZenohConfig) -> str:
    """``[zenoh] host``, or the machine's host name (its first label) when that is ""."""
    if z.host:
        return z.host
    name = socket.gethostname().split(".")[0]
    cleaned = "".join(ch if ch.isalnum() or ch in "_-" else "-" for ch in name)[:32]
    return cleaned or "host"


def _read_secret(path: str, key: str) -> str:
    try:  # a regular file of a few bytes: a FIFO would block the start, a link to /dev/zero never end
        text = read_input_text(path, f"zenoh.{key}", max_bytes=4096, errors="strict", error=ConfigError).strip()
    except UnicodeDecodeError as exc:
        raise ConfigError(f"zenoh.{key} = {path!r}: cannot read: {exc}") from None
    if not text or "\n" in text:
        raise ConfigError(f"zenoh.{key} = {path!r}: must hold one line, the password")
    return text


def session_settings(z: ZenohConfig) -> dict[str, Any]:
    """The Zenoh configuration (path -> value, as ``zenoh.Config.insert_json5`` takes them) of ``[zenoh]``."""
    out: dict[str, Any] = {
        "mode": z.mode,
        "listen/endpoints": list(z.listen),
        "connect/endpoints": list(z.connect),
        "connect/exit_on_failure": False,  # the other side may start later or restart: keep retrying
        "scouting/multicast/enabled": False,
        "scouting/gossip/enabled": False,
        "adminspace/enabled": False,
    }
    if z.user:
        auth: dict[str, str] = {"user": z.user, "password": _read_secret(z.password_file, "password_file")}
        if z.users_file:
            if not Path(z.users_file).is_file():
                raise ConfigError(f"zenoh.users_file = {z.users_file!r}: no such file")
            auth["dictionary_file"] = z.users_file
        out["transport/auth/usrpwd"] = auth
    if z.tls_root_ca:
        tls: dict[str, Any] = {"root_ca_certificate": z.tls_root_ca}
        if z.tls_cert:
            tls |= {"listen_certificate": z.tls_cert, "listen_private_key": z.tls_key,
                    "connect_certificate": z.tls_cert, "connect_private_key": z.tls_key,
                    "enable_mtls": True}  # fmt: skip
        for key in ("tls_root_ca", "tls_cert", "tls_key"):
            if getattr(z, key) and not Path(getattr(z, key)).is_file():
                raise ConfigError(f"zenoh.{key} = {getattr(z, key)!r}: no such file")
        out["transport/link/tls"] = tls
    return out


def open_session(z: ZenohConfig) -> zenoh.Session:
    """A Zenoh session of ``[zenoh]`` (blocking: listens and starts connecting).

    Raises
    ------
    ConfigError
        A password, users or certificate file is missing or unreadable.
    DeviceError
        Zenoh refused the configuration or cannot listen (an endpoint in use, an address not on this machine).
    """
    config = zenoh.Config()
    for path, value in session_settings(z).items():
        config.insert_json5(path, json.dumps(value))
    try:
        return zenoh.open(config)
    except zenoh.ZError as exc:
        raise DeviceError(f"zenoh: cannot open a session (listen {list(z.listen)}, connect {list(z.connect)}): "
                          f"{exc}") from None  # fmt: skip
