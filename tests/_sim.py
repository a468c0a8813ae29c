"""Import helper: the device simulator lives in tools/ (a script), not in the package."""

from __future__ import annotations

import sys
from pathlib import Path

TOOLS = Path(__file__).resolve().parents[1] / "tools"
if str(TOOLS) not in sys.path:
    sys.path.insert(0, str(TOOLS))

import xsens_sim  # noqa: E402

__all__ = ["xsens_sim"]
