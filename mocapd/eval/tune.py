"""Re-tuning the cost weights on the DEVELOPMENT split only (never on evaluation clips).

A small grid over the weights the evaluation showed to matter (λ_A, λ_R, λ_P) is scored on the development
sequences for the two headline configurations (8 cameras + 13 IMUs and 4 cameras + 6 IMUs). The score is the
sum over both configurations of the global mean joint error (mm) plus 5 mm per degree of mean orientation error,
so neither accuracy is bought with the other.
"""

from __future__ import annotations

import itertools
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from mocapd.core.terms import CostOptions
from mocapd.eval.harness import RunConfig, solver_errors
from mocapd.eval.runner import EvalOptions, _head, prepare
from mocapd.io.prior import load_default_prior

GRID: dict[str, tuple[float, ...]] = {
    "lambda_acceleration": (1e-3, 1e-4, 1e-5, 0.0),
    "lambda_orientation": (1.0, 10.0, 100.0),
    "lambda_position": (1e-3,),
}
MM_PER_DEG = 5.0


def tune(data_root: Path | None, frames: int = 120, grid: dict[str, tuple[float, ...]] | None = None) -> dict[str, Any]:
    g = GRID if grid is None else grid
    opts = EvalOptions(split="development", progress=False)
    seqs = [_head(s, frames) for s in prepare(opts, data_root)]
    prior = load_default_prior()
    rows = []
    keys = list(g)
    for values in itertools.product(*(g[k] for k in keys)):
        w = dict(zip(keys, values, strict=True))
        cost = CostOptions()
        upd: dict[str, Any] = {k: v for k, v in w.items() if v > 0}
        for k, v in w.items():
            if v == 0.0:
                upd[f"use_{k.removeprefix('lambda_')}"] = False
        cost = replace(cost, **upd)
        t0 = time.perf_counter()
        score = 0.0
        row: dict[str, Any] = {"weights": w}
        for label, cfg in (("8c13i", RunConfig(8, 13)), ("4c6i", RunConfig(4, 6))):
            tab = solver_errors(seqs, cfg, prior, cost, lambda n: None).table()
            row[label] = {"global_mm": tab["global_mm"]["mean"], "orientation_deg": tab["orientation_deg"]["mean"]}
            score += tab["global_mm"]["mean"] + MM_PER_DEG * tab["orientation_deg"]["mean"]
        row["score"] = round(score, 1)
        row["seconds"] = round(time.perf_counter() - t0, 1)
        rows.append(row)
        print(row, flush=True)
    best = min(rows, key=lambda r: r["score"])
    return {
        "split": "development",
        "sequences": len(seqs),
        "frames_per_sequence": frames,
        "frames": int(sum(s.clip.n_frames for s in seqs)),
        "score": f"sum over 8c13i and 4c6i of global mean mm + {MM_PER_DEG} × orientation mean deg",
        "grid": rows,
        "best": best,
        "std_of_scores": float(np.std([r["score"] for r in rows])),
    }
