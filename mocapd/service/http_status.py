"""A minimal HTTP/1.1 server on loopback for ``/status`` (JSON) and ``/metrics`` (Prometheus text format), and the
daemon's few actions (``POST /heading/reset``).

asyncio streams, GET (and POST to an action's path), one request per connection (``Connection: close``); requests
are bounded in size and time so a stuck client cannot hold the daemon.

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
import socket
import time
from collections.abc import Callable, Mapping
from typing import Any
from urllib.parse import parse_qs

from mocapd.errors import MocapdError
from mocapd.io import ports
from mocapd.service.metrics import CONTENT_TYPE as METRICS_CONTENT_TYPE

log = logging.getLogger(__name__)

#: a POST action: the query's parameters in, a JSON-able result out (MocapdError: a 400 with its message)
Action = Callable[[dict[str, str]], Any]
MAX_REQUEST = 8192
READ_TIMEOUT_S = 2.0
#: snapshots a second at most (a monitoring poll every 250 ms sees every change; a flood of polls costs 4 renders/s)
MAX_SNAPSHOT_HZ = 4.0


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
    ) -> None:
        self.snapshots = Snapshots(status, metrics, max_hz, clock)
        #: POST paths -> what they do (called with the query's parameters on the event loop; a JSON-able result)
        self.actions: Mapping[str, Action] = actions if actions is not None else {}
        self._sock = sock
        self.host, self.port = (str(sock.getsockname()[0]), int(sock.getsockname()[1])) if sock else (host, port)
        self.requests = 0
        self.bad_requests = 0
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
            status, ctype, body = self._respond(head)
        except (asyncio.IncompleteReadError, asyncio.LimitOverrunError, TimeoutError, ConnectionError):
            self.bad_requests += 1
            status, ctype, body = "400 Bad Request", "text/plain", b"bad request\n"
        self.requests += 1
        writer.write(
            f"HTTP/1.1 {status}\r\nContent-Type: {ctype}\r\nContent-Length: {len(body)}\r\n"
            "Connection: close\r\nCache-Control: no-store\r\n\r\n".encode()
            + body
        )
        with contextlib.suppress(ConnectionError):
            await writer.drain()
        writer.close()
        with contextlib.suppress(ConnectionError):
            await writer.wait_closed()

    def _act(self, target: str, query: str) -> tuple[str, str, bytes]:
        params = {k: v[-1] for k, v in parse_qs(query).items()}
        try:
            result = self.actions[target](params)
        except MocapdError as exc:
            return "400 Bad Request", "application/json", json.dumps({"error": str(exc)}).encode() + b"\n"
        return "200 OK", "application/json", json.dumps(result, indent=1).encode() + b"\n"

    def _respond(self, head: bytes) -> tuple[str, str, bytes]:
        if len(head) > MAX_REQUEST:
            self.bad_requests += 1
            return "431 Request Header Fields Too Large", "text/plain", b"request too large\n"
        parts = head.split(b"\r\n", 1)[0].decode("latin-1").split(" ")
        if len(parts) != 3 or not parts[2].startswith("HTTP/1."):
            self.bad_requests += 1
            return "400 Bad Request", "text/plain", b"bad request line\n"
        method, target = parts[0], parts[1].split("?", 1)[0]
        if method == "POST" and target in self.actions:
            return self._act(target, parts[1].partition("?")[2])
        if method != "GET":
            allowed = ", ".join(f"POST {a}" for a in self.actions)
            return "405 Method Not Allowed", "text/plain", f"only GET{', ' + allowed if allowed else ''}\n".encode()
        return self._get(target)

    def _get(self, target: str) -> tuple[str, str, bytes]:
        if target == "/status":
            return "200 OK", "application/json", self.snapshots.status_json()
        if target == "/metrics":
            return "200 OK", METRICS_CONTENT_TYPE, self.snapshots.metrics_text()
        return "404 Not Found", "text/plain", b"try /status or /metrics\n"
