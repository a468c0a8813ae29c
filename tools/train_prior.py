#!/usr/bin/env python3
"""Train the shipped default pose prior from the CMU clips of the ``prior`` split (see mocapd/eval/train_prior.py).

Usage: ``.venv/bin/python tools/train_prior.py [--data-root ../shared/data] [--out mocapd/data/prior_cmu.npz]``
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from mocapd.eval.train_prior import train

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--data-root", type=Path, default=None)
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "mocapd/data/prior_cmu.npz")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    print(json.dumps(train(args.data_root, args.out, args.seed), indent=2))
