"""``mocapd bench``: the benchmarks a user runs to judge a machine (issue 46: one home for them).

Every verb prints one JSON object on stdout whose ``"machine"`` entry names the CPU (model, the instruction-set
flags that matter, cores) and one line for a person on stderr (:func:`mocapd.service.bench.machine.emit`).
``bench latency`` (the daemon end to end) is registered with the daemon's commands
(:mod:`mocapd.service.cli.daemon`). Developer benchmarks (policy comparisons, loss under artificial load, the
lifecycle table...) stay in ``tools/``.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any


def _cmd_solver(args: argparse.Namespace) -> int:
    from mocapd.service.bench import solver as bench_solver
    from mocapd.service.bench.machine import emit

    r = bench_solver.run(frames=args.frames, scipy_frames=args.scipy_frames, seed=args.seed)
    a, c = r["a_8cam_13imu"]["median_ms"], r["c_0cam_13imu"]["median_ms"]
    emit(r, f"bench solver: {a} ms per frame (8 cameras + 13 IMUs), {c} ms (13 IMUs alone), "
            f"{r['speedup_vs_scipy_same_frames']}x scipy")  # fmt: skip
    return 0


def _cmd_sorting(args: argparse.Namespace) -> int:
    from mocapd.eval import tracking as eval_tracking
    from mocapd.service.bench.machine import emit

    r = eval_tracking.bench_sorting(frames=args.frames)
    worst = max(r.items(), key=lambda kv: kv[1]["median_ms"])
    emit(r, f"bench sorting: {worst[1]['median_ms']} ms per frame at most ({worst[0]})")
    return 0


def _cmd_detector(args: argparse.Namespace) -> int:
    from mocapd.service.bench import detector
    from mocapd.service.bench.machine import emit

    r = detector.run(args)
    emit(r, f"bench detector: {r['naive_camera_frames_per_s_median']} camera frames/s whole, "
            f"{r['packed_camera_frames_per_s_median']} packed ({r['speedup_median']}x; {r['image_size'][0]}x"
            f"{r['image_size'][1]} frames, {args.threads} threads)")  # fmt: skip
    return 0


def _cmd_streams(args: argparse.Namespace) -> int:
    from mocapd.service.bench import streams
    from mocapd.service.bench.machine import emit

    r = streams.run(args.subjects, args.rate, args.frames)
    emit(r, f"bench streams: MVN + VMC publish {100 * r['budget_fraction']:.2f} % of a {args.rate:g} Hz frame for "
            f"{args.subjects} subjects, Rokoko {100 * r['rokoko']['budget_fraction']:.2f} %")  # fmt: skip
    return 0


def _cmd_record(args: argparse.Namespace) -> int:
    from mocapd.service.bench import record
    from mocapd.service.bench.machine import emit

    r = record.run(seconds=args.seconds, repeats=args.repeats, resolve_seconds=args.resolve_seconds)
    pose = r["realtime_median_run"]["call_us"]["pose"]["median"]
    written, resolved = r["throughput"]["records_per_s"], r["resolve"]["frames_per_s"]
    emit(r, f"bench record: {pose} us per published frame on the tick loop, writer {written:.0f} records/s, "
            f"resolve {resolved} frames/s")  # fmt: skip
    return 0


def _cmd_capture(args: argparse.Namespace) -> int:
    from mocapd.errors import MocapdError
    from mocapd.service.bench import capture
    from mocapd.service.bench.machine import emit

    try:
        r = capture.run(args)
    except MocapdError as exc:  # no Aravis, no unshare, a video that does not decode: the cause in one line
        print(f"error: {exc}", file=sys.stderr)
        return 2
    emit(r, capture.summary_line(r))
    return 0


def detector_arguments(ap: argparse.ArgumentParser) -> None:
    """The options of ``mocapd bench detector`` (the packing ones default to the shipped ``[detector.packing]``)."""
    from mocapd.pipeline.detector_config import PackingConfig

    ap.add_argument("--demo", default="Demo_MultiPerson", help="Demo_SinglePerson or Demo_MultiPerson")
    ap.add_argument("--pairs", type=int, default=30, help="frame pairs to time (each: 8 camera frames)")
    ap.add_argument("--threads", type=int, default=2, help="onnxruntime intra-op threads")
    defaults = PackingConfig()
    ap.add_argument("--margin", type=float, default=defaults.roi_margin, help="ROI margin (fraction of box side)")
    ap.add_argument("--gap", type=int, default=defaults.gap, help="canvas pixels between tiles")
    ap.add_argument("--min-scale-ratio", type=float, default=1.0, help="packed tile scale / naive scale, minimum")
    ap.add_argument("--max-scale-ratio", type=float, default=1.0, help="packed tile scale / naive scale, maximum")
    ap.add_argument("--align-stride", type=int, default=32, help="0: common-scale packing; >0: aligned tiles")
    ap.add_argument(
        "--max-tile-height", type=float, default=defaults.max_tile_height, help="tallest tile / canvas height (0: off)"
    )
    ap.add_argument("--refresh-every", type=int, default=defaults.refresh_every, help="whole-frame refresh period")
    ap.add_argument("--refresh-scale-ratio", type=float, default=defaults.refresh_scale_ratio, help="refresh scale")
    ap.add_argument("--canvas", default="", help="packed canvas size WxH (default: the model's 640x640)")


def register(subparsers: Any) -> argparse._SubParsersAction[argparse.ArgumentParser]:
    """Add the ``bench`` group and its verbs (but ``latency``) to the CLI; returns the group's subparsers."""
    bench = subparsers.add_parser("bench", help="benchmarks that print JSON naming the CPU, and a summary line")
    sub: argparse._SubParsersAction[argparse.ArgumentParser] = bench.add_subparsers(
        dest="bench", metavar="BENCH", required=True
    )
    solver = sub.add_parser("solver", help="per-frame solver cost of the standard configurations")
    solver.add_argument("--frames", type=int, default=600, help="frames per configuration (default 600)")
    solver.add_argument("--scipy-frames", type=int, default=30, help="frames for the scipy baseline (default 30)")
    solver.add_argument("--seed", type=int, default=0)
    solver.set_defaults(func=_cmd_solver)
    sorting = sub.add_parser("sorting", help="multi-person detection sorting time per frame")
    sorting.add_argument("--frames", type=int, default=60)
    sorting.set_defaults(func=_cmd_sorting)
    det = sub.add_parser("detector", help="pose detector camera frames/s, whole frames against ROI packing, on the "
                         "Pose2Sim demo videos")  # fmt: skip
    detector_arguments(det)
    det.set_defaults(func=_cmd_detector)
    streams = sub.add_parser("streams", help="serialisation and send cost of the MVN, VMC and Rokoko UDP streams")
    streams.add_argument("--subjects", type=int, default=4)
    streams.add_argument("--rate", type=float, default=60.0, help="output rate, Hz (default 60)")
    streams.add_argument("--frames", type=int, default=3000)
    streams.set_defaults(func=_cmd_streams)
    record = sub.add_parser("record", help="session recorder: cost on the tick loop, write rate, resolve speed")
    record.add_argument("--seconds", type=float, default=10.0, help="session length (default 10)")
    record.add_argument("--repeats", type=int, default=3)
    record.add_argument("--resolve-seconds", type=float, default=4.0, help="session length resolved (default 4)")
    record.set_defaults(func=_cmd_record)
    cap = sub.add_parser("capture", help="GigE Vision capture cost: 4 fake cameras serving the Pose2Sim demo videos on "
                         "loopback, in a private network namespace (needs Aravis and unshare)")  # fmt: skip
    from mocapd.service.bench.capture import arguments as capture_arguments

    capture_arguments(cap)
    cap.set_defaults(func=_cmd_capture)
    return sub
