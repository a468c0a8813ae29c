"""Asyncio serial transport over pyserial: blocking open in an executor, non-blocking fd reads via add_reader.

Only moves bytes (in the spirit of pyserial-asyncio): ``protocol.data_received(data)`` for every read,
``protocol.connection_lost(exc)`` when the port disappears (EIO on an unplugged USB device or a closed pty,
end of file), and a small write buffer drained with ``add_writer`` when the kernel buffer is full.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
from collections.abc import Callable

import serial

from mocapd.errors import DeviceError

_READ_SIZE = 65536


class SerialTransport(asyncio.Transport):
    """Transport over an open :class:`serial.Serial` (POSIX file descriptor)."""

    def __init__(self, loop: asyncio.AbstractEventLoop, protocol: asyncio.Protocol, port: serial.Serial) -> None:
        super().__init__()
        self._loop = loop
        self._protocol = protocol
        self._port = port
        self._fd: int = port.fileno()
        os.set_blocking(self._fd, False)
        self._write_buffer = bytearray()
        self._closing = False
        self._writer_registered = False
        self.bytes_read = 0
        loop.add_reader(self._fd, self._read_ready)
        loop.call_soon(protocol.connection_made, self)

    @property
    def port_name(self) -> str:
        return str(self._port.port)

    def _read_ready(self) -> None:
        try:
            data = os.read(self._fd, _READ_SIZE)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            self._lose(DeviceError(f"serial port {self.port_name} failed: {exc}"))
            return
        if not data:
            self._lose(DeviceError(f"serial port {self.port_name} closed (end of file)"))
            return
        self.bytes_read += len(data)
        self._protocol.data_received(data)

    def read_pending(self) -> None:
        """Read what the kernel holds for the port now, as the loop would when it next runs (a watcher about to
        judge the port silent asks first)."""
        if not self._closing:
            self._read_ready()

    def write(self, data: bytes | bytearray | memoryview) -> None:
        if self._closing or not data:
            return
        if self._write_buffer:
            self._write_buffer += data
            return
        try:
            n = os.write(self._fd, data)
        except (BlockingIOError, InterruptedError):
            n = 0
        except OSError as exc:
            self._lose(DeviceError(f"write to serial port {self.port_name} failed: {exc}"))
            return
        if n < len(data):
            self._write_buffer += memoryview(data)[n:]
            self._loop.add_writer(self._fd, self._write_ready)
            self._writer_registered = True

    def _write_ready(self) -> None:
        try:
            n = os.write(self._fd, self._write_buffer)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            self._lose(DeviceError(f"write to serial port {self.port_name} failed: {exc}"))
            return
        del self._write_buffer[:n]
        if not self._write_buffer:
            self._loop.remove_writer(self._fd)
            self._writer_registered = False

    def get_write_buffer_size(self) -> int:
        return len(self._write_buffer)

    def is_closing(self) -> bool:
        return self._closing

    def close(self) -> None:
        self._lose(None)

    def abort(self) -> None:
        self._lose(None)

    def _lose(self, exc: Exception | None) -> None:
        if self._closing:
            return
        self._closing = True
        self._loop.remove_reader(self._fd)
        if self._writer_registered:
            self._loop.remove_writer(self._fd)
        with contextlib.suppress(OSError, serial.SerialException):
            self._port.close()
        self._loop.call_soon(self._protocol.connection_lost, exc)


def _open_port(url: str, baudrate: int) -> serial.Serial:
    # exclusive=True: a second reader on the same device would silently steal bytes.
    return serial.serial_for_url(url, baudrate=baudrate, timeout=0, write_timeout=0, exclusive=True)


async def create_serial_connection(
    protocol_factory: Callable[[], asyncio.Protocol], url: str, *, baudrate: int = 921_600
) -> tuple[SerialTransport, asyncio.Protocol]:
    """Open ``url`` (a device path) in the default executor and wire it to a new protocol.

    Raises
    ------
    DeviceError
        If the port cannot be opened (missing, busy, permission), with the reason.
    """
    loop = asyncio.get_running_loop()
    try:
        port = await loop.run_in_executor(None, _open_port, url, baudrate)
    except (serial.SerialException, OSError, ValueError) as exc:
        raise DeviceError(f"cannot open serial port {url}: {exc}") from exc
    protocol = protocol_factory()
    return SerialTransport(loop, protocol, port), protocol
