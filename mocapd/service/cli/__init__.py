"""The ``mocapd`` command line.

This module is light on purpose: :func:`entry` installs the stop signals' handlers
(:func:`mocapd.io.lifecycle.install_stop_signals`) before the commands are imported — seconds of NumPy, SciPy,
OpenCV and pydantic on a loaded machine, during which a Ctrl-C would otherwise print a ``KeyboardInterrupt``
traceback, a SIGHUP kill the process unannounced, and a SIGINT inherited as ignored be lost. The parser and the
commands are in :mod:`mocapd.service.cli.commands`.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import argparse


#: commands that serve until stopped: a stop signal is how they end, exit status 0 (others: 128 + the signal)
SERVING = frozenset({"run", "demo", "detect-host", "replay", "feed"})


def _command(argv: Sequence[str]) -> str:
    """The command word of a command line (its first argument that is not an option; "" if none)."""
    return next((a for a in argv if not a.startswith("-")), "")


def entry() -> None:
    """The ``mocapd`` program (console script and ``python -m mocapd``).

    A stop signal ends a serving command (``run``, ``demo``, ``detect-host``, ``replay``) cleanly with exit status
    0, whatever phase it is in; any other command stops with 128 + the signal's number (130 for SIGINT, 143 for
    SIGTERM, 129 for SIGHUP), its output not written. The long-running commands end with
    :func:`~mocapd.io.lifecycle.exit_now` once they have closed everything they opened; others exit normally.
    """
    from mocapd.io import lifecycle

    command = _command(sys.argv[1:])

    def stop_status(signum: int) -> int:
        return 0 if command in SERVING else 128 + signum

    lifecycle.install_stop_signals(f"mocapd {command}".rstrip(), stop_status)
    lifecycle.enter_phase("starting")  # STATUS=starting: what systemd (and a test) sees once a stop is handled
    try:
        from mocapd.service.cli.commands import dispatch

        lifecycle.setup_logging()
        code, fast = dispatch(None)
    except lifecycle.StopRequested as stop:  # a command that computes (resolve, eval), or a daemon's set-up
        code, fast = stop_status(stop.signum), True
    except BrokenPipeError:  # `mocapd session S | head`: the reader left; not an error of ours, no traceback
        code, fast = 0, True
    if fast:
        lifecycle.exit_now(code)
    sys.exit(code)


def main(argv: Sequence[str] | None = None) -> int:
    """Run one command and return its exit status (what tests call, in-process)."""
    from mocapd.service.cli.commands import main as run

    return run(argv)


def build_parser() -> argparse.ArgumentParser:
    """The parser of every command."""
    from mocapd.service.cli.commands import build_parser as build

    return build()


if __name__ == "__main__":
    entry()
