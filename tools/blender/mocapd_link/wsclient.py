"""A small WebSocket client (RFC 6455) for the Blender add-on: text frames in, masked frames out.

Hand-written on purpose: Blender's bundled Python has no ``websockets`` package and an add-on that needs none
installs with one command into any Blender; the client needs only the handshake, unfragmented or fragmented data
frames, ping/pong and close, which is this file. :class:`FrameParser` is sans-I/O (bytes in, messages out) and
:class:`Connection` the socket around it. No Blender import here, so it is tested in mocapd's own venv against the
daemon's real ``websockets`` server.
"""

from __future__ import annotations

import base64
import contextlib
import hashlib
import os
import socket
import struct
from urllib.parse import urlsplit

GUID = "258EAFA5-E914-47DA-95CA-C5AB0DC85B11"
OP_CONT, OP_TEXT, OP_BINARY, OP_CLOSE, OP_PING, OP_PONG = 0x0, 0x1, 0x2, 0x8, 0x9, 0xA
MAX_MESSAGE = 16 * 1024 * 1024
"""Largest message accepted (bytes); a frame message of 64 subjects is about 100 kB."""


class ProtocolError(Exception):
    """The server broke the WebSocket protocol, or the handshake failed."""


def encode_frame(opcode: int, payload: bytes, mask: bytes | None = None) -> bytes:
    """One final frame, masked as a client must (``mask``: 4 bytes, random when None)."""
    mask = os.urandom(4) if mask is None else mask
    n = len(payload)
    head = bytes([0x80 | opcode])
    if n < 126:
        head += bytes([0x80 | n])
    elif n < 1 << 16:
        head += bytes([0x80 | 126]) + struct.pack("!H", n)
    else:
        head += bytes([0x80 | 127]) + struct.pack("!Q", n)
    masked = bytes(b ^ mask[i % 4] for i, b in enumerate(payload))
    return head + mask + masked


class FrameParser:
    """Server frames → complete messages ``(opcode, payload)``; control frames are returned as they come."""

    def __init__(self) -> None:
        self.buffer = bytearray()
        self.partial: bytearray | None = None
        self.partial_op = 0

    def feed(self, data: bytes) -> list[tuple[int, bytes]]:
        self.buffer += data
        out: list[tuple[int, bytes]] = []
        while True:
            frame = self._next_frame()
            if frame is None:
                return out
            fin, op, payload = frame
            if op >= OP_CLOSE:
                out.append((op, payload))
            elif op == OP_CONT:
                if self.partial is None:
                    raise ProtocolError("continuation frame without a message")
                self.partial += payload
                if fin:
                    out.append((self.partial_op, bytes(self.partial)))
                    self.partial = None
            elif fin:
                out.append((op, payload))
            else:
                self.partial, self.partial_op = bytearray(payload), op
            if self.partial is not None and len(self.partial) > MAX_MESSAGE:
                raise ProtocolError(f"message larger than {MAX_MESSAGE} bytes")

    def _next_frame(self) -> tuple[bool, int, bytes] | None:
        b = self.buffer
        if len(b) < 2:
            return None
        fin, op, masked, n = bool(b[0] & 0x80), b[0] & 0x0F, bool(b[1] & 0x80), b[1] & 0x7F
        pos = 2
        if n == 126:
            if len(b) < 4:
                return None
            n, pos = struct.unpack_from("!H", b, 2)[0], 4
        elif n == 127:
            if len(b) < 10:
                return None
            n, pos = struct.unpack_from("!Q", b, 2)[0], 10
        if masked:
            raise ProtocolError("a server frame must not be masked")
        if n > MAX_MESSAGE:
            raise ProtocolError(f"frame larger than {MAX_MESSAGE} bytes")
        if len(b) < pos + n:
            return None
        payload = bytes(b[pos : pos + n])
        del b[: pos + n]
        return fin, op, payload


class Connection:
    """A blocking client connection to ``ws://host:port/path`` (loopback or any host the user gives)."""

    def __init__(self, url: str, timeout: float = 5.0) -> None:
        parts = urlsplit(url)
        if parts.scheme != "ws" or parts.hostname is None:
            raise ProtocolError(f"expected a ws://host:port/ URL, got {url!r}")
        self.sock = socket.create_connection((parts.hostname, parts.port or 80), timeout=timeout)
        path = (parts.path or "/") + (f"?{parts.query}" if parts.query else "")
        key = base64.b64encode(os.urandom(16)).decode()
        request = (
            f"GET {path} HTTP/1.1\r\nHost: {parts.hostname}:{parts.port or 80}\r\nUpgrade: websocket\r\n"
            f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n"
        )
        self.sock.sendall(request.encode())
        head = b""
        while b"\r\n\r\n" not in head:
            chunk = self.sock.recv(4096)
            if not chunk:
                raise ProtocolError("connection closed during the handshake")
            head += chunk
        head, rest = head.split(b"\r\n\r\n", 1)
        lines = head.decode("latin-1").split("\r\n")
        if " 101 " not in lines[0] + " ":
            raise ProtocolError(f"handshake refused: {lines[0]}")
        fields = {k.strip().lower(): v.strip() for k, _, v in (ln.partition(":") for ln in lines[1:])}
        want = base64.b64encode(hashlib.sha1((key + GUID).encode()).digest()).decode()
        if fields.get("sec-websocket-accept") != want:
            raise ProtocolError("bad Sec-WebSocket-Accept in the handshake")
        self.parser = FrameParser()
        self.pending = self.parser.feed(rest)
        self.closed = False

    def send_text(self, text: str) -> None:
        self.sock.sendall(encode_frame(OP_TEXT, text.encode()))

    def receive(self) -> str | bytes | None:
        """The next data message (str for text, bytes for binary); None once the connection is closed."""
        while not self.closed:
            while self.pending:
                op, payload = self.pending.pop(0)
                if op == OP_TEXT:
                    return payload.decode("utf-8")
                if op == OP_BINARY:
                    return payload
                if op == OP_PING:
                    self.sock.sendall(encode_frame(OP_PONG, payload))
                elif op == OP_CLOSE:
                    self._close(payload[:2])
                    return None
            try:
                data = self.sock.recv(65536)
            except TimeoutError:
                continue
            except OSError:
                if self.closed:  # closed from another thread while waiting
                    return None
                raise
            if not data:
                self.closed = True
                return None
            self.pending.extend(self.parser.feed(data))
        return None

    def _close(self, code: bytes = b"\x03\xe8") -> None:
        if not self.closed:
            self.closed = True
            # The server may have gone already; the socket is closed below either way.
            with contextlib.suppress(OSError):
                self.sock.sendall(encode_frame(OP_CLOSE, code))
        self.sock.close()

    def close(self) -> None:
        """Send a close frame (1000) and close the socket."""
        self._close()
