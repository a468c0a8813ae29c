#!/usr/bin/env python3
"""Grid-search cost weights on the development split (mocapd/eval/tune.py); prints and writes JSON.

Usage: ``.venv/bin/python tools/tune_weights.py [--frames 120] [--out results/tuning/development.json]``
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from mocapd.eval.tune import tune

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--data-root", type=Path, default=None)
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--out", type=Path, default=Path("results/tuning/development.json"))
    args = ap.parse_args()
    res = tune(args.data_root, args.frames)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(res, indent=2) + "\n", encoding="utf-8")
    print(json.dumps(res["best"], indent=2))
