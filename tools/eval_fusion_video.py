#!/usr/bin/env python3
"""Held-out-view reprojection error of the learned fusion and of the LM solver on the Pose2Sim demo footage.

Usage::

    .venv/bin/python tools/eval_fusion_video.py [--model DIR] [--demo Demo_SinglePerson] [--out results/fusion-video]

Takes the detections ``mocapd eval video`` makes of the demo (cached in ~/.cache/mocapd/eval-video/: the same file),
then mocapd.eval.fusion_video's comparison; prints the JSON and writes ``video.json`` and ``video.md``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from mocapd.eval import fusion_video
from mocapd.io.prior import load_default_prior
from mocapd.pipeline.fusion import FusionModels
from mocapd.service.config import load_config

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--model",
        type=Path,
        default=None,
        help="networks folder (default: ~/.cache/mocapd/fusion, from tools/train_fusion.py)",
    )
    ap.add_argument("--demo", default="Demo_SinglePerson", choices=("Demo_SinglePerson", "Demo_MultiPerson"))
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--out", type=Path, default=Path("results/fusion-video"))
    args = ap.parse_args()
    cfg = load_config()
    models = FusionModels(args.model)
    inputs = fusion_video.video_inputs(cfg.detector.options(), args.demo, args.frames, models.grid.scale)
    res = fusion_video.run(models, load_default_prior(), cfg.solver.cost, inputs, cfg.fusion.weight)
    fusion_video.save(res, args.out, args.demo)
    print(json.dumps(res["pooled"], indent=2))
