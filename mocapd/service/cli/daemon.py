"""``mocapd run``, ``mocapd detect-host``, ``mocapd demo``, ``mocapd check-config`` and ``mocapd bench latency``.

All of them build the daemon through :mod:`mocapd.service.assembly`: ``run`` from the user's config, ``demo``
and the benchmark from a generated one.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from mocapd.errors import ConfigError, MocapdError
from mocapd.io import cpu_budget, lifecycle
from mocapd.service.cli.numbers import number

# The parser is built for every command: the config schema (pydantic, and through its defaults the detector's and
# the rig's modules: NumPy, SciPy, NumBa, onnxruntime, OpenCV) is imported by the commands that read a config, not
# by `mocapd --help`.
if TYPE_CHECKING:
    from mocapd.service import assembly
    from mocapd.service.config import Config
    from mocapd.service.rig_plan import RigPlan


def _subcommand_group(subparsers: Any, name: str) -> Any:
    """The sub-subparsers of an existing command group (e.g. ``bench``)."""
    parser = subparsers.choices[name]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return action
    raise LookupError(name)  # a programming error: the group must exist before register() runs


def _load(path: Path | None, http_port: int | None = None) -> Config:
    from mocapd.service.config import load_config

    cfg = load_config(path)
    if http_port is not None:
        cfg = cfg.model_copy(update={"daemon": cfg.daemon.model_copy(update={"http_port": http_port})})
    return cfg


def check(cfg: Config) -> RigPlan:
    """Everything ``mocapd run`` checks before it opens a device: the rig against its calibration and files, and
    the IMU suits' calibration files."""
    from mocapd.io.tls_files import check_tls_files
    from mocapd.service.config.cameras import AravisCamera, ImagesCamera, UvcCamera, VideoCamera
    from mocapd.service.rig_plan import plan_rig

    plan = plan_rig(cfg)
    check_tls_files(cfg.zenoh.tls_root_ca, cfg.zenoh.tls_cert, cfg.zenoh.tls_key)  # Zenoh would fail in silence
    if len(cfg.cameras) == 1:  # run's detection sorting refused it only once the models were loaded (issue 45)
        raise ConfigError(
            f"cameras: one camera ({cfg.cameras[0].name}): detection sorting needs at least two cameras (it "
            "triangulates across views), or none (a rig of IMUs alone)"
        )
    if any(isinstance(c, (AravisCamera, UvcCamera, VideoCamera, ImagesCamera)) for c in cfg.cameras):  # detected
        _model_file(cfg.detector.model.path, "detector.model.path")
        _model_file(cfg.detector.packing.canvas_model_path, "detector.packing.canvas_model_path")
    if not plan.synthetic or cfg.imu.sources():  # a synthetic rig loads suits only for IMU inputs of its own
        _suits(cfg)
    return plan


def _model_file(path: str, key: str) -> None:
    """A model file the user named must be a regular file, as the detector will find (a FIFO, a device or a folder
    passed check-config, then `run` said "not found", issue 45). Empty: the default model, found by `run`."""
    import os
    import stat

    from mocapd.io.input_files import file_kind

    if not path:
        return
    try:
        mode = os.stat(path).st_mode
    except OSError as exc:
        raise ConfigError(f"{key} = {path!r}: {exc.strerror or exc}") from None
    if not stat.S_ISREG(mode):
        raise ConfigError(f"{key} = {path!r}: not a regular file ({file_kind(mode)}); give the ONNX model file")


def _suits(cfg: Config) -> list[Any]:
    from mocapd.service.rig_plan import rig_skeleton
    from mocapd.service.suits import load_suits

    return load_suits(cfg.imu, rig_skeleton(cfg))


def _latency_text(latency_s: float | str) -> str:
    return "auto" if isinstance(latency_s, str) else f"{1e3 * latency_s:g} ms"


def _rig_summary(cfg: Config) -> str:
    from mocapd.service.config.cameras import describe

    d = cfg.daemon
    if cfg.cameras:
        cams = "; ".join(f"{c.name} ({describe(c)})" for c in cfg.cameras)
        rig = f"{len(cfg.cameras)} camera(s): {cams}; {len(cfg.imu.ports)} serial IMU port(s)"
    else:
        persons = cfg.imu.persons
        whose = f" to {len(persons)} persons ({', '.join(persons)})" if persons else ""
        rig = (
            f"IMUs only (no cameras): {'; '.join(cfg.imu.sources())}; {len(cfg.imu.sensors)} sensor(s) assigned{whose}"
        )
    return (
        f"{rig}; output {d.output_rate_hz:g} Hz, latency {_latency_text(d.latency_s)}; "
        f"{_status_text(d.http_host, d.http_port)}"
    )


def _status_text(host: str, port: int) -> str:
    """Where /status will be: a port the config fixes, or (port 0) one the system picks, printed once bound."""
    if port == 0:
        return "status on a free port (printed when ready)"
    return f"status http://{host}:{port}/status"


def _imu_notes(cfg: Config, path: object) -> list[str]:
    """What an IMU-only rig still lacks before it streams a pose, each with the command that gives it."""
    if cfg.cameras:
        return []
    notes = []
    imu = cfg.imu
    # Which table assigns this rig's sensors: Xsens (and bridge) ids in [imu.assignment], SlimeVR's in its own.
    xsens = bool(imu.ports) or imu.awinda.experimental or imu.bridge.enabled
    slime_only = imu.slimevr.enabled and not xsens
    if not imu.sensors:
        table = "[imu.slimevr.assignment]" if slime_only else "[imu.assignment]"
        notes.append(
            f"{table} is empty: say which sensor sits on which bone (`mocapd devices` lists Xsens ids; "
            "SlimeVR trackers are listed under imu.slimevr.trackers in /status once `mocapd run` hears them)"
        )
    suits = _suits(cfg)
    if suits:
        names = ", ".join(f"{s.id} ({len(s.sensors)} sensors)" for s in suits)
        notes.append(f"suits calibrated in {imu.calibration_dir}/: {names}")
    if imu.persons:  # one suit per person's table: what each of them still lacks
        notes += _person_notes(cfg, path, {s.id: dict(s.calibration.bones) for s in suits}, slime_only)
    elif not suits:
        # An Xsens heading is the compass's: a facing heading off by δ turns every bone's frame by δ, and a knee then
        # bends sideways (90°) or backwards (180°). SlimeVR trackers are heading-reset at calibration instead.
        facing = "" if slime_only else " facing magnetic north"
        other = "" if slime_only else (
            " (facing elsewhere: that compass heading, or --facing-from SENSOR:AXIS with a sensor axis that points "
            "forward; a wrong heading bends the knees sideways or backwards)")  # fmt: skip
        notes.append(
            f"no suit is calibrated in {imu.calibration_dir}/ yet, so no pose is streamed: stand still in a T-pose"
            f"{facing} and run `mocapd calibrate imu --config {path} --person NAME --facing-heading 0`{other}"
        )
    return notes


def _person_notes(cfg: Config, path: object, calibrated: dict[str, dict[str, str]], slime_only: bool) -> list[str]:
    """Per-person tables (``[imu.assignment.alice]``): each person without a calibration, or whose calibration is of
    other sensors or bones than their table, with the command that calibrates them."""
    imu = cfg.imu
    facing = "" if slime_only else " facing magnetic north"
    notes = []
    for person, table in imu.persons.items():
        command = f"`mocapd calibrate imu --config {path} --person {person} --facing-heading 0`"
        bones = calibrated.get(person)
        if bones is None:
            notes.append(
                f"{person} ({len(table)} sensor{'s' * (len(table) != 1)} assigned) has no calibration in "
                f"{imu.calibration_dir}/ yet, so "
                f"no pose is streamed for them: stand {person} still in a T-pose{facing} and run {command}"
            )
        elif bones != table:
            differ = sorted(set(table.items()) ^ set(bones.items()))
            notes.append(
                f"{person}'s calibration in {imu.calibration_dir}/ is of other sensors than their table "
                f"({', '.join(f'{sid} {bone}' for sid, bone in differ[:4])}{', ...' if len(differ) > 4 else ''}): "
                f"calibrate them again with {command}"
            )
    return notes


def _subject_notes(cfg: Config) -> list[str]:
    """UDP streams that name a suit this rig has no calibration for (``suit:alice`` where the calibrated suit is
    ``bob``): the config is valid, the daemon runs, and that stream never gets the pose it was set up for."""
    u = cfg.udp
    named: list[tuple[str, str]] = []  # (where, identity)
    if u.vrchat.enabled and u.vrchat.subject:
        named.append(("[udp.vrchat] subject", u.vrchat.subject))
    for name, stream in (("mvn", u.mvn), ("vmc", u.vmc), ("rokoko", u.rokoko)):
        if stream.enabled:
            named += [(f"[udp.{name}] subjects", i) for i in stream.subjects or ()]
    if u.mvn.enabled:
        named += [("[udp.mvn] character_ids", i) for i in u.mvn.character_ids]
    if u.rokoko.enabled:
        named += [("[udp.rokoko] actor_names", i) for i in u.rokoko.actor_names]
    named = [(where, i) for where, i in named if i.startswith("suit:")]
    if not named:
        return []
    suits = {f"suit:{s.id}" for s in _suits(cfg)}
    have = ", ".join(sorted(suits)) or f"none in {cfg.imu.calibration_dir}/"
    return [
        f"{where} names {i!r}, which is not a calibrated suit of this rig (suits: {have}): that stream never gets "
        f"its pose; name one of them, or calibrate it (`mocapd calibrate imu --person {i.removeprefix('suit:')}`)"
        for where, i in dict.fromkeys(named) if i not in suits
    ]  # fmt: skip


def _print_config_error(path: object, exc: ConfigError) -> None:
    """One ``FILE: error: ...`` line per problem (a file-level message names the file already: not twice)."""
    for line in str(exc).removeprefix(f"{path}: ").splitlines():
        print(f"{path}: error: {line}", file=sys.stderr)


def cmd_check_config(args: argparse.Namespace) -> int:
    from mocapd.service.config import DEFAULT_CONFIG, load_config

    path = args.path if args.path is not None else DEFAULT_CONFIG
    try:
        cfg = load_config(path)
    except ConfigError as exc:
        _print_config_error(path, exc)
        return 2
    try:
        check(cfg)
        notes = _imu_notes(cfg, path) + _subject_notes(cfg)
    except ConfigError as exc:
        if args.path is None and not cfg.cameras:
            # The shipped file is valid and describes no rig on purpose: a rig is the user's to write.
            print(f"{path}: ok: the shipped config is valid and describes no rig (no [[cameras]]); write yours "
                  "(`mocapd devices` prints [[cameras]] tables for what is plugged in) and check it with "
                  "`mocapd check-config FILE`, or try `mocapd demo`")  # fmt: skip
            return 0
        _print_config_error(path, exc)
        return 2
    print(f"{path}: ok ({_rig_summary(cfg)})")
    for note in notes:
        print(f"{path}: note: {note}")
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    from mocapd.service.config import DEFAULT_CONFIG

    path = args.config if args.config is not None else DEFAULT_CONFIG
    try:
        cfg = _load(args.config, args.http_port)
        check(cfg)
    except ConfigError as exc:
        _print_config_error(path, exc)
        return 2
    from mocapd.service import assembly
    from mocapd.service.assembly import RunOptions

    print(f"mocapd run: {_rig_summary(cfg)}", flush=True)
    for note in _imu_notes(cfg, path) + _subject_notes(cfg):  # what check-config says: why no pose streams
        print(f"mocapd run: note: {note}", flush=True)
    # An IMU-only rig loads no detector: "loading models" would be a wait for nothing to a user watching it start.
    print(f"mocapd run: {'loading models, ' if cfg.cameras else ''}opening every device ...", flush=True)
    if args.verbose:  # and what happens to the devices: each one streaming, trackers connecting, heading resets
        import logging

        logging.getLogger("mocapd").setLevel(logging.INFO)

    def ready(a: assembly.Assembly) -> None:
        print(f"ready: status {a.daemon.http.url}/status  metrics {a.daemon.http.url}/metrics  (Ctrl-C stops)",
              flush=True)  # fmt: skip
        for line in assembly.ready_lines(a):
            print(line, flush=True)

    async def main(stop: asyncio.Event) -> int:
        status_line = (lambda s: print(s, flush=True)) if args.verbose else None
        options = RunOptions(record=args.record, status_line=status_line)
        return await assembly.run(cfg, options, stop=stop, on_ready=ready)

    try:
        return lifecycle.run_until_stopped(main)
    except MocapdError as exc:  # a device that did not open, a stream that cannot listen, a session that exists
        print(f"error: {exc}", file=sys.stderr)
        return 2


def cmd_reset_heading(args: argparse.Namespace) -> int:
    """``mocapd reset-heading``: ask the running daemon (``POST /heading/reset``) for a heading reset."""
    import time
    import urllib.parse

    query = f"?{urllib.parse.urlencode({'suit': args.suit})}" if args.suit else ""
    if args.delay > 0:
        print(f"stand straight, facing forward (the way you faced at calibration): reset in {args.delay:g} s",
              flush=True)  # fmt: skip
        time.sleep(args.delay)
    return ask_daemon(args, "/heading/reset" + query, "mocapd reset-heading")


def cmd_save_calibration(args: argparse.Namespace) -> int:
    """``mocapd calibrate save``: ask the running daemon (``POST /calibration/save``) to write the cameras it runs
    with to its calibration file (``[calibration] save_to``, else ``file``; the old one backed up)."""
    return ask_daemon(args, "/calibration/save", "mocapd calibrate save")


def ask_daemon(args: argparse.Namespace, target: str, client: str) -> int:
    """POST ``target`` to the daemon of ``args.config`` / ``args.http_port``; print its JSON answer (0) or its
    words on a refusal, or that no daemon answers (2)."""
    import urllib.error
    import urllib.request

    from mocapd.protocols.web_access import REQUEST_HEADER
    from mocapd.service.config import DEFAULT_CONFIG

    path = args.config if args.config is not None else DEFAULT_CONFIG
    try:
        cfg = _load(args.config, args.http_port)
    except ConfigError as exc:
        _print_config_error(path, exc)
        return 2
    d = cfg.daemon
    url = f"http://{d.http_host}:{d.http_port}{target}"
    try:
        # The header a web page cannot send (docs/reliability.md "The web surface"); its value names us in the log.
        request = urllib.request.Request(url, method="POST", headers={REQUEST_HEADER: client})
        with urllib.request.urlopen(request, timeout=10) as r:
            result = json.loads(r.read())
    except urllib.error.HTTPError as exc:  # a 400 (no such suit, nowhere to save), a 429 (too many): its words
        body = exc.read()
        try:
            said = json.loads(body).get("error", exc)
        except (ValueError, AttributeError):
            said = body.decode("utf-8", "replace").strip() or exc
        print(f"error: {said}", file=sys.stderr)
        return 2
    except (urllib.error.URLError, OSError) as exc:
        print(f"error: no daemon answers at {url} ({getattr(exc, 'reason', exc)}): start one with `mocapd run "
              f"--config FILE`, or name its port (--http-port, --config)", file=sys.stderr)  # fmt: skip
        return 2
    print(json.dumps(result, indent=2))
    return 0


def cmd_detect_host(args: argparse.Namespace) -> int:
    path = args.config
    try:
        cfg = _load(args.config)
    except ConfigError as exc:
        _print_config_error(path, exc)
        return 2
    from mocapd.service import detect_host

    cams = ", ".join(c.name for c in cfg.cameras)
    print(f"mocapd detect-host: {len(cfg.cameras)} camera(s): {cams}; rig {cfg.zenoh.rig!r}, listen "
          f"{list(cfg.zenoh.listen)}, connect {list(cfg.zenoh.connect)}", flush=True)  # fmt: skip

    def ready(host: str) -> None:
        print(f"ready: host {host} publishing mocapd/{cfg.zenoh.rig}/<camera>/detections (Ctrl-C stops)", flush=True)

    try:
        return detect_host.run(cfg, seconds=args.seconds if args.seconds > 0 else None, on_ready=ready)
    except MocapdError as exc:  # bad rig, a session that cannot listen, a device that does not open
        for line in str(exc).splitlines():
            print(f"{path}: error: {line}", file=sys.stderr)
        return 2


def cmd_demo(args: argparse.Namespace) -> int:
    try:
        cfg = _load(args.config, args.http_port)
        if args.imu_only:
            from mocapd.service.demo import imu_only

            with cpu_budget.held(args.cpu_budget):  # the simulated suit's threads too: they run in this process
                return imu_only.run(cfg, None if args.seconds <= 0 else args.seconds, record=args.record)
        if args.synthetic:
            from mocapd.service.demo import synthetic

            with cpu_budget.held(args.cpu_budget):
                return synthetic.run(cfg, None if args.seconds <= 0 else args.seconds, record=args.record)
        from mocapd.service.demo import cameras

        opts = cameras.CameraDemoOptions(scale=args.scale, latency_s=args.latency, speed=args.speed,
                                         packed=_packed(args), cpu_budget=args.cpu_budget,
                                         replug_after_s=args.replug_after)  # fmt: skip
        return cameras.run(args.config, cfg, None if args.seconds <= 0 else args.seconds, opts=opts,
                           record=args.record)  # fmt: skip
    except MocapdError as exc:  # bad config, a port in use, a session that exists, a device that did not open
        for line in str(exc).splitlines():
            print(f"error: {line}", file=sys.stderr)
        return 2


def cmd_bench_latency(args: argparse.Namespace) -> int:
    if args.rig == "cameras":
        from mocapd.service.bench import cameras
        from mocapd.service.config import load_config
        from mocapd.service.demo.cameras import CameraDemoOptions

        if args.config is not None:
            try:
                load_config(args.config)  # a bad file is one line here, not a traceback in the namespace
            except ConfigError as exc:
                _print_config_error(args.config, exc)
                return 2
        opts = CameraDemoOptions(
            scale=args.scale, latency_s=args.latency, packed=_packed(args), cpu_budget=args.cpu_budget
        )
        return cameras.run(args.seconds, opts, warm_up_s=args.warm_up, alone_passes=args.alone_passes,
                           config=args.config)  # fmt: skip
    from mocapd.service.bench import latency
    from mocapd.service.bench.machine import emit

    try:
        with cpu_budget.held(args.cpu_budget) as budget:
            if args.rig == "imu":
                report = latency.run_imu(seconds=args.seconds, output=args.output)
            else:
                report = latency.run(seconds=args.seconds, cameras=args.cameras, people=args.people)
            report["cpu_budget"] = budget.describe() if budget is not None else None
    except MocapdError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    e2e, out = report.get("end_to_end_ms") or {}, report["output"]
    emit(report, f"bench latency ({args.rig}): end to end p50 {e2e.get('p50')} ms, output {out['achieved_hz']} Hz, "
                 f"missed ticks {out['missed_ticks']}")  # fmt: skip
    return 0


def _packed(args: argparse.Namespace) -> bool | Literal["auto"]:
    """``[detector.packing] enabled`` of the camera demo from ``--detection`` (``--packed``: packed)."""
    if args.packed:
        return True
    choice: bool | Literal["auto"] = {"packed": True, "whole": False}.get(args.detection, "auto")
    return choice


def _latency(text: str) -> float | Literal["auto"]:
    """``--latency``: seconds, or "auto"."""
    if text == "auto":
        return "auto"
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: a number of seconds or 'auto'") from None


_LATENCY_HELP = 'camera rig: delay behind wall time, s, or "auto" (default: follows the detector)'
_DETECTION_HELP = (
    'camera rig: "auto" (default; each pass packed or a whole frame, whichever costs less detector time per '
    'camera frame), "packed" (cameras\' ROIs on shared canvases) or "whole" (one inference per camera frame)'
)
_BUDGET_HELP = (
    "hold the daemon's process to this many CPUs (e.g. 0.8) with a cgroup, as a slower or busier machine would; "
    "camera rig: the fake cameras are exempt (needs a writable cgroup cpu controller: root)"
)
_RECORD_HELP = "record this run as a session into this new directory (docs/sessions.md)"


def register(subparsers: Any) -> None:
    """Add run, demo, check-config and ``bench latency`` to the CLI."""
    lifecycle.setup_logging()  # a fault repeated many times a second is a few lines and a count
    run = subparsers.add_parser("run", help="run the daemon on the rig of a config file ([[cameras]], [imu])")
    run.add_argument("--config", type=Path, default=None, help="config file (default: the shipped config.toml)")
    run.add_argument("--http-port", type=int, default=None, help="override daemon.http_port (0 = any free port)")
    run.add_argument("--record", type=Path, default=None, help=_RECORD_HELP)
    run.add_argument("--verbose", action="store_true", help="print a status line per second, and each device "
                     "that starts streaming, SlimeVR tracker that connects and heading reset")  # fmt: skip
    run.set_defaults(func=cmd_run, fast_exit=True)

    host = subparsers.add_parser("detect-host", help="a camera host: run its cameras and detector, publish the "
                                 "detections over Zenoh to a solver host (docs/scaling.md)")  # fmt: skip
    host.add_argument("--config", type=Path, required=True, help="config file: [[cameras]], [calibration], [zenoh]")
    host.add_argument("--seconds", type=float, default=0.0, help="stop after this long (default: until Ctrl-C)")
    host.set_defaults(func=cmd_detect_host, fast_exit=True)

    demo = subparsers.add_parser("demo", help="the full daemon on an embedded rig, no hardware needed")
    demo.add_argument(
        "--synthetic", action="store_true", help="synthetic motion: simulated keypoints + Xsens IMUs on ptys"
    )
    demo.add_argument("--imu-only", action="store_true",
                      help="no camera: a simulated Xsens suit on ptys walking recorded motion drives the avatar alone "
                      "(viewer; VRChat OSC when --config enables [udp.vrchat])")  # fmt: skip
    demo.add_argument("--seconds", type=float, default=0.0, help="stop after this long (default: until Ctrl-C)")
    demo.add_argument("--config", type=Path, default=None, help="config file (default: the shipped config.toml)")
    demo.add_argument("--http-port", type=int, default=None, help="override daemon.http_port (0 = any free port)")
    demo.add_argument("--record", type=Path, default=None, help=_RECORD_HELP)
    demo.add_argument("--scale", type=float, default=0.5, help="camera rig: image size / 1088x1920 (default 0.5)")
    demo.add_argument("--latency", type=_latency, default="auto", help=_LATENCY_HELP)
    demo.add_argument("--detection", choices=["auto", "packed", "whole"], default="auto", help=_DETECTION_HELP)
    demo.add_argument("--packed", action="store_true", help="camera rig: same as --detection packed")
    demo.add_argument("--cpu-budget", type=float, default=None, metavar="CORES", help=_BUDGET_HELP)
    demo.add_argument("--speed", type=float, default=1.0,
                      help="camera rig: video playback speed (default 1, their pace; < 1: slow motion)")  # fmt: skip
    demo.add_argument("--replug-after", type=number(0.0, 3600.0), default=3.0, metavar="S",
                      help="camera rig: a fake camera whose process ends (kill one to pull its cable) is started "
                      "again after S seconds (default 3)")  # fmt: skip
    demo.set_defaults(func=cmd_demo, fast_exit=True)

    reset = subparsers.add_parser(
        "reset-heading", help="heading reset of the running daemon's suits: the wearer stands straight facing forward "
        "(IMUs without cameras drift in heading; POST /heading/reset, docs/vr.md)")  # fmt: skip
    reset.add_argument("--config", type=Path, default=None, help="the daemon's config file (for its http_port)")
    reset.add_argument("--http-port", type=int, default=None, help="the daemon's status port (default: the config's)")
    reset.add_argument("--suit", default=None, help="only this suit (default: every suit)")
    reset.add_argument("--delay", type=float, default=0.0, help="seconds to wait first, to stand straight (default 0)")
    reset.set_defaults(func=cmd_reset_heading)

    check_ = subparsers.add_parser("check-config", help="validate a config file and its rig, and say what is wrong")
    check_.add_argument("path", nargs="?", type=Path, default=None, help="config file (default: the shipped one)")
    check_.set_defaults(func=cmd_check_config)

    bench = _subcommand_group(subparsers, "bench")
    lat = bench.add_parser("latency", help="daemon end-to-end latency, output rate, CPU and memory (synthetic rig, or "
                           "the camera demo against its detector alone)")  # fmt: skip
    lat.add_argument("--seconds", type=float, default=60.0, help="run length (default 60)")
    lat.add_argument("--cameras", type=int, default=4)
    lat.add_argument("--people", type=int, default=2)
    lat.add_argument("--rig", choices=["synthetic", "cameras", "imu"], default="synthetic",
                     help="cameras: the camera demo (fake GigE cameras, real detector) in a private netns; imu: "
                     "`mocapd demo --imu-only`'s suit alone (13 simulated Xsens IMUs, no camera)")  # fmt: skip
    lat.add_argument("--output", choices=["delayed", "predicted"], default=None,
                     help="imu: [daemon] output (default: the shipped config's)")  # fmt: skip
    lat.add_argument("--scale", type=float, default=0.5, help="cameras: image size / 1088x1920")
    lat.add_argument("--latency", type=_latency, default="auto", help=_LATENCY_HELP)
    lat.add_argument("--detection", choices=["auto", "packed", "whole"], default="auto", help=_DETECTION_HELP)
    lat.add_argument("--packed", action="store_true", help="cameras: same as --detection packed")
    lat.add_argument("--cpu-budget", type=float, default=None, metavar="CORES", help=_BUDGET_HELP)
    lat.add_argument("--warm-up", type=float, default=20.0, help="cameras: seconds run before measuring (default 20)")
    lat.add_argument("--alone-passes", type=int, default=20,
                     help="cameras: detector-alone passes timed before the live run (default 20)")  # fmt: skip
    lat.add_argument("--config", type=Path, default=None,
                     help="cameras: base config whose [detector] (providers, precision, threads, packing) and [daemon] "
                     "are measured; the demo's cameras replace its rig (default: the shipped config)")  # fmt: skip
    lat.set_defaults(func=cmd_bench_latency)
