"""What devices this machine can see, and the ``[[cameras]]`` / ``[imu]`` config that would use them.

:func:`take_inventory` looks without broadcasting unless asked:

* USB3 Vision cameras through Aravis, its GigE Vision interface disabled (:mod:`mocapd.io.aravis_devices`);
* GigE Vision cameras only on the interfaces named (:mod:`mocapd.io.gige_discovery`: one broadcast per
  interface, on that interface only);
* V4L2 capture devices (UVC webcams) from sysfs (:mod:`mocapd.io.v4l_devices`);
* serial ports of Xsens devices (USB vendor 0x2639) and any ports named, each asked its device id, product code
  and firmware over Xbus (:mod:`mocapd.io.xsens_probe`).

:func:`config_snippet` turns an :class:`Inventory` into TOML for config.toml: one ``[[cameras]]`` entry per camera
(named from its user-defined name, or model and serial), an ``[imu]`` section with the ports, and commented
``[imu.assignment]`` lines to fill in.
"""

from __future__ import annotations

import asyncio
import json
import re
import unicodedata
from dataclasses import asdict, dataclass, field
from typing import Any

from mocapd.errors import DeviceError
from mocapd.io.aravis_devices import AravisDevice, list_aravis_devices
from mocapd.io.gige_discovery import DEFAULT_TIMEOUT_S, GigECamera, discover
from mocapd.io.v4l_devices import VideoDevice, list_video_devices
from mocapd.io.xsens_probe import ProbeResult, list_xsens_ports, port_for_path, probe_ports
from mocapd.protocols.gvcp import IpConfig

_NAME_MAX = 32
_NOT_IN_NAME = re.compile(r"[^A-Za-z0-9_.-]+")
_CONTROL = re.compile(r"[\x00-\x1f\x7f-\x9f]")


@dataclass(frozen=True)
class InventoryOptions:
    """What to look for beyond what needs no broadcast."""

    gige_interfaces: tuple[str, ...] = ()
    """Network interfaces to run GigE Vision discovery on (nothing is broadcast elsewhere)."""
    serial_paths: tuple[str, ...] = ()
    """Serial ports to probe for an Xsens device besides the Xsens USB ports found."""
    gige_timeout_s: float = DEFAULT_TIMEOUT_S
    baudrate: int = 921_600
    response_timeout_s: float = 0.25
    """Per Xbus request of the probe, in seconds (each sent twice before giving up)."""


@dataclass
class Inventory:
    """Everything found, and what went wrong while looking."""

    aravis: list[AravisDevice] = field(default_factory=list)
    gige: list[GigECamera] = field(default_factory=list)
    gige_counters: dict[str, dict[str, int]] = field(default_factory=dict)
    """Per interface: what became of the datagrams discovery received, and the answers from this host left out."""
    uvc: list[VideoDevice] = field(default_factory=list)
    serial: list[ProbeResult] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)
    """One line per thing that could not be looked at."""
    failed_requests: int = 0
    """How many of the interfaces and ports the user named gave nothing usable."""


def take_inventory(opts: InventoryOptions) -> Inventory:
    """Look for every kind of device (blocking: up to ``gige_timeout_s`` per interface, and the Xsens probes)."""
    inv = Inventory()
    try:
        inv.aravis = [d for d in list_aravis_devices() if d.protocol != "GigEVision"]
    except DeviceError as exc:
        inv.problems.append(f"aravis: {exc}")
    for interface in opts.gige_interfaces:
        try:
            found = discover(interface, opts.gige_timeout_s)
        except DeviceError as exc:
            inv.problems.append(f"gige {interface}: {exc}")
            inv.failed_requests += 1
            continue
        inv.gige += found.cameras
        inv.gige_counters[interface] = {**found.counters.as_dict(), "local_answers": found.local_answers}
    inv.uvc = list_video_devices()
    ports = list_xsens_ports()
    known = {p.device for p in ports}
    ports += [port_for_path(p) for p in opts.serial_paths if p not in known]
    inv.serial = asyncio.run(probe_ports(ports, baudrate=opts.baudrate, response_timeout_s=opts.response_timeout_s))
    for result in inv.serial:
        if result.info is None:
            inv.problems.append(f"serial {result.port.device}: {result.error}")
            if result.port.device in opts.serial_paths:
                inv.failed_requests += 1
    return inv


def camera_name(*parts: str) -> str:
    """A ``[[cameras]]`` name (1-32 of ``A-Za-z0-9_.-``) from descriptive parts, the last one kept whole where it
    fits (the serial: what tells two cameras of one model apart)."""
    ascii_parts = [unicodedata.normalize("NFKD", p).encode("ascii", "ignore").decode() for p in parts]  # Ü -> U
    clean = [_NOT_IN_NAME.sub("_", p).strip("_") for p in ascii_parts if p.strip()]
    clean = [c for c in clean if c]
    if not clean:
        return "camera"
    last = clean[-1][-_NAME_MAX:]
    head = "-".join(clean[:-1])
    room = _NAME_MAX - len(last) - 1
    if not head or room < 1:
        return last
    return f"{head[:room].rstrip('_-')}-{last}"


def _unique(name: str, taken: set[str]) -> str:
    out, k = name, 2
    while out in taken:
        suffix = f"-{k}"
        out, k = name[: _NAME_MAX - len(suffix)] + suffix, k + 1
    taken.add(out)
    return out


def printable(text: str) -> str:
    """``text`` with control characters (line breaks, terminal escapes) replaced by ``?``. What a device says
    about itself goes into comments of the snippet and onto the terminal: a name with a line break in it must
    not become a line of config."""
    return _CONTROL.sub("?", text)


def _toml(value: str) -> str:
    # A JSON string is a valid TOML basic string (same escapes), and json.dumps escapes every control character.
    return json.dumps(value, ensure_ascii=False)


def _ip_config(ack_config: IpConfig) -> str:
    names = [(flag.name or "").lower() for flag in IpConfig if flag in ack_config]
    return "+".join(names) or "none"


def _aravis_entry(dev: AravisDevice, name: str) -> list[str]:
    about = f"{dev.protocol}: {dev.vendor} {dev.model}, serial {dev.serial or '-'} ({dev.physical_id})"
    lines = [f"# {printable(about)}",
             "[[cameras]]", f"name = {_toml(name)}", 'source = "aravis"']  # fmt: skip
    # Aravis' Fake devices are found by id only; a USB3 Vision camera by the serial printed on it.
    if dev.serial and dev.protocol == "USB3Vision":
        lines.append(f"serial = {_toml(dev.serial)}")
    else:
        lines.append(f"device_id = {_toml(dev.device_id)}")
    return lines


def _gige_entry(cam: GigECamera, name: str) -> list[str]:
    ack = cam.ack
    lines = [
        printable(
            f"# GigE Vision on {cam.interface.name}: {ack.manufacturer} {ack.model}, serial {ack.serial or '-'}, "
            f"MAC {ack.mac}, IP {cam.address} ({_ip_config(ack.ip_config_current)})"
        ),
        "[[cameras]]",
        f"name = {_toml(name)}",
        'source = "aravis"',
    ]
    by_serial = [f"serial = {_toml(ack.serial)}", f"interface = {_toml(cam.interface.name)}"]
    if not ack.serial:
        by_serial[0] = f"device_id = {_toml(cam.device_id)}"
    by_address = f"address = {_toml(cam.address)}"
    # A camera whose address comes from DHCP or link-local may change it: find it by serial on its link instead.
    if IpConfig.PERSISTENT in ack.ip_config_current or ack.ip_config_current == IpConfig(0):
        lines += [by_address, "# or find it by serial on its interface (one discovery broadcast there):",
                  *(f"# {line}" for line in by_serial)]  # fmt: skip
    else:
        lines += [*by_serial, "# or, once it has a fixed (persistent) address, open it directly:", f"# {by_address}"]
    return lines


def _uvc_entry(dev: VideoDevice, name: str) -> list[str]:
    what = ", ".join(p for p in (dev.usb_id, f"serial {dev.serial}" if dev.serial else "") if p)
    return [printable(f"# UVC: {dev.name} at {dev.device}" + (f" ({what})" if what else "")), "[[cameras]]",
            f"name = {_toml(name)}", 'source = "uvc"', f"device = {_toml(dev.by_id or dev.device)}"]  # fmt: skip


def config_snippet(inv: Inventory) -> str:
    """TOML for config.toml using every camera and Xsens device in ``inv`` (empty sections left out)."""
    taken: set[str] = set()
    blocks: list[list[str]] = []
    for dev in inv.aravis:
        blocks.append(_aravis_entry(dev, _unique(camera_name(dev.model, dev.serial or dev.device_id), taken)))
    for cam in inv.gige:
        ack = cam.ack
        name = camera_name(ack.user_name or ack.model, ack.serial or ack.mac.replace(":", ""))
        blocks.append(_gige_entry(cam, _unique(name, taken)))
    for video in inv.uvc:
        blocks.append(_uvc_entry(video, _unique(camera_name(video.name, video.serial), taken)))
    found = [(r.port.stable or r.port.device, r.info) for r in inv.serial if r.info is not None]
    if found:
        imu = ["[imu]", "ports = ["]
        imu += [f"    {_toml(path)},  # {printable(f'{i.product_code} {i.serial} firmware {i.firmware}')}"
                for path, i in found]  # fmt: skip
        imu += ["]", "", "# Which bone each sensor is on: uncomment, and name the bone (Hips, Head, LeftUpperArm...)."]
        imu += ["[imu.assignment]", *(f'# "{i.serial}" = "<bone>"' for _, i in found)]
        blocks.append(imu)
    head = ["# From `mocapd devices`. Every camera must also be in the [calibration] file under this name, at the",
            "# image size it delivers; [imu] replaces the section of that name in config.toml."]  # fmt: skip
    if not blocks:
        return "\n".join([*head, "# (no cameras or Xsens devices found)"]) + "\n"
    return "\n\n".join("\n".join(b) for b in [head, *blocks]) + "\n"


def inventory_json(inv: Inventory) -> dict[str, Any]:
    """The inventory as plain JSON values, with the config snippet."""
    gige = []
    for cam in inv.gige:
        ack = cam.ack
        entry = {k: v for k, v in asdict(ack).items() if k not in ("ip_config_supported", "ip_config_current")}
        entry.update(interface=cam.interface.name, address=cam.address, source=cam.source, device_id=cam.device_id,
                     ip_config=_ip_config(ack.ip_config_current), spec_version=list(ack.spec_version))  # fmt: skip
        gige.append(entry)
    serial = []
    for r in inv.serial:
        info = r.info
        serial.append({**asdict(r.port), "device_id": info.serial if info else None,
                       "product_code": info.product_code if info else None,
                       "firmware": info.firmware if info else None, "error": r.error or None})  # fmt: skip
    return {
        "aravis": [asdict(d) for d in inv.aravis],
        "gige": gige,
        "gige_counters": dict(inv.gige_counters),
        "uvc": [asdict(d) for d in inv.uvc],
        "serial": serial,
        "problems": list(inv.problems),
        "snippet": config_snippet(inv),
    }
