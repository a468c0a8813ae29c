"""The ``mocapd`` command line."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from mocapd import __version__
from mocapd.service import cmd_model


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mocapd", description=__doc__)
    parser.add_argument("--version", action="version", version=f"mocapd {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    cmd_model.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    func = getattr(args, "func", None)
    return int(func(args)) if func is not None else 0


if __name__ == "__main__":
    sys.exit(main())
