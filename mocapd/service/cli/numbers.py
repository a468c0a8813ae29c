"""Numbers on the command line are a door too: ``type=number(lo, hi)`` for argparse checks type, finiteness and
range where the argument is parsed (``--rate nan`` was a ``ValueError`` traceback in ``export``; ``--facing-heading
nan`` wrote a NaN calibration into the session with exit 0). A bad value is argparse's usage line and one
``error: argument --rate: ...`` line, exit 2."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable


def number(lo: float, hi: float, *, integer: bool = False) -> Callable[[str], float]:
    """An argparse ``type``: a finite number (an integer with ``integer``) in ``[lo, hi]``."""

    def parse(text: str) -> float:
        try:
            value: float = int(text) if integer else float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not {'an integer' if integer else 'a number'}") from None
        if not (math.isfinite(value) and lo <= value <= hi):
            raise argparse.ArgumentTypeError(f"{text!r}; allowed: {'an integer' if integer else 'a number'} from "
                                             f"{lo:g} to {hi:g}")  # fmt: skip
        return value

    parse.__name__ = "integer" if integer else "number"  # argparse names the type in its messages
    return parse
