"""``mocapd run``, ``mocapd demo``, ``mocapd check-config`` and ``mocapd bench latency``."""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import sys
from pathlib import Path
from typing import Any

from mocapd.errors import ConfigError, MocapdError
from mocapd.service.config import DEFAULT_CONFIG, Config, load_config
from mocapd.service.outputs.udp import build_udp_sinks


def _subcommand_group(subparsers: Any, name: str) -> Any:
    """The sub-subparsers of an existing command group (e.g. ``bench``)."""
    parser = subparsers.choices[name]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return action
    raise LookupError(name)  # a programming error: the group must exist before register() runs


def _load(path: Path | None, http_port: int | None = None) -> Config:
    cfg = load_config(path)
    if http_port is not None:
        cfg = cfg.model_copy(update={"daemon": cfg.daemon.model_copy(update={"http_port": http_port})})
    return cfg


def cmd_check_config(args: argparse.Namespace) -> int:
    path = args.path if args.path is not None else DEFAULT_CONFIG
    try:
        cfg = load_config(path)
        cfg.daemon.scheduler_options([f"cam{i}" for i in range(cfg.daemon.synthetic.cameras)])
    except ConfigError as exc:  # a file-level message names the file already
        print(f"{path}: error: {str(exc).removeprefix(f'{path}: ')}", file=sys.stderr)
        return 2
    d = cfg.daemon
    print(
        f"{path}: ok (rig {d.rig}, output {d.output_rate_hz:g} Hz, latency {1e3 * d.latency_s:g} ms, "
        f"{len(cfg.imu.ports)} serial IMU port(s), status http://{d.http_host}:{d.http_port}/status)"
    )
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from mocapd.service.demo import synthetic as demo_synthetic

    try:
        cfg = _load(args.config, args.http_port)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    try:
        if not args.synthetic:
            from mocapd.service.demo import cameras as demo_cameras
            from mocapd.service.demo.camera_rig import CameraDemoOptions

            opts = CameraDemoOptions(scale=args.scale, latency_s=args.latency, packed=args.packed)
            return demo_cameras.run(args.config, cfg, None if args.seconds <= 0 else args.seconds, opts=opts,
                                    record=args.record)  # fmt: skip
        return demo_synthetic.run(cfg, None if args.seconds <= 0 else args.seconds, record=args.record)
    except MocapdError as exc:  # found when the sinks start: a stream's port in use, a session that exists
        print(f"error: {exc}", file=sys.stderr)
        return 2


def cmd_run(args: argparse.Namespace) -> int:
    from mocapd.io.prior import resolve_prior
    from mocapd.service.daemon import Daemon, Rig
    from mocapd.service.outputs.recorder import attach_recorder, synthetic_extra
    from mocapd.service.outputs.websocket import build_websocket_sinks
    from mocapd.service.suits import load_suits
    from mocapd.sim.world import SyntheticKeypointSource, SyntheticWorld

    try:
        cfg = _load(args.config, args.http_port)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    syn = cfg.daemon.synthetic
    world = SyntheticWorld(syn.cameras, syn.people, 0, seed=syn.seed, motion=syn.motion)
    import time

    epoch = time.monotonic_ns()
    sources = [
        SyntheticKeypointSource(world, c, epoch_ns=epoch, rate_hz=syn.camera_rate_hz, delay_s=syn.detection_delay_s,
                                noise_px=syn.noise_px, seed=syn.seed)
        for c in range(len(world.cameras))
    ]  # fmt: skip
    try:
        suits = load_suits(cfg.imu, world.skeleton)  # the IMU suits calibrated with `mocapd calibrate imu`
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    rig = Rig(world.cameras, list(sources), world.skeleton, world.targets, resolve_prior(cfg.solver.prior), suits)
    daemon = Daemon(cfg, rig, status_line=(lambda s: print(s, flush=True)) if args.verbose else None)
    daemon.sinks.extend(build_udp_sinks(cfg, daemon))
    daemon.sinks.extend(build_websocket_sinks(cfg, daemon))
    attach_recorder(cfg, daemon, args.record, extra={"synthetic": synthetic_extra(syn, epoch, suits=0)})
    print(f"mocapd run: status http://{cfg.daemon.http_host}:{cfg.daemon.http_port}/status", flush=True)
    if cfg.websocket.enabled:
        print(f"mocapd run: viewer http://{cfg.websocket.host}:{cfg.websocket.port}/ (stream ws://same)", flush=True)
    try:
        return asyncio.run(daemon.run())
    except MocapdError as exc:  # found when the sinks start: a stream's port in use, a session that exists
        print(f"error: {exc}", file=sys.stderr)
        return 2


def cmd_bench_latency(args: argparse.Namespace) -> int:
    from mocapd.service.bench import latency as bench_latency

    if args.rig == "cameras":
        from mocapd.service.bench import cameras as bench_cameras
        from mocapd.service.demo.camera_rig import CameraDemoOptions

        opts = CameraDemoOptions(scale=args.scale, latency_s=args.latency, packed=args.packed)
        return bench_cameras.run(args.seconds, opts)
    print(json.dumps(bench_latency.run(seconds=args.seconds, cameras=args.cameras, people=args.people), indent=2))
    return 0


_RECORD_HELP = "record this run as a session into this new directory (docs/sessions.md)"


def register(subparsers: Any) -> None:
    """Add run, demo, check-config and ``bench latency`` to the CLI."""
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    run = subparsers.add_parser("run", help="run the daemon (config.toml; rig 'synthetic' until the detector lands)")
    run.add_argument("--config", type=Path, default=None, help="config file (default: the shipped config.toml)")
    run.add_argument("--http-port", type=int, default=None, help="override daemon.http_port (0 = any free port)")
    run.add_argument("--record", type=Path, default=None, help=_RECORD_HELP)
    run.add_argument("--verbose", action="store_true", help="print a status line per second")
    run.set_defaults(func=cmd_run)

    demo = subparsers.add_parser("demo", help="the full daemon on an embedded rig, no hardware needed")
    demo.add_argument(
        "--synthetic", action="store_true", help="synthetic motion: simulated keypoints + Xsens IMUs on ptys"
    )
    demo.add_argument("--seconds", type=float, default=0.0, help="stop after this long (default: until Ctrl-C)")
    demo.add_argument("--config", type=Path, default=None, help="config file (default: the shipped config.toml)")
    demo.add_argument("--http-port", type=int, default=None, help="override daemon.http_port (0 = any free port)")
    demo.add_argument("--record", type=Path, default=None, help=_RECORD_HELP)
    demo.add_argument("--scale", type=float, default=0.5, help="camera rig: image size / 1088x1920 (default 0.5)")
    demo.add_argument("--latency", type=float, default=1.0, help="camera rig: fixed latency, s (default 1.0)")
    demo.add_argument("--packed", action="store_true", help="camera rig: all cameras' ROIs packed per detector pass")
    demo.set_defaults(func=cmd_demo)

    check = subparsers.add_parser("check-config", help="validate a config file and say what is wrong")
    check.add_argument("path", nargs="?", type=Path, default=None, help="config file (default: the shipped one)")
    check.set_defaults(func=cmd_check_config)

    bench = _subcommand_group(subparsers, "bench")
    lat = bench.add_parser("latency", help="daemon end-to-end latency, output rate, CPU and memory (synthetic rig)")
    lat.add_argument("--seconds", type=float, default=60.0, help="run length (default 60)")
    lat.add_argument("--cameras", type=int, default=4)
    lat.add_argument("--people", type=int, default=2)
    lat.add_argument("--rig", choices=["synthetic", "cameras"], default="synthetic",
                     help="cameras: the camera demo (fake GigE cameras, real detector) in a private netns")  # fmt: skip
    lat.add_argument("--scale", type=float, default=0.5, help="cameras: image size / 1088x1920")
    lat.add_argument("--latency", type=float, default=1.0, help="cameras: fixed latency, s (default 1.0)")
    lat.add_argument("--packed", action="store_true", help="cameras: all cameras' ROIs packed per detector pass")
    lat.set_defaults(func=cmd_bench_latency)
