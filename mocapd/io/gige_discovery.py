"""GigE Vision discovery on one named network interface, never on any other.

Why our own: Aravis 0.8.26 (Debian 12) sends its discovery broadcast from every IPv4 interface of the host and
offers no way to restrict it (``arv_gv_interface_set_discovery_interface_name`` came later). mocapd never lets
Aravis' GigE Vision discovery run (:func:`mocapd.io.aravis_camera.aravis_without_gige_discovery`); a GigE camera
is opened by IP address, or found here on the interface the config names and then opened by the IP it reported.

How. One UDP socket, bound to the interface (``SO_BINDTODEVICE``) and to its IPv4 address, sends the
DISCOVERY_CMD of :mod:`mocapd.protocols.gvcp` to the limited broadcast address 255.255.255.255, port 3956, and
collects acknowledges for ``timeout_s``. Why the limited broadcast rather than the interface's subnet broadcast:
it is the address GigE Vision broadcast discovery is defined on, and it also reaches a camera whose address is
outside the interface's subnet (a link-local or factory address: the usual first contact with a new camera).
It leaves through that interface only: the socket is bound to the device, and Linux sends a limited broadcast
from a bound source address out of the interface owning that address even where ``SO_BINDTODEVICE`` is refused
(kernels before 5.7 required CAP_NET_RAW for it). The command is sent ``sends`` times spread over the first half
of the window (UDP may lose one); a device answering twice is counted once.

Answers from this host itself are not cameras on the link: Linux also delivers a broadcast it sends to the host's
own listeners, so a program here listening on port 3956 (an Aravis fake camera, a GigE Vision emulator) answers
discovery on every interface. Their answers come from one of the host's own addresses; they are counted
(:attr:`GigEDiscovery.local_answers`) and left out, except on a loopback interface, where every camera is local.

Matching a camera by name follows Aravis' own names, so that ``device_id`` means what ``arv-tool-0.8`` shows:
``<manufacturer>-<model>-<serial>`` (the MAC address standing in for an empty serial, control characters
removed), the user-defined name, ``<manufacturer>-<serial>``, Aravis' vendor alias with the serial, or the MAC.
"""

from __future__ import annotations

import contextlib
import ipaddress
import select
import socket
import time
from dataclasses import dataclass, field

import psutil

from mocapd.errors import DeviceError
from mocapd.protocols.gvcp import GVCP_PORT, DiscoveryAck, DiscoveryCollector, DiscoveryCounters

LIMITED_BROADCAST = "255.255.255.255"
DEFAULT_TIMEOUT_S = 1.0
"""How long discovery waits for acknowledges (GigE Vision devices answer within a few ms; a device may delay its
answer by its discovery-ack-delay register, 1 s by default where it exists, hence Aravis' 1 s too)."""

# Aravis 0.8.26 arvinterfaceprivate.h ARV_DEVICE_NAME_ILLEGAL_CHARACTERS (0x10 is not in it) and arvmisc.c
# vendor_aliases.
_ILLEGAL = {c for c in range(0x01, 0x20) if c != 0x10}
_VENDOR_ALIASES = {
    "The Imaging Source Europe GmbH": "TIS",
    "Point Grey Research": "PointGrey",
    "Lucid Vision Labs": "LucidVision",
    "New-Imaging-Technologies": "NIT",
}


@dataclass(frozen=True, slots=True)
class InterfaceAddress:
    """The IPv4 address of one network interface."""

    name: str
    address: str
    netmask: str
    broadcast: str
    """The subnet broadcast address ("" for an interface without one, such as lo)."""


def interface_ipv4(name: str) -> InterfaceAddress:
    """The first IPv4 address of interface ``name``.

    Raises
    ------
    DeviceError
        If there is no such interface (the message lists the ones there are), it is down, or it has no IPv4
        address.
    """
    addresses = psutil.net_if_addrs()
    if name not in addresses:
        raise DeviceError(f"no network interface {name!r} (there are: {', '.join(sorted(addresses)) or 'none'})")
    stats = psutil.net_if_stats().get(name)
    if stats is not None and not stats.isup:
        raise DeviceError(f"network interface {name!r} is down")
    for a in addresses[name]:
        if a.family == socket.AF_INET:
            return InterfaceAddress(name, a.address, a.netmask or "", a.broadcast or "")
    raise DeviceError(f"network interface {name!r} has no IPv4 address: give it one on the cameras' subnet")


def aravis_device_id(ack: DiscoveryAck) -> str:
    """The device id Aravis 0.8 gives this camera: ``<manufacturer>-<model>-<serial or MAC>``."""
    return _strip_illegal(f"{ack.manufacturer}-{ack.model}-{ack.serial or ack.mac}")


def aravis_names(ack: DiscoveryAck) -> set[str]:
    """Every name Aravis opens this camera by (its device id, user-defined name, vendor-serial, alias-serial,
    MAC)."""
    serial = ack.serial or ack.mac
    alias = _VENDOR_ALIASES.get(ack.manufacturer, ack.manufacturer)
    names = {aravis_device_id(ack), _strip_illegal(f"{ack.manufacturer}-{serial}"),
             _strip_illegal(f"{alias}-{serial}"), ack.mac}  # fmt: skip
    if ack.user_name:
        names.add(ack.user_name)
    return names


def _strip_illegal(text: str) -> str:
    return "".join(ch for ch in text if ord(ch) not in _ILLEGAL)


@dataclass(frozen=True, slots=True)
class GigECamera:
    """A camera that answered discovery on ``interface``."""

    ack: DiscoveryAck
    source: str
    """IPv4 address the acknowledge came from."""
    interface: InterfaceAddress

    @property
    def address(self) -> str:
        """The IPv4 address to open it at: the one it reports, or where its answer came from if it reports none."""
        return self.ack.ip if self.ack.ip != "0.0.0.0" else self.source

    @property
    def device_id(self) -> str:
        return aravis_device_id(self.ack)

    def matches(self, *, serial: str = "", device_id: str = "") -> bool:
        """Whether this is the camera named by ``serial`` (surrounding spaces ignored) or Aravis ``device_id``."""
        if serial:
            return self.ack.serial.strip() == serial.strip()
        return bool(device_id) and device_id in aravis_names(self.ack)


@dataclass(frozen=True, slots=True)
class GigEDiscovery:
    """The result of one discovery on one interface."""

    interface: InterfaceAddress
    cameras: list[GigECamera]
    counters: DiscoveryCounters = field(default_factory=DiscoveryCounters)
    local_answers: int = 0
    """Answers from programs on this host, left out (see the module docstring)."""


def _bound_socket(iface: InterfaceAddress) -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
        # Refused without CAP_NET_RAW on kernels before 5.7: the bound source address below still keeps the
        # limited broadcast on this interface (see the module docstring).
        with contextlib.suppress(PermissionError):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_BINDTODEVICE, iface.name.encode())
        sock.bind((iface.address, 0))
    except OSError as exc:
        sock.close()
        raise DeviceError(f"cannot open a discovery socket on {iface.name} ({iface.address}): {exc}") from exc
    sock.setblocking(False)
    return sock


def discover(interface: str, timeout_s: float = DEFAULT_TIMEOUT_S, *, sends: int = 2) -> GigEDiscovery:
    """Broadcast GigE Vision discovery on ``interface`` only and collect the cameras that answer (blocking for
    ``timeout_s``).

    Parameters
    ----------
    interface : str
        Network interface name (``eth1``, ``enp3s0``...).
    timeout_s : float
        How long to wait for acknowledges, in seconds.
    sends : int
        How many discovery commands to send, spread over the first half of the window.

    Raises
    ------
    DeviceError
        If the interface does not exist, is down, has no IPv4 address, or the broadcast cannot be sent.
    """
    if timeout_s <= 0 or sends < 1:
        raise ValueError(f"discovery needs timeout_s > 0 and sends >= 1, got {timeout_s} and {sends}")
    iface = interface_ipv4(interface)
    collector = DiscoveryCollector()
    start = time.monotonic()
    deadline = start + timeout_s
    send_at = [start + k * timeout_s / (2 * sends) for k in range(sends)]
    with _bound_socket(iface) as sock:
        while (now := time.monotonic()) < deadline:
            while send_at and send_at[0] <= now:
                send_at.pop(0)
                try:
                    sock.sendto(collector.command(), (LIMITED_BROADCAST, GVCP_PORT))
                except OSError as exc:
                    raise DeviceError(f"cannot send GigE Vision discovery on {interface}: {exc}") from exc
            wake = min(deadline, send_at[0]) if send_at else deadline
            readable, _, _ = select.select([sock], [], [], max(0.0, wake - time.monotonic()))
            if readable:
                _drain(sock, collector)
    cameras = sorted((GigECamera(d.ack, d.source, iface) for d in collector.devices), key=_by_address)
    if not ipaddress.IPv4Address(iface.address).is_loopback:
        own = _host_ipv4_addresses()
        remote = [c for c in cameras if c.source not in own]
        return GigEDiscovery(iface, remote, collector.counters, local_answers=len(cameras) - len(remote))
    return GigEDiscovery(iface, cameras, collector.counters)


def _by_address(camera: GigECamera) -> tuple[int, str]:
    return int(ipaddress.IPv4Address(camera.address)), camera.ack.serial


def _host_ipv4_addresses() -> set[str]:
    return {a.address for addrs in psutil.net_if_addrs().values() for a in addrs if a.family == socket.AF_INET}


def _drain(sock: socket.socket, collector: DiscoveryCollector) -> None:
    while True:
        try:
            data, (source, _port) = sock.recvfrom(2048)
        except BlockingIOError:
            return
        except OSError as exc:
            raise DeviceError(f"GigE Vision discovery: receiving failed: {exc}") from exc
        collector.receive_datagram(data, source)


def find_camera(
    interface: str, *, serial: str = "", device_id: str = "", timeout_s: float = DEFAULT_TIMEOUT_S
) -> GigECamera:
    """The one camera on ``interface`` with this ``serial`` or Aravis ``device_id``.

    Raises
    ------
    DeviceError
        If discovery fails, no camera matches (the message lists those that answered) or several do.
    """
    if bool(serial) == bool(device_id):
        raise ValueError("find_camera needs exactly one of serial, device_id")
    found = discover(interface, timeout_s)
    matching = [c for c in found.cameras if c.matches(serial=serial, device_id=device_id)]
    what = f"serial {serial!r}" if serial else f"device id {device_id!r}"
    if not matching:
        seen = ", ".join(f"{c.device_id} at {c.address}" for c in found.cameras) or "none"
        raise DeviceError(
            f"no GigE Vision camera with {what} answered discovery on {interface} within {timeout_s:g} s "
            f"(cameras that answered: {seen})"
        )
    if len(matching) > 1:
        at = ", ".join(c.address for c in matching)
        raise DeviceError(f"several GigE Vision cameras with {what} answered on {interface} ({at}): open by address")
    return matching[0]
