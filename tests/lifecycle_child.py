"""A child for tests/test_lifecycle.py, run through ``python -m mocapd.io.lifecycle tests.lifecycle_child:sleep``."""

from __future__ import annotations

import time


def sleep(argv: list[str]) -> int:
    """Sleep ``argv[0]`` seconds (a child that would outlive its parent)."""
    time.sleep(float(argv[0]))
    return 0


def spam(argv: list[str]) -> int:
    """Log the same warning ``argv[0]`` times from one call site (the rate limit of every mocapd process)."""
    import logging

    log = logging.getLogger("mocapd.test")
    for i in range(int(argv[0])):
        log.warning("the same fault again (%d)", i)
    return 0
