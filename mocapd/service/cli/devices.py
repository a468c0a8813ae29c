"""``mocapd devices``: list the cameras and Xsens devices this machine can see, and print config for them.

Nothing is broadcast unless asked: USB3 Vision cameras, UVC devices and Xsens USB serial ports are found without
any network traffic; GigE Vision cameras only with ``--gige-interface IFACE`` (one discovery broadcast on that
interface, none elsewhere). ``--serial PATH`` probes a port that is not an Xsens USB device (a USB-serial adapter,
a pseudo-terminal). Prints a table per kind and a ``[[cameras]]`` / ``[imu]`` snippet to paste into config.toml;
``--json`` prints one JSON object instead. Exit status 1 when an interface or port named on the command line gave
nothing usable, else 0.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import TYPE_CHECKING, Any

from mocapd.io.gige_discovery import DEFAULT_TIMEOUT_S

# The parser is built for every command: the inventory (OpenCV for the UVC cameras, NumPy) is imported when
# `mocapd devices` runs, not by `mocapd --help`.
if TYPE_CHECKING:
    from mocapd.service.inventory import Inventory


def register(subparsers: Any) -> None:
    """Add ``devices`` to the CLI's subcommands."""
    p = subparsers.add_parser(
        "devices", help="list cameras and Xsens devices, and print a [[cameras]]/[imu] config snippet for them"
    )
    p.add_argument(
        "--gige-interface",
        action="append",
        default=[],
        metavar="IFACE",
        help="run GigE Vision discovery on this network interface (repeatable; nothing is broadcast anywhere else, "
        "and nowhere without this option)",
    )
    p.add_argument(
        "--serial",
        action="append",
        default=[],
        metavar="PATH",
        help="also ask this serial port for an Xsens device (repeatable)",
    )
    p.add_argument(
        "--timeout",
        type=float,
        default=DEFAULT_TIMEOUT_S,
        help=f"how long GigE Vision discovery waits for answers, s (default {DEFAULT_TIMEOUT_S:g})",
    )
    p.add_argument("--baudrate", type=int, default=921_600, help="serial baud rate for the Xsens probe")
    p.add_argument("--json", action="store_true", help="print one JSON object (with the snippet) instead")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from mocapd.service.inventory import InventoryOptions, config_snippet, inventory_json, take_inventory

    if args.timeout <= 0:
        print(f"error: --timeout must be > 0, got {args.timeout}", file=sys.stderr)
        return 2
    opts = InventoryOptions(
        gige_interfaces=tuple(args.gige_interface),
        serial_paths=tuple(args.serial),
        gige_timeout_s=args.timeout,
        baudrate=args.baudrate,
    )
    inv = take_inventory(opts)
    if args.json:
        print(json.dumps(inventory_json(inv), indent=2))
    else:
        print(render_tables(inv, searched=opts.gige_interfaces))
        print(config_snippet(inv), end="")
    for problem in inv.problems:
        print(f"warning: {problem}", file=sys.stderr)
    return 1 if inv.failed_requests else 0


def _table(headers: list[str], rows: list[list[str]]) -> list[str]:
    from mocapd.service.inventory import printable

    rows = [[printable(cell) for cell in row] for row in rows]  # what devices say about themselves
    widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(headers)]
    fmt = "  ".join(f"{{:<{w}}}" for w in widths)
    return ["  " + fmt.format(*headers).rstrip(), *("  " + fmt.format(*r).rstrip() for r in rows)]


def render_tables(inv: Inventory, *, searched: tuple[str, ...] = ()) -> str:
    """The human-readable listing: one table per kind of device, ``-`` for what a device did not say."""
    out: list[str] = []
    out.append("Aravis cameras (USB3 Vision; GigE Vision is listed only with --gige-interface):")
    rows = [[d.protocol, d.device_id, d.vendor, d.model, d.serial or "-", d.physical_id or "-"] for d in inv.aravis]
    out += _table(["protocol", "device id", "vendor", "model", "serial", "attached at"], rows) if rows else ["  none"]
    for interface in searched:
        out.append(f"GigE Vision cameras on {interface}:")
        cams = [c for c in inv.gige if c.interface.name == interface]
        rows = [
            [c.address, c.ack.mac, c.ack.manufacturer, c.ack.model, c.ack.serial or "-", c.ack.user_name or "-",
             c.ack.device_version or "-", c.device_id]
            for c in cams
        ]  # fmt: skip
        headers = ["address", "MAC", "vendor", "model", "serial", "user name", "version", "device id"]
        out += _table(headers, rows) if rows else ["  none"]
    out.append("UVC / V4L2 video devices:")
    rows = [[d.device, d.name, d.usb_id or "-", d.serial or "-", d.by_id or "-"] for d in inv.uvc]
    out += _table(["device", "name", "usb id", "serial", "stable path"], rows) if rows else ["  none"]
    out.append("Xsens serial devices:")
    rows = []
    for r in inv.serial:
        if r.info is None:
            rows.append([r.port.device, "-", "-", "-", f"no answer: {r.error}"])
        else:
            rows.append([r.port.device, r.info.serial, r.info.product_code, r.info.firmware, r.port.stable or "-"])
    out += _table(["port", "device id", "product code", "firmware", "stable path"], rows) if rows else ["  none"]
    # SlimeVR trackers are on Wi-Fi and find their server by broadcasting to it: nothing here can list them, and a
    # tracker owner following "from `mocapd devices` to a live avatar" would otherwise see no word about them.
    out.append("SlimeVR trackers (Wi-Fi, not listed here: they connect to a running server):")
    out.append("  set [imu.slimevr] enabled = true and host = this machine's LAN address, run `mocapd run --config "
               "FILE --verbose` and switch them on: each is named as it connects, and each sensor's id for "
               "[imu.slimevr.assignment] as it streams (also in /status imu.slimevr.trackers; docs/vr.md)")  # fmt: skip
    return "\n".join(out) + "\n"
