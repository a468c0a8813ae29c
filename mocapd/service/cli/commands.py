"""The ``mocapd`` command line: the parser of every command, and dispatch (:mod:`mocapd.service.cli` runs it)."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence

from mocapd import __version__
from mocapd.errors import InputError
from mocapd.service.cli import bench as cmd_bench
from mocapd.service.cli import calibrate as cmd_calibrate
from mocapd.service.cli import daemon as cmd_daemon
from mocapd.service.cli import devices as cmd_devices
from mocapd.service.cli import eval as eval_cli
from mocapd.service.cli import feed as cmd_feed
from mocapd.service.cli import imu as cmd_imu
from mocapd.service.cli import model as cmd_model
from mocapd.service.cli import recordings as cmd_recordings
from mocapd.service.cli import session as cmd_session


def _cmd_eval_tracking(args: argparse.Namespace) -> int:
    from mocapd.eval import tracking as eval_tracking
    from mocapd.io.progress import Progress

    motion = "synthetic" if args.synthetic else "real"
    n_scenes = len(args.scene) if args.scene else len(eval_tracking.SCENES)
    try:
        with Progress(2 * n_scenes, "eval tracking") as bar:
            report = eval_tracking.evaluate(seconds=args.seconds, seed=args.seed, motion=motion, scenes=args.scene,
                                            progress=bar)  # fmt: skip
    except InputError as exc:  # an unknown scene name
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(report, indent=2))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mocapd", description="Real-time multi-person motion capture daemon.")
    parser.add_argument("--version", action="version", version=f"mocapd {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    cmd_bench.register(sub)  # solver, sorting, detector, streams, record, capture (latency: cmd_daemon)

    ev = sub.add_parser("eval", help="evaluations that print JSON")
    ev_sub = ev.add_subparsers(dest="eval", metavar="EVAL", required=True)
    tracking = ev_sub.add_parser("tracking", help="multi-person tracking on synthetic scenes")
    tracking.add_argument("--seconds", type=float, default=8.0, help="length of each scene (default 8)")
    tracking.add_argument("--seed", type=int, default=0)
    tracking.add_argument("--synthetic", action="store_true", help="generated motion instead of recorded clips")
    tracking.add_argument("--scene", action="append", default=None, metavar="NAME",
                          help="run only this scene (repeatable; default: every scene)")  # fmt: skip
    tracking.set_defaults(func=_cmd_eval_tracking)
    eval_cli.register(ev_sub)

    cmd_calibrate.register(sub)
    cmd_imu.register(sub)  # adds "imu" to the calibrate group
    cmd_model.register(sub)
    cmd_daemon.register(sub)  # run, demo, check-config, bench latency
    cmd_devices.register(sub)
    cmd_session.register(sub)  # replay, resolve, export, session
    cmd_recordings.register(sub)  # import mtw, import mvnx, import keypoints
    cmd_feed.register(sub)  # feed keypoints
    return parser


def dispatch(argv: Sequence[str] | None) -> tuple[int, bool]:
    """Run one command; returns its exit status and whether the process may end without interpreter teardown."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2, False
    result: int = args.func(args)
    return result, bool(getattr(args, "fast_exit", False))


def main(argv: Sequence[str] | None = None) -> int:
    """Run one command and return its exit status (what tests call, in-process)."""
    return dispatch(argv)[0]
