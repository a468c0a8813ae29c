"""``mocapd feed keypoints``: another detector's keypoint files into a running daemon, over Zenoh.

::

    mocapd feed keypoints --config feed.toml --calibration calib.toml --fps 30 [--follow] CAM=FOLDER...

``feed.toml`` is a camera host's config (``[zenoh]``: ``rig``, ``host``, ``connect``: docs/scaling.md); the daemon
runs the cameras as ``source = "zenoh"`` cameras of that host. See :mod:`mocapd.service.feed` and
``docs/sessions.md`` ("Live: feeding a running daemon").
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from mocapd.errors import ConfigError, MocapdError
from mocapd.service.cli.numbers import number


def cmd_feed_keypoints(args: argparse.Namespace) -> int:
    from mocapd.io.calibration_files import read_any
    from mocapd.service import feed
    from mocapd.service.config import load_config

    try:
        cfg = load_config(args.config)
    except ConfigError as exc:
        for line in str(exc).splitlines():
            print(f"{args.config}: error: {line}", file=sys.stderr)
        return 2

    def ready(host: str, cameras: list[str]) -> None:
        print(f"ready: host {host} feeding {', '.join(cameras)} on mocapd/{cfg.zenoh.rig}/<camera>/detections"
              + (" (following; Ctrl-C stops)" if args.follow else ""), flush=True)  # fmt: skip

    try:
        calib = read_any(args.calibration)  # the cameras' names and image sizes: no world needed
        opts = feed.FeedOptions(list(args.inputs), args.fps, args.format, args.keypoints, args.solve_format,
                                args.latency, args.follow, seconds=args.seconds or None)  # fmt: skip
        result = feed.run(cfg, calib, opts, on_ready=ready)
    except MocapdError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(result, indent=2))
    return 0


def register(subparsers: Any) -> None:
    """Add ``feed keypoints``."""
    from mocapd.core.keypoint_sets import SETS
    from mocapd.core.keypoints import FORMATS as SOLVE_FORMATS
    from mocapd.io.keypoint_files import FORMATS, MAX_FPS, MIN_FPS

    fd = subparsers.add_parser("feed", help="feed a running daemon from outside: another detector's keypoints")
    what = fd.add_subparsers(dest="feed_what", metavar="WHAT", required=True)
    kp = what.add_parser("keypoints", help="per-frame keypoint files (OpenPose, MMPose) published as a camera host "
                         "over Zenoh (the daemon's cameras: source = \"zenoh\")")  # fmt: skip
    kp.add_argument("inputs", nargs="+", metavar="[CAMERA=]PATH",
                    help="per camera: the folder the detector writes its per-frame JSON into (as for `mocapd import "
                    "keypoints`)")  # fmt: skip
    kp.add_argument("--config", type=Path, required=True,
                    help="a camera host's config: [zenoh] rig, host, connect (docs/scaling.md)")  # fmt: skip
    kp.add_argument("--calibration", type=Path, required=True, metavar="FILE",
                    help="the daemon's calibration (the cameras' names and image sizes)")  # fmt: skip
    kp.add_argument("--fps", type=number(MIN_FPS, MAX_FPS), required=True, help="the detector's frame rate")
    kp.add_argument("--format", default="auto", choices=FORMATS, help="the files' layout (default: told from them)")
    kp.add_argument("--keypoints", default=None, choices=tuple(SETS),
                    help="the files' keypoint set (default: told from their length or metadata)")  # fmt: skip
    kp.add_argument("--solve-format", default=None, choices=tuple(SOLVE_FORMATS),
                    help="the daemon's [detector.model] keypoint_format (default: the one the set is solved in: "
                    "body25 for BODY_25, halpe26 for Halpe-26 and WholeBody, blazepose33 for BlazePose, coco17 for "
                    "COCO)")  # fmt: skip
    kp.add_argument(
        "--latency",
        type=number(0.0, 10.0),
        default=0.0,
        metavar="S",
        help="the detector's delay: the first frame was captured this long before its file appeared",
    )
    kp.add_argument("--follow", action="store_true",
                    help="keep reading the folders for new files until Ctrl-C (a detector writing live); without it "
                    "the files there are replayed at --fps and the command ends")  # fmt: skip
    kp.add_argument("--seconds", type=number(0.0, 1e6), default=0.0, help="with --follow: stop after this long")
    kp.set_defaults(func=cmd_feed_keypoints, fast_exit=True)
