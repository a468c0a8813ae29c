#!/usr/bin/env python3
"""Noise levels of the real MTw recordings in static segments (mocapd/eval/mtw.py), as JSON.

Usage: ``.venv/bin/python tools/measure_mtw_noise.py [--data-root ../shared/data]``
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from mocapd.eval.data import default_data_root
from mocapd.eval.mtw import measure_all

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--data-root", type=Path, default=None)
    args = ap.parse_args()
    root = args.data_root or default_data_root()
    print(json.dumps(measure_all(root / "imu" / "opensense_mtw"), indent=2))
