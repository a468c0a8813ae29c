"""The ``[zenoh]`` section: how camera hosts (``mocapd detect-host``) and the solver host reach each other.

Endpoints are explicit (Zenoh locators ``tcp/<ip>:<port>`` or ``tls/<ip>:<port>``, IP literals only: what the
file says is where mocapd listens and connects). Zenoh's scouting is always off (its multicast scouting would send
on every interface of the machine; with explicit endpoints it finds nothing anyway). Any endpoint off loopback
needs authentication of both sides: user/password (``user``, ``password_file``, and ``users_file`` on a listener)
or mutual TLS (``tls/`` endpoints with ``tls_root_ca``, and ``tls_cert``/``tls_key`` on the listener *and* on the
connecting side: a listener with a certificate asks every peer for one signed by its CA, so knowing the public CA
certificate is not enough to connect): mocapd refuses the config otherwise. docs/scaling.md shows both.

Who speaks for a camera host (issue 34): on the solver host, ``identities`` names the authenticated identity of each
camera host (``hostA = "user:hostA"``: the user name it presents; ``"cert:hostA.studio"``: the common name of its
certificate). The Zenoh session then enforces it (Zenoh's access control, :func:`mocapd.io.zenoh_link.access_control`):
that identity alone may publish the host's status and its cameras' detections and answer its clock queries. A user
name is checked by this side only when it listens with ``users_file``; a certificate's name on any TLS link.
"""

from __future__ import annotations

import ipaddress
import re
from typing import Annotated, Literal, Self

from pydantic import AfterValidator, Field, model_validator

from mocapd.service.config.schema import Allowed, PathStr, RuleError, Section, Seq, Text, unique

_ENDPOINT = re.compile(r"^(tcp|tls)/(\[[0-9A-Fa-f:.]+\]|[0-9.]+):([0-9]{1,5})$")
_HOST_NAME = re.compile(r"^[A-Za-z0-9_.-]{0,32}$")
_IDENTITY = re.compile(r"^(user|cert):([A-Za-z0-9_.@-]{1,64})$")
MAX_ENDPOINTS = 16
MAX_HOSTS = 64
"""Camera hosts one solver host names an identity for (as many as it may have cameras)."""


def _endpoint(value: str) -> str:
    m = _ENDPOINT.match(value)
    ok = m is not None and int(m.group(3)) <= 65535
    if ok and m is not None:
        try:
            ipaddress.ip_address(m.group(2).strip("[]"))
        except ValueError:
            ok = False
    if not ok:
        raise ValueError('allowed: "tcp/<ip>:<port>" or "tls/<ip>:<port>" (an IP literal, [v6] in brackets)')
    return value


def _host_name(value: str) -> str:
    if not _HOST_NAME.match(value):
        raise ValueError('must be "" or 1 to 32 letters, digits, "_", "." or "-"')
    return value


def _speaker_identity(value: str) -> str:
    if not _IDENTITY.match(value):
        raise ValueError('allowed: "user:<user name>" (user/password) or "cert:<certificate common name>" (mutual '
                         'TLS), the name 1 to 64 letters, digits, "_", ".", "@" or "-"')  # fmt: skip
    return value


def identity_kind(identity: str) -> tuple[str, str]:
    """``"user:hostA"`` -> ``("user", "hostA")`` (a checked identity)."""
    kind, _, name = identity.partition(":")
    return kind, name


def endpoint_address(endpoint: str) -> str:
    """The IP of a checked endpoint: ``tcp/[::1]:7447`` -> ``::1``."""
    return endpoint.split("/", 1)[1].rsplit(":", 1)[0].strip("[]")


def is_loopback_endpoint(endpoint: str) -> bool:
    return ipaddress.ip_address(endpoint_address(endpoint)).is_loopback


Endpoint = Annotated[
    Text, AfterValidator(_endpoint), Allowed('"tcp/<ip>:<port>" or "tls/<ip>:<port>"'),
    Field(examples=["tcp/127.0.0.1:7447"]),
]  # fmt: skip
Endpoints = Annotated[Seq[Endpoint], Field(max_length=MAX_ENDPOINTS), AfterValidator(unique)]
HostName = Annotated[str, Field(min_length=1, max_length=32), AfterValidator(_host_name)]
Identity = Annotated[Text, AfterValidator(_speaker_identity), Field(examples=["user:hostA"])]


class ZenohConfig(Section):
    """``[zenoh]`` (see the module docstring)."""

    ordered = (("status_period_s", "<", "lost_after_s"),)

    rig: HostName = "rig"
    """The rig's name: the first part of every key (``mocapd/<rig>/<camera>/detections``)."""
    host: Annotated[Text, AfterValidator(_host_name)] = ""
    """This camera host's name (``mocapd detect-host``); "" = the machine's host name."""
    mode: Literal["peer", "client"] = "peer"
    listen: Endpoints = ("tcp/127.0.0.1:7447",)
    """Endpoints this process listens on (the solver host, usually)."""
    connect: Endpoints = ()
    """Endpoints this process connects to (camera hosts: the solver host's)."""
    user: Text = ""
    """User name presented to the other side (user/password authentication)."""
    password_file: PathStr = ""
    """File holding this user's password (one line)."""
    users_file: PathStr = ""
    """A listener's accepted users: lines ``user:password``."""
    tls_root_ca: PathStr = ""
    """CA certificate (PEM) that signed the other side's certificate."""
    tls_cert: PathStr = ""
    """This side's certificate (PEM; required on a tls/ listener, and on both sides off loopback: mutual TLS)."""
    tls_key: PathStr = ""
    """This side's private key (PEM)."""
    lost_after_s: float = Field(2.0, ge=0.1, le=60.0)
    """A camera host not heard from for this long is shown lost and its cameras drop out of the solve (s)."""
    status_period_s: float = Field(0.5, ge=0.05, le=10.0)
    """How often a camera host publishes its status (s)."""
    clock_period_s: float = Field(0.5, ge=0.05, le=10.0)
    """How often the solver host measures each camera host's clock offset by a round trip (s)."""
    clock_timeout_s: float = Field(1.0, ge=0.01, le=10.0)
    """A clock round trip not answered within this is dropped (s)."""
    clock_window: int = Field(32, ge=1, le=1024)
    """Round trips kept per host; the one with the smallest error bound gives the offset."""
    clock_drift_ppm: float = Field(100.0, ge=0.0, le=10_000.0)
    """Bound on the two clocks' relative drift, ageing old round trips' error bounds (ppm)."""
    identities: Annotated[dict[HostName, Identity], Field(max_length=MAX_HOSTS)] = Field(default_factory=dict)
    """Solver host: camera host name -> the identity that alone may speak for it (module docstring)."""

    @model_validator(mode="after")
    def _secured_off_loopback(self) -> Self:
        remote_listen = [e for e in self.listen if not is_loopback_endpoint(e)]
        remote = remote_listen + [e for e in self.connect if not is_loopback_endpoint(e)]
        tls = [e for e in (*self.listen, *self.connect) if e.startswith("tls/")]
        if bool(self.user) != bool(self.password_file):
            raise RuleError("{0} and {1} go together", "user", "password_file", values=(self.user, self.password_file))
        if bool(self.tls_cert) != bool(self.tls_key):
            raise RuleError("{0} and {1} go together", "tls_cert", "tls_key", values=(self.tls_cert, self.tls_key))
        if tls and not self.tls_root_ca:
            raise RuleError("{0} use TLS: {1} must be set", "listen", "tls_root_ca", values=(tls, ""))
        tls_listen = [e for e in self.listen if e.startswith("tls/")]
        if tls_listen and not (self.tls_cert and self.tls_key):
            raise RuleError("{0} listen with TLS: {1} and {2} must be set", "listen", "tls_cert", "tls_key",
                            values=(tls_listen, self.tls_cert, self.tls_key))  # fmt: skip
        if not remote:
            return self
        usrpwd = bool(self.user) and (bool(self.users_file) or not remote_listen)
        mutual_tls = all(e.startswith("tls/") for e in remote) and bool(self.tls_cert)  # each side its certificate
        if not (usrpwd or mutual_tls):
            raise RuleError(
                "{0} is not loopback: mocapd talks to other machines only authenticated on both sides, with {1}/{2} "
                "(and {3} on a listener) or over tls/ endpoints with this side's {4} (mutual TLS, docs/scaling.md)",
                "listen" if remote_listen else "connect", "user", "password_file", "users_file", "tls_cert",
                values=(remote, self.user, self.password_file, self.users_file, self.tls_cert),
            )  # fmt: skip
        return self

    @model_validator(mode="after")
    def _identities_checkable(self) -> Self:
        """Each identity must be one this side authenticates, on a link the host reaches it by directly."""
        kinds = {identity_kind(i)[0] for i in self.identities.values()}
        if not kinds:
            return self
        if self.mode != "peer":
            raise RuleError("{0} need {1}: the camera hosts connect to this solver host itself (through a router it "
                            "would see the router's identity)", "identities", "mode",
                            values=(dict(self.identities), self.mode))  # fmt: skip
        if "user" in kinds and not self.users_file:
            raise RuleError("{0} name users: this side checks them against {1} (camera hosts connect to it with "
                            "their own user and password)", "identities", "users_file",
                            values=(dict(self.identities), self.users_file))  # fmt: skip
        tls = [e for e in (*self.listen, *self.connect) if e.startswith("tls/")]
        if "cert" in kinds and not (tls and self.tls_cert):
            raise RuleError("{0} name certificates: the links must be mutual TLS (tls/ endpoints in {1}, and {2})",
                            "identities", "listen", "tls_cert", values=(dict(self.identities), self.listen,
                            self.tls_cert))  # fmt: skip
        return self
