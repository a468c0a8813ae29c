"""``mocapd eval accuracy``, ``mocapd eval video`` and ``mocapd eval keypoints``: the accuracy harnesses from the
command line (registered by ``mocapd.service.cli``)."""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

from mocapd.service.cli.numbers import number


def register(sub: Any) -> None:
    """Add ``accuracy``, ``video`` and ``keypoints`` to the subparsers of ``mocapd eval``."""
    p = sub.add_parser("accuracy", help="accuracy on real recorded motion vs baselines (docs/accuracy.md)")
    p.add_argument("--quick", action="store_true", help="CI smoke run: a few short sequences (< 2 minutes)")
    p.add_argument("--split", default=None, help="evaluation (default), development or quick")
    p.add_argument("--out", type=Path, default=Path("results/accuracy"), help="results directory")
    p.add_argument("--data-root", type=Path, default=None, help="shared data root (default ../shared/data)")
    p.add_argument("--config", type=Path, default=None, help="config.toml whose [solver] weights to use")
    p.add_argument("--prior", default=None, help='"default", "none" or a .npz path (default: the config\'s)')
    p.add_argument("--max-frames", type=int, default=None, help="cap per sequence for the main table")
    p.add_argument("--sweep-frames", type=int, default=None, help="cap per sequence for sweep/ablation")
    p.add_argument("--clean", action="store_true", help="clean detections and IMUs (debugging)")
    p.add_argument("--fusion", action="store_true", help="also seed 001's Table 6: the learned fusion's rows")
    p.add_argument(
        "--only-fusion", action="store_true", help="the learned fusion's rows alone (docs/learned-fusion.md)"
    )
    p.add_argument(
        "--fusion-model",
        type=Path,
        default=None,
        help="networks folder (default: ~/.cache/mocapd/fusion, from tools/train_fusion.py)",
    )
    p.add_argument("--fusion-frames", type=int, default=None, help="cap per sequence for the learned fusion's table")
    p.add_argument("--no-scenarios", action="store_true", help="skip the learned fusion's noise scenarios")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-progress", action="store_true", help="no progress bar (it is drawn only on a terminal)")
    p.set_defaults(func=_run)
    v = sub.add_parser("video", help="accuracy on real multi-view footage beside Pose2Sim (docs/accuracy-video.md)")
    v.add_argument("--take", action="append", default=None, metavar="NAME",
                   help="Demo_SinglePerson or Demo_MultiPerson (repeatable; default: both)")  # fmt: skip
    v.add_argument("--max-frames", type=number(1, 1e9, integer=True), default=None,
                   help="only the first frames of each take (CI)")  # fmt: skip
    v.add_argument("--config", type=Path, default=None, help="mocapd config to run (default: the shipped one)")
    v.add_argument("--out", type=Path, default=Path("results/accuracy-video"), help="results directory")
    v.add_argument("--precision", default="fp32", choices=("fp32", "int8", "bf16"),
                   help="detector precision of the shared detections (default fp32)")  # fmt: skip
    v.add_argument("--no-pose2sim", action="store_true", help="leave Pose2Sim out (it is an optional install)")
    v.add_argument("--images", type=number(0, 1000, integer=True), default=3,
                   help="frames per camera drawn (default 3, 0: none)")  # fmt: skip
    v.add_argument("--no-cache", action="store_true", help="detect again even when the detections are cached")
    v.add_argument("--no-progress", action="store_true", help="no progress bar (it is drawn only on a terminal)")
    v.add_argument("--calibration", type=Path, default=None, metavar="FILE",
                   help="score with this calibration's cameras instead of the demos' own (e.g. one from `mocapd "
                   "calibrate cameras --from-people`; needs --no-pose2sim) and its time_offset_s")  # fmt: skip
    v.set_defaults(func=_run_video)
    k = sub.add_parser("keypoints", help="multi-person benchmark through import keypoints + resolve (docs/accuracy.md)")
    k.add_argument("--people", type=int, default=3, help="people in the scene, 2 to 4 (default 3)")
    k.add_argument("--seconds", type=float, default=10.0, help="length of the take (default 10)")
    k.add_argument("--seed", type=int, default=0, help="seed of the detector's noise (default 0)")
    k.add_argument(
        "--out",
        type=Path,
        default=Path("results/keypoints"),
        help="results directory: input/, session/, keypoints.json, keypoints.md (must not hold a session)",
    )
    k.add_argument("--data-root", type=Path, default=None, help="shared data root (default ../shared/data)")
    k.add_argument("--no-pose2sim", action="store_true", help="leave Pose2Sim out (it is an optional install)")
    k.set_defaults(func=_run_keypoints)


def _run_keypoints(args: argparse.Namespace) -> int:
    from mocapd.errors import MocapdError
    from mocapd.service.keypoint_eval import run_keypoint_eval

    try:
        report = run_keypoint_eval(args.out, args.people, args.seconds, args.seed, data_root=args.data_root,
                                   pose2sim=not args.no_pose2sim)  # fmt: skip
    except MocapdError as exc:  # a bad option, the data root missing, an OUT that already holds a session
        print(f"error: {exc}", file=sys.stderr)
        return 2
    summary = {name: {key: s[key] for key in ("pcp_average", "mpjpe_mm", "misses", "misses_after_first_0.2s",
                                              "identity_switches", "tracks", "false_positive_tracks")}
               for name, s in report["systems"].items()}  # fmt: skip
    print(json.dumps({"out": str(args.out), "pose2sim": report["benchmark"]["pose2sim"], "systems": summary,
                      "commands": report["commands"]}, indent=2))  # fmt: skip
    return 0


def _run_video(args: argparse.Namespace) -> int:
    from mocapd.errors import ConfigError, InputError, MocapdError
    from mocapd.io.pose2sim_demo import DEMOS
    from mocapd.service.video_eval import VideoEvalOptions, run_video_eval

    opts = VideoEvalOptions(
        takes=tuple(args.take) if args.take else DEMOS, max_frames=args.max_frames, config=args.config,
        precision=args.precision, pose2sim=not args.no_pose2sim, images=args.images, use_cache=not args.no_cache,
        progress=not args.no_progress, calibration=args.calibration,
    )  # fmt: skip
    try:
        res = run_video_eval(opts, args.out, say=lambda line: print(f"mocapd eval video: {line}", file=sys.stderr))
    except (ConfigError, InputError) as exc:  # an unknown take, a config that is none: the arguments' fault
        print(f"mocapd eval video: {exc}", file=sys.stderr)
        return 2
    except MocapdError as exc:  # the demo data or a model not there, Pose2Sim failing
        print(f"mocapd eval video: {exc}", file=sys.stderr)
        return 1
    summary = {name: {"targets": t["targets"], "held_out_common_median_px": {
        s: v["held_out"]["common"]["all"]["median"] for s, v in t["systems"].items()}}
        for name, t in res["takes"].items()}  # fmt: skip
    print(json.dumps({"out": str(args.out), "takes": summary, "setup": res["setup"]}, indent=2, default=str))
    return 0


def _run(args: argparse.Namespace) -> int:
    from mocapd.eval.runner import EvalOptions, run_eval
    from mocapd.eval.simulate import DetectionNoise, ImuNoise
    from mocapd.io import lifecycle
    from mocapd.service.config import load_config

    opts = EvalOptions.quick() if args.quick else EvalOptions()
    cfg = load_config(args.config)
    opts = replace(
        opts,
        cost=cfg.solver.cost,
        cost_label=f"[solver] of {args.config or 'the shipped config.toml'}",
        prior=args.prior or cfg.solver.prior,
        seed=args.seed,
        progress=not args.no_progress,
    )
    if args.split:
        opts = replace(opts, split=args.split)
    if args.max_frames is not None:
        opts = replace(opts, max_frames=args.max_frames)
    if args.sweep_frames is not None:
        opts = replace(opts, sweep_frames=args.sweep_frames)
    if args.clean:
        opts = replace(opts, detections=DetectionNoise.clean(), imus=ImuNoise.clean())
    # A stop signal raises StopRequested in the experiments: the results directory is written only at the end.
    lifecycle.enter_phase("evaluating (results are written at the end)")
    if args.fusion or args.only_fusion:
        from mocapd.errors import ModelError
        from mocapd.eval.fusion_eval import FusionEvalOptions
        from mocapd.pipeline.fusion import FusionModels

        try:  # before the hours of evaluation: the networks are trained by the user, not shipped
            FusionModels(args.fusion_model)
        except ModelError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        fo = FusionEvalOptions(
            model=args.fusion_model,
            max_frames=args.fusion_frames,
            scenarios=not args.no_scenarios,
            seed=args.seed,
            lambda_learned=cfg.fusion.weight,
        )
        if args.quick:
            fo = replace(fo, scenario_frames=60, scenario_configs=((8, 13), (4, 6)))
        opts = replace(opts, fusion=fo, only_fusion=args.only_fusion)
    res = run_eval(opts, args.out, args.data_root)
    summary = {"targets": res.get("targets"), "setup": res["setup"]}
    print(json.dumps({"out": str(args.out), **summary}, indent=2))
    return 0
