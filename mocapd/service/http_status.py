"""A minimal HTTP/1.1 server on loopback for ``/status`` (JSON) and ``/metrics`` (Prometheus text format), and the
daemon's few actions (``POST /heading/reset``).

asyncio streams, GET (and POST to an action's path), one request per connection (``Connection: close``); requests
are bounded in size and time so a stuck client cannot hold the daemon.

Only requests that name this machine are served (:mod:`mocapd.protocols.web_access`): a ``Host`` other than a
loopback address, ``localhost`` or a configured name is a 421 (DNS rebinding), an ``Origin`` other than the
server's own or a configured one a 403 (another site's page, a ``file://`` page), and a POST without the
``X-Mocapd-Request`` header a 403 (no simple cross-origin request can change the daemon's state). An action that
is asked too often (:class:`~mocapd.errors.RateLimitError`) is a 429 with ``Retry-After``. Refusals are counted
by reason (``refused``) and logged at most once per 10 s.

The server shares the event loop with the output tick, so what a request costs must not grow with how often
clients ask: requests are answered from a **snapshot** — the status document taken at most ``max_hz`` times a
second (when a request finds the last one older than ``1 / max_hz``), its JSON and its Prometheus text each
rendered at most once per snapshot and then served as the same bytes to every request until the next one.
A thousand polls a second cost the tick loop ``max_hz`` renders a second plus the (small, fixed) cost of
answering each connection, however large the document.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import socket
import time
from collections.abc import Callable, Mapping
from typing import Any, NamedTuple
from urllib.parse import parse_qs

from mocapd.errors import MocapdError, RateLimitError
from mocapd.io import ports
from mocapd.io.rejections import Rejections
from mocapd.protocols.web_access import REQUEST_HEADER, WebAccess
from mocapd.service.metrics import CONTENT_TYPE as METRICS_CONTENT_TYPE

log = logging.getLogger(__name__)

#: a POST action: the query's parameters and who asked (for the log: "HTTP request from 127.0.0.1:40312
#: (mocapd reset-heading)") in, a JSON-able result out (MocapdError: a 400 with its message; RateLimitError: 429)
Action = Callable[[dict[str, str], str], Any]
MAX_REQUEST = 8192
READ_TIMEOUT_S = 2.0
#: snapshots a second at most (a monitoring poll every 250 ms sees every change; a flood of polls costs 4 renders/s)
MAX_SNAPSHOT_HZ = 4.0


class Reply(NamedTuple):
    """One answer: status line, content type, body, and more header lines (each ending in CRLF)."""

    status: str
    ctype: str
    body: bytes
    headers: str = ""


class Snapshots:
    """The latest status snapshot and its documents, rendered lazily once each per snapshot.

    Parameters
    ----------
    status
        Takes a snapshot: a new JSON-able document of the daemon's state (called on the event loop).
    metrics
        Renders the Prometheus text of one snapshot.
    max_hz
        Snapshots a second at most: a request within ``1 / max_hz`` of the last snapshot is served from it.
    clock
        Monotonic nanoseconds (a test may step it).
    """

    def __init__(
        self,
        status: Callable[[], dict[str, Any]],
        metrics: Callable[[dict[str, Any]], bytes],
        max_hz: float = MAX_SNAPSHOT_HZ,
        clock: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        if not max_hz > 0:
            raise ValueError(f"max_hz must be > 0, got {max_hz}")
        self._status = status
        self._metrics = metrics
        self._min_age_ns = round(1e9 / max_hz)
        self._clock = clock
        self._taken_ns: int | None = None
        self._doc: dict[str, Any] = {}
        self._json: bytes | None = None
        self._text: bytes | None = None
        #: snapshots taken, JSON documents rendered, Prometheus documents rendered (since start)
        self.snapshots = 0
        self.json_renders = 0
        self.metrics_renders = 0

    def _current(self) -> dict[str, Any]:
        now = self._clock()
        if self._taken_ns is None or now - self._taken_ns >= self._min_age_ns:
            self._doc = self._status()
            self._taken_ns = now
            self._json = self._text = None
            self.snapshots += 1
        return self._doc

    def document(self) -> dict[str, Any]:
        """The current snapshot's document (shared: read it, do not change it)."""
        return self._current()

    def status_json(self) -> bytes:
        """The /status body of the current snapshot."""
        doc = self._current()
        if self._json is None:
            self._json = json.dumps(doc, indent=1).encode() + b"\n"
            self.json_renders += 1
        return self._json

    def metrics_text(self) -> bytes:
        """The /metrics body of the current snapshot."""
        doc = self._current()
        if self._text is None:
            self._text = self._metrics(doc)
            self.metrics_renders += 1
        return self._text


class StatusServer:
    """Serves snapshots of ``status()`` as JSON at /status and their ``metrics(status)`` text at /metrics
    (see :class:`Snapshots`: at most ``max_hz`` snapshots a second however many requests come).

    ``sock``: serve on this already listening TCP socket instead of binding ``host:port`` (the camera demo's
    daemon runs in a private network namespace and serves on a socket its parent bound in the host's).
    """

    def __init__(
        self,
        status: Callable[[], dict[str, Any]],
        metrics: Callable[[dict[str, Any]], bytes],
        host: str = "127.0.0.1",
        port: int = 0,
        *,
        sock: socket.socket | None = None,
        max_hz: float = MAX_SNAPSHOT_HZ,
        clock: Callable[[], int] = time.monotonic_ns,
        actions: Mapping[str, Action] | None = None,
        allowed_hosts: tuple[str, ...] = (),
        allowed_origins: tuple[str, ...] = (),
    ) -> None:
        self.snapshots = Snapshots(status, metrics, max_hz, clock)
        #: POST paths -> what they do (called with the query's parameters on the event loop; a JSON-able result)
        self.actions: Mapping[str, Action] = actions if actions is not None else {}
        self._sock = sock
        self.host, self.port = (str(sock.getsockname()[0]), int(sock.getsockname()[1])) if sock else (host, port)
        #: the Host and Origin rules (``[web]``): names of this machine, the server's own origin and configured ones
        self.access = WebAccess(self.host, allowed_hosts, allowed_origins)
        self.requests = 0
        self.bad_requests = 0
        #: requests refused for their Host ("host"), Origin ("origin"), a POST without REQUEST_HEADER ("csrf") or
        #: too many of an action ("rate")
        self.refused = Rejections("status server", log)
        self._server: asyncio.Server | None = None

    async def start(self) -> int:
        """Listen; returns the bound port (useful with port 0)."""
        if self._sock is not None:
            self._server = await asyncio.start_server(self._handle, sock=self._sock)
        else:
            try:
                self._server = await asyncio.start_server(self._handle, self.host, self.port)
            except OSError as exc:  # a second daemon, another program: one line naming the key and the holder
                raise ports.listen_error("[daemon] http_port", self.host, self.port, exc) from None
        self.port = int(self._server.sockets[0].getsockname()[1])
        return self.port

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()
            with contextlib.suppress(TimeoutError):  # do not wait on stuck clients at shutdown
                await asyncio.wait_for(self._server.wait_closed(), 0.5)
            self._server = None

    @property
    def renders(self) -> int:
        """Status snapshots taken so far (each costs one ``status()`` call on the event loop)."""
        return self.snapshots.snapshots

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}"

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), READ_TIMEOUT_S)
            status, ctype, body, extra = self._respond(head, _peer(writer))
        except (asyncio.IncompleteReadError, asyncio.LimitOverrunError, TimeoutError, ConnectionError):
            self.bad_requests += 1
            status, ctype, body, extra = Reply("400 Bad Request", "text/plain", b"bad request\n")
        self.requests += 1
        writer.write(
            f"HTTP/1.1 {status}\r\nContent-Type: {ctype}\r\nContent-Length: {len(body)}\r\n"
            f"Connection: close\r\nCache-Control: no-store\r\n{extra}\r\n".encode()
            + body
        )
        with contextlib.suppress(ConnectionError):
            await writer.drain()
        writer.close()
        with contextlib.suppress(ConnectionError):
            await writer.wait_closed()

    def _act(self, target: str, query: str, who: str) -> Reply:
        params = {k: v[-1] for k, v in parse_qs(query).items()}
        try:
            result = self.actions[target](params, who)
        except RateLimitError as exc:
            self.refused.reject("rate", f"{target} by {who}: {exc}")
            body = json.dumps({"error": str(exc), "retry_after_s": round(exc.retry_after_s, 2)}).encode() + b"\n"
            return Reply(
                "429 Too Many Requests", "application/json", body, f"Retry-After: {math.ceil(exc.retry_after_s)}\r\n"
            )
        except MocapdError as exc:
            return Reply("400 Bad Request", "application/json", json.dumps({"error": str(exc)}).encode() + b"\n")
        return Reply("200 OK", "application/json", json.dumps(result, indent=1).encode() + b"\n")

    def _respond(self, head: bytes, peer: str) -> Reply:
        if len(head) > MAX_REQUEST:
            self.bad_requests += 1
            return Reply("431 Request Header Fields Too Large", "text/plain", b"request too large\n")
        first, _, rest = head.partition(b"\r\n")
        parts = first.decode("latin-1").split(" ")
        if len(parts) != 3 or not parts[2].startswith("HTTP/1."):
            self.bad_requests += 1
            return Reply("400 Bad Request", "text/plain", b"bad request line\n")
        method, target = parts[0], parts[1].split("?", 1)[0]
        headers = _headers(rest)
        refused = self._refusal(method, target, headers, peer)
        if refused is not None:
            return refused
        if method == "POST" and target in self.actions:
            client = headers[REQUEST_HEADER.lower()][0]
            return self._act(target, parts[1].partition("?")[2], f"HTTP request from {peer} ({_printable(client)})")
        if method != "GET":
            allowed = ", ".join(f"POST {a}" for a in self.actions)
            return Reply(
                "405 Method Not Allowed", "text/plain", f"only GET{', ' + allowed if allowed else ''}\n".encode()
            )
        return self._get(target)

    def _refusal(self, method: str, target: str, headers: dict[str, list[str]], peer: str) -> Reply | None:
        """The answer to a request this server must not serve (a foreign Host or Origin, a POST without
        REQUEST_HEADER), counted by reason; None for the rest."""
        why = self.access.refusal(headers.get("host", []), headers.get("origin", []))
        if why is not None:
            shown = f"Host {headers.get('host')}, Origin {headers.get('origin')}, from {peer}"
            self.refused.reject(why, f"{method} {target[:80]}: {shown}")
            if why == "host":
                return Reply("421 Misdirected Request", "text/plain", b"this server answers only to its own names\n")
            return Reply("403 Forbidden", "text/plain", b"requests from other sites' pages are refused\n")
        if method == "POST" and target in self.actions:
            client = headers.get(REQUEST_HEADER.lower(), [])
            if len(client) != 1 or not client[0]:
                self.refused.reject("csrf", f"POST {target} without {REQUEST_HEADER}, from {peer}")
                return Reply("403 Forbidden", "text/plain", f"a POST needs the header {REQUEST_HEADER}\n".encode())
        return None

    def _get(self, target: str) -> Reply:
        if target == "/status":
            return Reply("200 OK", "application/json", self.snapshots.status_json())
        if target == "/metrics":
            return Reply("200 OK", METRICS_CONTENT_TYPE, self.snapshots.metrics_text())
        return Reply("404 Not Found", "text/plain", b"try /status or /metrics\n")


def _headers(raw: bytes) -> dict[str, list[str]]:
    """Header lines (after the request line) -> lower-case name: every value sent (Latin-1, stripped)."""
    out: dict[str, list[str]] = {}
    for line in raw.decode("latin-1").split("\r\n"):
        name, sep, value = line.partition(":")
        if sep and name and name == name.strip():
            out.setdefault(name.lower(), []).append(value.strip())
    return out


def _peer(writer: asyncio.StreamWriter) -> str:
    peer = writer.get_extra_info("peername")
    if isinstance(peer, tuple) and len(peer) >= 2:
        return f"[{peer[0]}]:{peer[1]}" if ":" in str(peer[0]) else f"{peer[0]}:{peer[1]}"
    return "?"


def _printable(text: str, limit: int = 40) -> str:
    """Outside text for the log: printable ASCII only, at most ``limit`` characters."""
    return "".join(c if " " <= c <= "~" else "?" for c in text[:limit])
