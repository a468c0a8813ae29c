#!/usr/bin/env python3
"""Choose ``[fusion] weight`` (λ_J of the learned joints in the LM solve) on the development split only.

For each λ_J, the accuracy harness's ``both`` solve (LM solver + learned joints as E_J on the learned frames) on
the development split's sequences (first ``--frames`` of each), for a few camera × IMU configurations, under
the realistic noise and under detector failures; the LM solver alone beside it. Prints JSON.

    nice -n 10 .venv/bin/python tools/tune_fusion_weight.py [--model DIR] [--frames 120] [--weights 1 10 30 100]
"""

from __future__ import annotations

import argparse
import json
import os
import time
import zlib
from dataclasses import replace
from pathlib import Path
from typing import Any

from mocapd.eval.data import load_clip, load_splits
from mocapd.eval.fusion_eval import SCENARIOS, FusionEvalOptions, evaluate_sequences
from mocapd.eval.harness import make_sequence, windows
from mocapd.io.prior import load_default_prior
from mocapd.pipeline.fusion import FusionModels
from mocapd.service.config import load_config


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", type=Path, default=None)
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--weights", type=float, nargs="+", default=[1.0, 10.0, 30.0, 100.0])
    ap.add_argument("--scenarios", nargs="+", default=["realistic", "detector failures"])
    args = ap.parse_args()
    t0 = time.perf_counter()
    models = FusionModels(args.model)
    prior = load_default_prior()
    cost = load_config().solver.cost
    clips = []
    for f in load_splits()["development"]:
        for w in windows(load_clip(f)):
            n = min(args.frames, w.n_frames)
            clips.append(
                replace(w, theta=w.theta[:n], positions=w.positions[:n], rotations=w.rotations[:n],
                        source_positions=w.source_positions[:n])
            )  # fmt: skip
    configs = ((8, 13), (4, 6), (4, 0))
    out: dict[str, Any] = {"frames_per_sequence": args.frames, "sequences": len(clips), "results": {}}
    for name in args.scenarios:
        det, imu, _ = SCENARIOS[name]
        seqs = [make_sequence(c, zlib.crc32(f"tune:{name}:{c.name}".encode()), det, imu) for c in clips]
        for lam in args.weights:
            opts = FusionEvalOptions(lambda_learned=lam, scenarios=False)
            res = evaluate_sequences(seqs, opts, models, prior, cost, configs=configs, network_rows=False)
            out["results"].setdefault(name, {})[str(lam)] = {
                cfg: {row: {"global_mm": r["global_mm"]["mean"], "orientation_deg": r["orientation_deg"]["mean"]}
                      for row, r in rows.items()}
                for cfg, rows in res.items()
            }  # fmt: skip
            print(json.dumps({name: {str(lam): out["results"][name][str(lam)]}}), flush=True)
    out["wall_s"] = round(time.perf_counter() - t0, 1)
    out["loadavg"] = os.getloadavg()
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
