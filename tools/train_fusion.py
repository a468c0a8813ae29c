#!/usr/bin/env python3
"""Train the learned fusion (issue 30, seed 001) through the simulator and export it to ONNX.

Usage::

    nice -n 10 .venv/bin/python tools/train_fusion.py [--config recipe.toml] [--seed 0] [--out DIR]
        [--ablation] [--tiny] [--work DIR] [--data-root ../shared/data]

Needs the ``[train]`` extra (PyTorch, CPU build: ``pip install -e '.[train]'``). Writes ``fusion_cnn.onnx``,
``fusion_temporal.onnx``, ``fusion_raw_imu.onnx`` and the provenance ``fusion.json`` into ``--out`` (default:
``~/.cache/mocapd/fusion``, where ``[fusion] model = "default"`` reads them; the weights are never committed,
``mocapd/data/fusion.json`` records the reference run);
``--ablation`` also trains the matte-only and joint-channel-only PVH networks of Table 6
(``fusion_cnn_matte.onnx``, ``fusion_cnn_joints.onnx``). Progress goes to stderr, the provenance to stdout.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path

from mocapd.eval.fusion_train import FusionRecipe, train
from mocapd.pipeline.fusion import default_model_dir

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", type=Path, default=None, help="recipe TOML (keys: FusionRecipe's fields)")
    ap.add_argument("--seed", type=int, default=None)
    ap.add_argument("--out", type=Path, default=default_model_dir(), help="networks folder (default: the cache's)")
    ap.add_argument("--data-root", type=Path, default=None)
    ap.add_argument("--ablation", action="store_true", help="also the single-channel PVH networks of Table 6")
    ap.add_argument("--tiny", action="store_true", help="the CI recipe (seconds; checks the pipeline only)")
    ap.add_argument(
        "--work",
        type=Path,
        default=None,
        help="keep the PVH networks here as they finish, and reuse them for the same recipe (resume)",
    )
    args = ap.parse_args()
    recipe = FusionRecipe.tiny() if args.tiny else FusionRecipe()
    if args.config is not None:
        recipe = FusionRecipe.from_toml(args.config)
    if args.seed is not None:
        recipe = replace(recipe, seed=args.seed)
    prov = train(recipe, args.out, args.data_root, ablation=args.ablation, work_dir=args.work)
    print(json.dumps({k: prov[k] for k in ("validation_mean_mm", "wall_s", "files")}, indent=2))
