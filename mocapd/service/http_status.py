"""A minimal HTTP/1.1 server on loopback for ``/status`` (JSON) and ``/metrics`` (Prometheus text format).

asyncio streams, GET only, one request per connection (``Connection: close``); requests are bounded in size
and time so a stuck client cannot hold the daemon.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import socket
from collections.abc import Callable
from typing import Any

log = logging.getLogger(__name__)

MAX_REQUEST = 8192
READ_TIMEOUT_S = 2.0


class StatusServer:
    """Serves ``status()`` as JSON at /status and ``metrics()`` as text at /metrics.

    ``sock``: serve on this already listening TCP socket instead of binding ``host:port`` (the camera demo's
    daemon runs in a private network namespace and serves on a socket its parent bound in the host's).
    """

    def __init__(
        self,
        status: Callable[[], dict[str, Any]],
        metrics: Callable[[], str],
        host: str = "127.0.0.1",
        port: int = 0,
        *,
        sock: socket.socket | None = None,
    ) -> None:
        self._status = status
        self._metrics = metrics
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
            self._server = await asyncio.start_server(self._handle, self.host, self.port)
        self.port = int(self._server.sockets[0].getsockname()[1])
        return self.port

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()
            with contextlib.suppress(TimeoutError):  # do not wait on stuck clients at shutdown
                await asyncio.wait_for(self._server.wait_closed(), 0.5)
            self._server = None

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

    def _respond(self, head: bytes) -> tuple[str, str, bytes]:
        if len(head) > MAX_REQUEST:
            self.bad_requests += 1
            return "431 Request Header Fields Too Large", "text/plain", b"request too large\n"
        parts = head.split(b"\r\n", 1)[0].decode("latin-1").split(" ")
        if len(parts) != 3 or not parts[2].startswith("HTTP/1."):
            self.bad_requests += 1
            return "400 Bad Request", "text/plain", b"bad request line\n"
        method, target = parts[0], parts[1].split("?", 1)[0]
        if method != "GET":
            return "405 Method Not Allowed", "text/plain", b"only GET\n"
        if target == "/status":
            return "200 OK", "application/json", json.dumps(self._status(), indent=1).encode() + b"\n"
        if target == "/metrics":
            return "200 OK", "text/plain; version=0.0.4; charset=utf-8", self._metrics().encode()
        return "404 Not Found", "text/plain", b"try /status or /metrics\n"
