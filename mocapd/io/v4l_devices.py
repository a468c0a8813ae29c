"""The V4L2 video capture devices (UVC webcams and others) the kernel knows, read from sysfs: nothing is opened.

For each ``/sys/class/video4linux/videoN``: its ``name``, its ``index`` (a UVC camera registers a metadata node
beside its capture node; only index 0 of a physical device delivers images, so only those are listed), and,
when it hangs off USB, the USB device's vendor:product id and serial (``device`` links to the USB interface,
whose parent holds ``idVendor``, ``idProduct``, ``serial``). The stable ``/dev/v4l/by-id/...`` link of each node
is given where udev made one: ``/dev/videoN`` numbers change with plugging order, by-id paths do not.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

SYSFS = Path("/sys/class/video4linux")
BY_ID = Path("/dev/v4l/by-id")


@dataclass(frozen=True, slots=True)
class VideoDevice:
    """One video capture node."""

    device: str
    """``/dev/videoN``."""
    name: str
    """The driver's name for it (a UVC camera's USB product string)."""
    by_id: str
    """Stable path (``/dev/v4l/by-id/usb-...-video-index0``) or ""."""
    usb_id: str
    """``vvvv:pppp`` (hex) when it is a USB device, else ""."""
    serial: str
    """USB serial number, "" when the device has none."""


def _read(path: Path) -> str:
    try:
        return path.read_text(encoding="utf-8", errors="replace").strip()
    except OSError:
        return ""


def _node_key(path: Path) -> tuple[int, str]:
    match = re.search(r"(\d+)$", path.name)
    return (int(match.group(1)) if match else -1, path.name)


def _by_id_links(folder: Path) -> dict[str, str]:
    links: dict[str, str] = {}
    if folder.is_dir():
        for link in sorted(folder.iterdir()):
            try:
                links.setdefault(str(link.resolve()), str(link))
            except OSError:  # a dangling or looping link: that node has no stable path, the others still do
                continue
    return links


def list_video_devices(sysfs: Path = SYSFS, by_id: Path = BY_ID, dev: Path = Path("/dev")) -> list[VideoDevice]:
    """The capture nodes under ``sysfs``, in device-number order.

    Parameters
    ----------
    sysfs : Path
        The ``video4linux`` class folder (a test points it at a tree of its own).
    by_id : Path
        Folder of udev's stable links.
    dev : Path
        Folder the device nodes are in (their names are the sysfs entries' names).
    """
    if not sysfs.is_dir():
        return []
    stable = _by_id_links(by_id)
    out = []
    for node in sorted(sysfs.iterdir(), key=_node_key):
        name = _read(node / "name")
        index = _read(node / "index") or "0"
        if not name or index != "0":
            continue
        usb = (node / "device").resolve().parent
        vendor, product = _read(usb / "idVendor"), _read(usb / "idProduct")
        path = str(dev / node.name)
        out.append(
            VideoDevice(
                device=path,
                name=name,
                by_id=stable.get(path, ""),
                usb_id=f"{vendor}:{product}" if vendor and product else "",
                serial=_read(usb / "serial") if vendor else "",
            )
        )
    return out
