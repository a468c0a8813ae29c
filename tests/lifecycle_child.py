"""A child for tests/test_lifecycle.py, run through ``python -m mocapd.io.lifecycle tests.lifecycle_child:sleep``."""

from __future__ import annotations

import time


def sleep(argv: list[str]) -> int:
    """Sleep ``argv[0]`` seconds (a child that would outlive its parent)."""
    time.sleep(float(argv[0]))
    return 0
