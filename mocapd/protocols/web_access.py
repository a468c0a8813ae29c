"""Who may use the daemon's local web surface (the status server and the WebSocket stream with its viewer): the
Host check against DNS rebinding, the Origin check against other sites' pages, and the header that keeps a state
change out of reach of a simple cross-origin request.

Why each check (docs/reliability.md, "The web surface"):

- **Host.** A page from ``http://evil.example:8766`` whose name the attacker's DNS later answers with 127.0.0.1
  (DNS rebinding) is, to the browser, the daemon's own origin: it may read every answer. Its requests still carry
  ``Host: evil.example:8766``. Only names that mean this machine's servers are accepted: IP literals of the
  address listened on (any loopback literal when that is loopback, any literal at all when it is the wildcard
  ``0.0.0.0`` / ``::``: an attacker controls names, not what a literal address points to), ``localhost``, and the
  configured ``[web] allowed_hosts``. The port is not compared: an SSH tunnel (``ssh -L 9000:localhost:8766``)
  makes the browser say ``localhost:9000``, and no rebinding is possible through a literal or ``localhost``.
- **Origin.** Browsers send ``Origin`` with every WebSocket handshake and every cross-origin ``fetch`` or form
  POST; other clients (Python, Unity, Node, curl) send none. A request with an Origin is accepted only from the
  server's own origin (the scheme and the very Host the request names, once that Host passed its check: the viewer
  served by the same server, also through a tunnel) or a configured ``[web] allowed_origins`` entry. ``Origin:
  null`` (a ``file://`` page, a sandboxed frame) is refused.
- **State changes.** A POST must carry :data:`REQUEST_HEADER`. A cross-origin page can only send a custom header
  after a CORS preflight (``OPTIONS``), which the status server never grants (405, no ``Access-Control-*``
  headers), so no ``<form>``, no ``no-cors`` fetch and no ``text/plain`` body reaches an action.

Pure: strings in, verdicts out; the servers (:mod:`mocapd.service.http_status`, :mod:`mocapd.io.ws_server`) apply
them and count what they refuse.
"""

from __future__ import annotations

import ipaddress
import re
from dataclasses import dataclass, field

REQUEST_HEADER = "X-Mocapd-Request"
"""The header every state-changing request (``POST /heading/reset``) must carry, with any non-empty value (which
names the client in the log: ``mocapd reset-heading`` sends its own name)."""

#: an allowed extra Host name: a DNS name (letters, digits, ``-``, dots), lower case once parsed
HOST_NAME = re.compile(r"(?=.{1,253}\Z)[a-z0-9]([a-z0-9-]{0,61}[a-z0-9])?(\.[a-z0-9]([a-z0-9-]{0,61}[a-z0-9])?)*")
#: an allowed extra origin: ``http(s)://host[:port]``, no path, no trailing slash
ORIGIN = re.compile(r"(https?)://([a-z0-9.-]+|\[[0-9a-f:.]+\])(?::([0-9]{1,5}))?")
_DEFAULT_PORT = {"http": 80, "https": 443}


def split_host(host: str) -> tuple[str, int | None] | None:
    """``name[:port]`` or ``[v6][:port]`` (an HTTP Host header) -> (name in lower case, port), None if malformed."""
    h = host.strip().lower()
    if h.startswith("["):
        name, sep, rest = h[1:].partition("]")
        if not sep:
            return None
        port_text = rest[1:] if rest.startswith(":") else None
        if rest and port_text is None:
            return None
    else:
        name, sep, port_text_ = h.partition(":")
        port_text = port_text_ if sep else None
    if not name:
        return None
    if port_text is None:
        return name, None
    if not port_text.isdigit() or len(port_text) > 5 or not 0 < int(port_text) < 65536:
        return None
    return name, int(port_text)


def _ip(name: str) -> ipaddress.IPv4Address | ipaddress.IPv6Address | None:
    try:
        return ipaddress.ip_address(name)
    except ValueError:
        return None


def _origin_parts(origin: str) -> tuple[str, str, int] | None:
    """(scheme, host name without brackets, port: the scheme's default when none) of an origin, None if it is
    not one (``null``, a path, another scheme)."""
    m = ORIGIN.fullmatch(origin.strip().lower())
    if m is None:
        return None
    scheme, host, port = m.group(1), m.group(2), m.group(3)
    number = _DEFAULT_PORT[scheme] if port is None else int(port)
    if not 0 < number < 65536:
        return None
    return scheme, host.strip("[]"), number


def normal_origin(origin: str) -> str | None:
    """``scheme://host[:port]`` in lower case without a default port, None if ``origin`` is not one."""
    parts = _origin_parts(origin)
    if parts is None:
        return None
    scheme, host, port = parts
    shown = f"[{host}]" if ":" in host else host
    return f"{scheme}://{shown}" + ("" if port == _DEFAULT_PORT[scheme] else f":{port}")


@dataclass(frozen=True)
class WebAccess:
    """The Host and Origin rules of one server.

    Parameters
    ----------
    bound : str
        The address the server listens on (an IP literal or ``localhost``).
    allowed_hosts : tuple of str
        More Host names to accept (``[web] allowed_hosts``: a name that points here, e.g. ``studio.local``).
    allowed_origins : tuple of str
        More origins whose pages may use the server (``[web] allowed_origins``).
    """

    bound: str
    allowed_hosts: tuple[str, ...] = ()
    allowed_origins: tuple[str, ...] = ()
    _origins: frozenset[str] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        origins = {normal_origin(o) for o in self.allowed_origins}
        object.__setattr__(self, "_origins", frozenset(o for o in origins if o is not None))

    def host_ok(self, host: str | None) -> bool:
        """Whether a request's Host header names this server (None: no Host header, a non-browser client)."""
        if host is None:
            return True  # every browser sends Host; HTTP/1.0 tools may not
        parsed = split_host(host)
        if parsed is None:
            return False
        name = parsed[0]
        ip, bound = _ip(name), _ip(self.bound)
        if ip is None:  # a name: "localhost" where a loopback (or every) address is listened on, or a configured one
            local = self.bound == "localhost" or bound is None or bound.is_loopback or bound.is_unspecified
            return (name == "localhost" and local) or name in {h.lower() for h in self.allowed_hosts}
        if bound is None:  # listening on "localhost": its loopback literals
            return ip.is_loopback
        return bound.is_unspecified or ip == bound or (bound.is_loopback and ip.is_loopback)

    def origin_ok(self, origin: str | None, host: str | None) -> bool:
        """Whether a request with this Origin header (None: none, a non-browser client) and Host may be served."""
        if origin is None:
            return True
        parts = _origin_parts(origin)
        if parts is None:
            return False  # "null" (file:// pages, sandboxed frames), or not an origin at all
        if normal_origin(origin) in self._origins:
            return True
        if host is None or not self.host_ok(host):
            return False
        # The server's own origin: the page came from the very name and port the request is addressed to.
        scheme, name, port = parts
        parsed = split_host(host)
        return parsed is not None and (name, port) == (parsed[0], parsed[1] or _DEFAULT_PORT[scheme])

    def refusal(self, host: list[str], origin: list[str]) -> str | None:
        """Why a request with these Host and Origin header values (each as many as it sent) is refused: ``"host"``
        (421), ``"origin"`` (403), or None (served)."""
        if len(host) > 1 or not self.host_ok(host[0] if host else None):
            return "host"
        if len(origin) > 1 or not self.origin_ok(origin[0] if origin else None, host[0] if host else None):
            return "origin"
        return None
