"""Zenoh sessions as ``[zenoh]`` describes them, and the key expressions of camera hosts.

What the session may do is decided here, once: it listens and connects only on the configured endpoints (a peer
left without ``listen`` endpoints would otherwise listen on every interface, ``tcp/[::]:0``), scouting is off
(multicast scouting sends on every interface; gossip would connect to peers of peers), user/password or TLS
when configured (the schema refuses endpoints off loopback without one of them); with a certificate of its own a
session uses mutual TLS (``enable_mtls``): as a listener it accepts only peers presenting a certificate signed by
``tls_root_ca``, as a connector it presents its own.

Who may speak for which camera host (``identities``, issue 34) is Zenoh's access control on the solver host's
session (:func:`access_control`): everything a peer sends is refused (``default_permission = "deny"``) except, for
the peer authenticated as a host's identity (its user name, or its certificate's common name), that host's status,
its cameras' detections and the declaration and replies of its clock queryable. The check is Zenoh's, on the
link's authenticated identity, before a message reaches mocapd: one camera host cannot publish as another even
with valid credentials of its own. Zenoh does not tell the application what its access control dropped (no hook,
no statistics in zenoh-python 1.10), so those are not counted here; what gets through and is still wrong (a status
message naming another host on a host's own key, another camera's frame) is counted by the solver host
(:mod:`mocapd.pipeline.remote_cameras`), and the identities of the links up are shown in ``/status``.
"""

from __future__ import annotations

import json
import socket
from collections.abc import Mapping, Sequence
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
    @property
    def identities(self) -> Mapping[str, str]: ...


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


ACL_MESSAGES = ("put", "delete", "query", "reply", "declare_subscriber", "declare_queryable", "liveliness_token",
                "liveliness_query", "declare_liveliness_subscriber")  # fmt: skip
"""Every message kind Zenoh's access control knows (this side may send all of them: egress is allowed)."""


def access_control(rig: str, identities: Mapping[str, str], cameras: Mapping[str, Sequence[str]]) -> dict[str, Any]:
    """Zenoh's ``access_control`` for a solver host: each host's keys only from its identity (module docstring).

    Parameters
    ----------
    rig : str
        ``[zenoh] rig``.
    identities : {host: "user:<name>" | "cert:<common name>"}
        ``[zenoh] identities`` (checked by the schema).
    cameras : {host: [camera, ...]}
        The ``source = "zenoh"`` cameras of each host; a host left out has none (its status and clock still).
    """
    rules: list[dict[str, Any]] = [
        {"id": "solver_out", "messages": list(ACL_MESSAGES), "flows": ["egress"], "permission": "allow",
         "key_exprs": [f"mocapd/{rig}/**"]},
    ]  # fmt: skip
    subjects: list[dict[str, Any]] = [{"id": "any"}]  # no property: every peer
    policies: list[dict[str, Any]] = [{"rules": ["solver_out"], "subjects": ["any"]}]
    for k, (host, identity) in enumerate(sorted(identities.items())):
        kind, _, name = identity.partition(":")
        talk = [status_key(rig, host), *(detections_key(rig, c) for c in sorted(cameras.get(host, ())))]
        rules += [
            {"id": f"h{k}_put", "messages": ["put"], "flows": ["ingress"], "permission": "allow", "key_exprs": talk},
            {"id": f"h{k}_clock", "messages": ["declare_queryable", "reply"], "flows": ["ingress"],
             "permission": "allow", "key_exprs": [clock_key(rig, host)]},
        ]  # fmt: skip
        subjects.append({"id": f"h{k}", "usernames" if kind == "user" else "cert_common_names": [name]})
        policies.append({"rules": [f"h{k}_put", f"h{k}_clock"], "subjects": [f"h{k}"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


def session_settings(z: ZenohConfig, cameras: Mapping[str, Sequence[str]] | None = None) -> dict[str, Any]:
    """The Zenoh configuration (path -> value, as ``zenoh.Config.insert_json5`` takes them) of ``[zenoh]``.

    ``cameras`` ({host: [camera, ...]}) is given by a solver host: with ``identities`` set, its session admits each
    host's messages from that host's identity alone (:func:`access_control`).
    """
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
    if z.identities and cameras is not None:
        out["access_control"] = access_control(z.rig, z.identities, cameras)
    return out


def link_identities(session: zenoh.Session) -> list[str]:
    """The authenticated identities of the session's links (``cert:<common name>``; Zenoh 1.10 reports a
    certificate's name, not a user name: a link authenticated by user/password shows as ``"?"``)."""
    out = []
    for link in session.info.links():
        ident = link.auth_identifier
        out.append("?" if ident is None else f"cert:{ident}")
    return sorted(out)


class LinkWatch:
    """Says, once per change, whether a connecting session has a link (issue 45): Zenoh reports nothing of a link it
    cannot make (the other side refuses this side's certificate, trusts another CA, is not there), so a camera host
    printed "ready ... publishing" and published into nothing without a word.

    :meth:`check` returns a line to log when the state changed: no link ``after_s`` after the start, or none any more
    (a warning); a link again (info). None otherwise.
    """

    def __init__(self, session: Any, connect: Sequence[str], after_s: float, now_s: float) -> None:
        self.session = session
        self.connect = list(connect)
        self.after_s = after_s
        self._start_s = now_s
        self._linked: bool | None = None  # None: not said yet

    def check(self, now_s: float) -> tuple[str, str] | None:
        """(level, line) when there is something new to say, else None (never when nothing is to be connected)."""
        if not self.connect:
            return None
        linked = any(True for _ in self.session.info.links())
        if linked == self._linked or (not linked and self._linked is None and now_s - self._start_s < self.after_s):
            return None
        before, self._linked = self._linked, linked
        if linked:
            return "info", f"zenoh: linked to {', '.join(self.connect)}"
        lost = "lost its link" if before else f"no link after {now_s - self._start_s:.0f} s"
        return "warning", (
            f"zenoh: {lost} to {', '.join(self.connect)}: the other side is not there or refuses this one "
            "(TLS: a certificate its CA did not sign, or a name its [zenoh.identities] does not expect; user/password)"
        )


def open_session(z: ZenohConfig, cameras: Mapping[str, Sequence[str]] | None = None) -> zenoh.Session:
    """A Zenoh session of ``[zenoh]`` (blocking: listens and starts connecting); ``cameras`` as
    :func:`session_settings` takes it.

    Raises
    ------
    ConfigError
        A password, users or certificate file is missing or unreadable.
    DeviceError
        Zenoh refused the configuration or cannot listen (an endpoint in use, an address not on this machine).
    """
    config = zenoh.Config()
    for path, value in session_settings(z, cameras).items():
        config.insert_json5(path, json.dumps(value))
    try:
        return zenoh.open(config)
    except zenoh.ZError as exc:
        raise DeviceError(f"zenoh: cannot open a session (listen {list(z.listen)}, connect {list(z.connect)}): "
                          f"{exc}") from None  # fmt: skip
