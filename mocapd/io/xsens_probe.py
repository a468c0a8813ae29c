"""Finding Xsens devices on serial ports and asking each what it is.

:func:`list_xsens_ports` lists the USB serial ports of Xsens devices (USB vendor id 0x2639, from pyserial's
``list_ports``: sysfs only, nothing is opened). :func:`probe_xsens` opens one port and runs the first steps of
bring-up (:func:`mocapd.protocols.xsens_session.identify_steps`: GoToConfig, ReqDID, ReqProductCode, ReqFWRev)
with short time-outs, so a port with nothing Xsens behind it costs at most ``4 × attempts × response_timeout_s``.
The device is left in configuration mode: it streams again when mocapd (or any other program) brings it up.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from serial.tools import list_ports
from serial.tools.list_ports_common import ListPortInfo

from mocapd.errors import DeviceError, DeviceTimeout
from mocapd.io.serial_transport import SerialTransport, create_serial_connection
from mocapd.protocols.xsens_session import BringUpFailed, DeviceInfo, State, Streaming, XsensSession, identify_steps

XSENS_USB_VENDOR = 0x2639
BY_ID = Path("/dev/serial/by-id")


@dataclass(frozen=True, slots=True)
class SerialPort:
    """A serial port that an Xsens device is (or may be) on."""

    device: str
    """``/dev/ttyUSB0``, ``/dev/ttyACM0`` or a path given by the user."""
    stable: str
    """``/dev/serial/by-id/...`` link to it, "" where udev made none: the path to put in ``[imu] ports``."""
    usb_id: str
    """``vvvv:pppp`` (hex), "" when unknown."""
    description: str


@dataclass(frozen=True, slots=True)
class ProbeResult:
    """What one port said: ``info`` when an Xsens device answered, else ``error`` says why not."""

    port: SerialPort
    info: DeviceInfo | None
    error: str = ""


def _stable_links(folder: Path) -> dict[str, str]:
    links: dict[str, str] = {}
    if folder.is_dir():
        for link in sorted(folder.iterdir()):
            with contextlib.suppress(OSError):  # a dangling link: no stable path for that port
                links.setdefault(str(link.resolve(strict=True)), str(link))
    return links


def list_xsens_ports(by_id: Path = BY_ID) -> list[SerialPort]:
    """Serial ports whose USB vendor is Xsens (0x2639), in device-name order."""
    return xsens_ports(list_ports.comports(), _stable_links(by_id))


def xsens_ports(ports: Iterable[ListPortInfo], stable: Mapping[str, str]) -> list[SerialPort]:
    """The Xsens ones (USB vendor 0x2639) of pyserial's port list; ``stable`` maps a device to its by-id link."""
    out = []
    for p in sorted(ports, key=lambda p: p.device):
        if p.vid != XSENS_USB_VENDOR:
            continue
        usb_id = f"{p.vid:04x}:{p.pid:04x}" if p.pid is not None else f"{p.vid:04x}:"
        out.append(SerialPort(p.device, stable.get(p.device, ""), usb_id, p.description or ""))
    return out


def port_for_path(path: str, by_id: Path = BY_ID) -> SerialPort:
    """A :class:`SerialPort` for a path the user named (a pseudo-terminal, a by-id link...)."""
    resolved = str(Path(path).resolve())
    stable = path if path.startswith(str(by_id)) else _stable_links(by_id).get(resolved, "")
    return SerialPort(path, stable, "", "")


class _ProbeProtocol(asyncio.Protocol):
    def __init__(self, session: XsensSession) -> None:
        self.session = session
        self.transport: SerialTransport | None = None
        self.changed = asyncio.Event()
        self.lost: Exception | None = None
        self.closed = False

    def data_received(self, data: bytes) -> None:
        self.session.receive_data(data, time.monotonic_ns())
        self.flush()
        self.changed.set()

    def flush(self) -> None:
        out = self.session.data_to_send()
        if out and self.transport is not None:
            self.transport.write(out)

    def connection_lost(self, exc: Exception | None) -> None:
        self.closed = True
        self.lost = exc
        self.changed.set()


async def probe_xsens(
    path: str, *, baudrate: int = 921_600, response_timeout_s: float = 0.25, attempts: int = 2
) -> DeviceInfo:
    """Open ``path`` and ask the device its id, product code and firmware revision.

    Raises
    ------
    DeviceError
        If the port cannot be opened or closes.
    DeviceTimeout
        If no Xsens device answers (the message names the step that got no reply).
    """
    session = XsensSession([], response_timeout_ns=round(response_timeout_s * 1e9), attempts=attempts,
                           steps=identify_steps())  # fmt: skip
    transport, proto = await create_serial_connection(lambda: _ProbeProtocol(session), path, baudrate=baudrate)
    assert isinstance(proto, _ProbeProtocol)
    proto.transport = transport  # connection_made comes later (call_soon); the first request goes out now
    try:
        session.start(time.monotonic_ns())
        proto.flush()
        while session.state is State.BRINGING_UP:
            if proto.closed:
                raise DeviceError(f"serial port {path} closed while probing ({proto.lost})")
            deadline = session.deadline_ns
            wait_s = 0.0 if deadline is None else max(0.0, (deadline - time.monotonic_ns()) / 1e9)
            proto.changed.clear()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(proto.changed.wait(), timeout=wait_s)
            session.handle_timeout(time.monotonic_ns())
            proto.flush()
        for event in session.events_received():
            if isinstance(event, Streaming):
                return event.info
            if isinstance(event, BringUpFailed):
                raise DeviceTimeout(f"{path}: no Xsens device answered ({event.reason})")
        raise DeviceTimeout(f"{path}: no Xsens device answered")
    finally:
        transport.close()


async def probe_ports(
    ports: Sequence[SerialPort], *, baudrate: int = 921_600, response_timeout_s: float = 0.25, attempts: int = 2
) -> list[ProbeResult]:
    """Probe every port at once (each with its own time-outs); a port that fails gives its error, not an
    exception."""

    async def one(port: SerialPort) -> ProbeResult:
        try:
            info = await probe_xsens(
                port.device, baudrate=baudrate, response_timeout_s=response_timeout_s, attempts=attempts
            )
        except DeviceError as exc:
            return ProbeResult(port, None, str(exc))
        return ProbeResult(port, info)

    return list(await asyncio.gather(*(one(p) for p in ports)))
