"""``mocapd calibrate imu``: record a T-pose from the configured IMUs and write a per-person calibration file.

The subject stands still in the T-pose (arms horizontal, facing one direction) for the whole recording. The
command connects to every configured serial IMU (and the bridge input and SlimeVR server if enabled), waits until
every assigned sensor streams (with per-person tables, ``[imu.assignment.<person>]``, every sensor of ``--person``'s
table: another suit on the same inputs is neither waited for nor calibrated), records ``--seconds``, then computes
R_ib per sensor and R_ig (:func:`mocapd.core.imu_calibration.calibrate_tpose`) and writes
``<calibration_dir>/<person>.imu.json``.

With ``--from SESSION`` nothing is recorded: the stillest standing window of a recorded or imported session is
used instead and the calibration is also stored in the session (:mod:`mocapd.service.session.calibrate`).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from mocapd.core.imu_calibration import (
    CALIBRATION_POSES,
    MAX_ACC_STD,
    MAX_TURN_DEG,
    POSE_HINTS,
    ImuCalibration,
    calibrate_tpose,
    facing_heading_from_sensor,
    quat_average,
    rest_orientations,
)
from mocapd.core.names import check_name
from mocapd.errors import ConfigError, DeviceTimeout, MocapdError, OutputError
from mocapd.io.output_files import check_output_file, write_text_atomic
from mocapd.service.cli.numbers import number

# The parser is built for every command: the config schema (pydantic, and through its defaults the detector's and
# the rig's modules) is imported when a calibration runs, not by `mocapd --help`. NumPy and the core's
# IMU calibration stay: the parser's choices and defaults are theirs (CALIBRATION_POSES, MAX_TURN_DEG, MAX_ACC_STD).
# The devices' modules (asyncio's streams, the serial and SlimeVR protocols) and the guided routine are imported
# when a calibration streams.
if TYPE_CHECKING:
    from mocapd.core.calibration_routine import CalibrationRoutine
    from mocapd.io.xsens_serial import ImuSample
    from mocapd.service.config.imu import ImuConfig


def _subcommand_group(subparsers: Any, name: str, help_text: str, dest: str) -> Any:
    """The nested sub-command group ``mocapd NAME ...``, shared with other modules that add to it."""
    parser = subparsers.choices.get(name)
    if parser is None:
        parser = subparsers.add_parser(name, help=help_text)
        parser.add_subparsers(dest=dest, metavar="WHAT", required=True)
    return next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))


def register(subparsers: Any) -> None:
    """Add ``calibrate imu`` to the CLI's subcommands."""
    group = _subcommand_group(subparsers, "calibrate", "calibration procedures", "calibrate_what")
    p = group.add_parser("imu", help="T-pose calibration of the IMU mountings (writes <person>.imu.json)")
    p.add_argument("--config", type=Path, default=None,
                   help="config file with an [imu] section (default: config.toml here); with --from, whose "
                   "calibration_dir gets the file too")  # fmt: skip
    p.add_argument("--person", help="name of the subject (file name of the calibration; required when recording; with "
                   "per-person tables, [imu.assignment.PERSON], whose sensors are recorded)")  # fmt: skip
    p.add_argument(
        "--from",
        dest="from_session",
        type=Path,
        metavar="SESSION",
        help="calibrate from a recorded or imported session's stillest standing window instead of recording",
    )
    p.add_argument(
        "--pose",
        choices=(*CALIBRATION_POSES, "auto"),
        default="t-pose",
        help="the posture held, as a hint: t-pose (arms horizontal), a-pose (upper arms about 30° below "
        "horizontal), n-pose or arms-down (arms hanging at the sides, palms in), auto (each tried; with --from the one "
        "with which knees and elbows bend the right way). The sensors' inclination refines it: upper arms 15-35° "
        "down, elbows or knees a little bent calibrate correctly (docs/imu.md)",
    )
    p.add_argument(
        "--pose-exact",
        action="store_true",
        help="take the --pose as held exactly (no posture estimated from the sensors nor from the take's motion: every "
        "mounting error stays)",
    )
    p.add_argument(
        "--guided",
        action="store_true",
        help="the guided routine on the live sensors: stand still, walk a few steps, bend the elbows, as it says; the "
        "facing from the steps (no --facing-heading needed), the mountings refined by the knees' and elbows' axes "
        "(docs/imu.md, 'Calibrating a suit live')",
    )
    p.add_argument(
        "--step-timeout",
        type=number(1.0, 3600.0),
        default=60.0,
        metavar="S",
        help="with --guided: the most seconds a step may take before the routine gives up (default 60)",
    )
    p.add_argument(
        "--no-motion",
        action="store_true",
        help="with --from: keep the still window's mountings (by default the take's knee and elbow bends, where they "
        "bend enough about one axis, refine them: docs/imu.md, 'Hinge axes from motion')",
    )
    p.add_argument(
        "--knee-extension",
        action="store_true",
        help="with --from: raise each knee's standing bend by how far the take's straightest knee reads bent "
        "backwards (by default measured and printed only: a knee may hyperextend; docs/imu.md, 'The knees' "
        "extension from motion')",
    )
    p.add_argument(
        "--max-turn",
        type=number(0.1, 45.0),
        default=MAX_TURN_DEG,
        metavar="DEG",
        help=f"stillness: the most a sensor may turn in the still window, degrees (default {MAX_TURN_DEG:g}; "
        "MTx/MTw/Awinda/SlimeVR standing still stay well below it, docs/imu.md)",
    )
    p.add_argument(
        "--max-acc-std",
        type=number(0.01, 10.0),
        default=MAX_ACC_STD,
        metavar="M_S2",
        help=f"stillness: the most a sensor's acceleration norm may vary in the still window, std in m/s² "
        f"(default {MAX_ACC_STD:g})",
    )
    p.add_argument("--suit", help="with --from: the suit name in the session (default: the import's, or the person)")
    facing = p.add_mutually_exclusive_group()
    facing.add_argument(
        "--facing-heading",
        type=number(-360.0, 360.0),
        help="compass heading the subject faces, degrees clockwise from magnetic north",
    )
    facing.add_argument(
        "--facing-from",
        metavar="SENSOR:AXIS",
        help="derive the heading from a sensor axis known to point forward, e.g. 00B421E6:-z (with --from: "
        "optional, the take's steps give it; a sign that bends the knees backwards is refused)",
    )
    p.add_argument("--world-heading", choices=("subject", "north"), default="subject", help="what world +Z is")
    p.add_argument("--seconds", type=number(0.1, 3600.0), default=3.0, help="recording length (s)")
    p.add_argument(
        "--window",
        default="1.0",
        help="length of the still window searched (s, default 1); with --from also START:END, the seconds of the "
        "session to search in (a 1 s window)",
    )
    p.add_argument("--port", action="append", default=[], help="serial device path (overrides imu.ports)")
    p.add_argument("--connect-timeout", type=number(0.1, 3600.0), default=15.0, help="wait for all sensors (s)")
    p.add_argument(
        "--out",
        type=Path,
        help="output file (default <calibration_dir>/<person>.imu.json; with --from: "
        "SESSION/calibration/<person>.imu.json, or --config's calibration_dir when --config is given)",
    )
    p.add_argument(
        "--mount-yaw",
        action="append",
        default=[],
        metavar="SENSOR=DEG",
        help="SlimeVR trackers (no shared heading): which way a tracker faces, degrees to the subject's left "
        "(default 0: on the front or back of its segment; 90: on the left side, -90: on the right)",
    )
    p.set_defaults(func=run_calibrate)


async def record(
    config: ImuConfig, seconds: float, connect_timeout: float, sensors: dict[str, str] | None = None
) -> dict[str, list[ImuSample]]:
    """Stream from every configured input until each of ``sensors`` (default: every assigned sensor) streams, then
    record ``seconds`` of their samples (another suit's sensors on the same inputs are neither waited for nor kept).
    """

    async def wait(_: Callable[[], dict[str, list[ImuSample]]]) -> None:
        await asyncio.sleep(seconds)

    return await streaming(config, connect_timeout, sensors, wait)


async def streaming(
    config: ImuConfig,
    connect_timeout: float,
    sensors: dict[str, str] | None,
    body: Callable[[Callable[[], dict[str, list[ImuSample]]]], Awaitable[None]],
) -> dict[str, list[ImuSample]]:
    """Stream from every configured input until each of ``sensors`` (default: every assigned sensor) streams, then
    keep their samples while ``body`` runs; ``body`` gets a function that returns the samples kept since its last
    call. Returns every sample kept."""
    from mocapd.io.imu_bridge import ImuBridgeListener
    from mocapd.io.slimevr import SlimeVrListener
    from mocapd.io.xsens_serial import XsensSerialDevice

    samples: dict[str, list[ImuSample]] = {}
    taken: dict[str, int] = {}
    seen: set[str] = set()
    recording = False

    wanted = set(config.sensors if sensors is None else sensors)

    def on_sample(s: ImuSample) -> None:
        if recording and s.sensor in wanted:
            samples.setdefault(s.sensor, []).append(s)
        else:
            seen.add(s.sensor)

    def take() -> dict[str, list[ImuSample]]:
        out = {sid: rs[taken.get(sid, 0) :] for sid, rs in samples.items()}
        taken.update({sid: len(rs) for sid, rs in samples.items()})
        return out

    devices = [XsensSerialDevice(p, on_sample) for p in config.port_configs()]
    tasks = [asyncio.create_task(d.run()) for d in devices]
    bridge = ImuBridgeListener(on_sample, host=config.bridge.host, port=config.bridge.port)
    if config.bridge.enabled:
        await bridge.start()
    sv = config.slimevr
    slimevr = SlimeVrListener(on_sample, host=sv.host, port=sv.port) if sv.enabled else None
    if slimevr is not None:
        try:
            await slimevr.start()
        except MocapdError:
            bridge.close()
            raise
        tasks.append(asyncio.create_task(slimevr.run()))
    try:
        deadline = time.monotonic() + connect_timeout
        while not wanted <= seen:
            if time.monotonic() > deadline:
                errors = "; ".join(d.last_error for d in devices if d.last_error)
                raise DeviceTimeout(
                    f"sensors {sorted(wanted - seen)} sent nothing within {connect_timeout} s"
                    + (f" ({errors})" if errors else "")
                )
            await asyncio.sleep(0.05)
        recording = True
        await body(take)
        recording = False
    finally:
        for d in devices:
            d.stop()
        if slimevr is not None:
            slimevr.stop()
        await asyncio.gather(*tasks)
        bridge.close()
        if slimevr is not None:
            slimevr.close()
    return samples


GUIDED_POLL_S = 0.25
"""How often the guided routine is fed the samples that arrived (s)."""


TICKS_HZ = 10_000.0
"""Xsens SampleTimeFine counts at 10 kHz."""


def _arrays(rows: list[ImuSample], base: dict[str, tuple[int, int]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Times (s), orientations (n, 4), specific force (n, 3) of the samples that carry both.

    A sample's time is its device clock's (SampleTimeFine) from the sensor's first sample on, put on the host clock
    at that first sample (``base``: sensor -> (host ns, ticks)): a loaded machine reads a serial port in bursts, and
    the host times of a burst's samples would be one instant (a still second would look shorter than it was)."""
    kept = [r for r in rows if r.quat is not None and r.acc is not None]
    times = []
    for r in kept:
        if r.device_ticks is None:
            times.append(r.host_ns / 1e9)
            continue
        host0, ticks0 = base.setdefault(r.sensor, (r.host_ns, r.device_ticks))
        times.append(host0 / 1e9 + ((r.device_ticks - ticks0) % (1 << 32)) / TICKS_HZ)
    return (np.array(times), np.array([r.quat for r in kept]).reshape(-1, 4),
            np.array([r.acc for r in kept]).reshape(-1, 3))  # fmt: skip


async def guided(config: ImuConfig, routine: CalibrationRoutine, connect_timeout: float) -> None:
    """Run the guided routine (:mod:`mocapd.core.calibration_routine`) on the live sensors, printing what it says."""
    said = 0
    base: dict[str, tuple[int, int]] = {}

    async def run(take: Callable[[], dict[str, list[ImuSample]]]) -> None:
        nonlocal said
        routine.start(time.monotonic_ns() / 1e9)
        while routine.step not in ("done", "failed"):
            await asyncio.sleep(GUIDED_POLL_S)
            routine.feed(time.monotonic_ns() / 1e9, {sid: _arrays(rows, base) for sid, rows in take().items()})
            for _, text in routine.said[said:]:
                print(text, flush=True)
            said = len(routine.said)

    await streaming(config, connect_timeout, routine.bones, run)


def run_calibrate(args: argparse.Namespace) -> int:
    """Entry point of ``mocapd calibrate imu``; returns the process exit status."""
    from mocapd.service.config import load_config
    from mocapd.service.config.imu import ImuConfig
    from mocapd.service.config.schema import validate

    if args.from_session is not None:
        from mocapd.service.cli.recordings import calibrate_from_session

        return calibrate_from_session(args)
    try:
        if not args.person:
            raise ConfigError("--person is required (the name of the calibration file)")
        if args.guided:
            return _run_guided(args)
        if args.facing_heading is None and args.facing_from is None:
            raise ConfigError(
                "give the facing direction of the T-pose: --facing-heading DEG or --facing-from SENSOR:AXIS "
                "(a recording calibrated with --from SESSION can take it from its steps)"
            )
        check_name(args.person, "--person")  # it names the calibration file: no '/', no newline
        window_s = float(args.window)
        config = load_config(args.config or Path("config.toml")).imu  # validates the whole file, like the daemon
        sensors = config.suit_sensors(args.person)  # per-person tables: this person's suit only
        out = args.out or Path(config.calibration_dir) / f"{args.person}.imu.json"
        try:  # before recording: a path that cannot be written is known at once
            replacing = check_output_file(out, overwrite=True, create_folder=True).exists()
        except OutputError as exc:
            print(f"mocapd calibrate imu: {exc}")
            return 2
        if args.port:  # --port replaces imu.ports, validated like the file's
            config = validate(ImuConfig, {**config.model_dump(), "ports": list(args.port)}, "imu")
        if not config.sensors:
            raise ConfigError("imu.assignment is empty: say which sensor sits on which bone")
        if args.facing_from is not None:
            parse_facing(args.facing_from)  # reject a malformed option before recording
        samples = asyncio.run(record(config, args.seconds, args.connect_timeout, sensors))
        rate = max(len(v) for v in samples.values()) / args.seconds if samples else 0.0
        recordings = {
            sid: (
                np.array([s.quat for s in samples[sid] if s.quat is not None]),
                np.array([s.acc for s in samples[sid] if s.acc is not None]),
            )
            for sid in sensors
            if sid in samples
        }
        heading = args.facing_heading
        if heading is None:
            heading = _heading_from(args.facing_from, recordings)
        own_yaw = _own_heading(sensors, args.mount_yaw)

        def calibrate(hint: str) -> ImuCalibration:
            return calibrate_tpose(
                args.person, recordings, sensors, facing_heading_deg=heading, world_heading=args.world_heading,
                window=max(2, int(window_s * rate)), own_heading=own_yaw, rest=rest_orientations(hint),
                max_spread_deg=args.max_turn, max_acc_std=args.max_acc_std, estimate_posture=not args.pose_exact,
                pose_hint=hint,
            )  # fmt: skip

        # Without motion, auto keeps the hint whose mountings stray least from case-along-the-segment ones.
        hints = POSE_HINTS if args.pose == "auto" else (args.pose,)
        calib = min((calibrate(h) for h in hints), key=_rms_residual)
    except MocapdError as exc:  # before ValueError: a ConfigError is one too, and says what is wrong itself
        print(f"mocapd calibrate imu: {exc}")
        return 1
    except ValueError:
        print(f"mocapd calibrate imu: --window {args.window!r}: give seconds (START:END only with --from)")
        return 1
    return _write_and_say(calib, out, replacing)


def _run_guided(args: argparse.Namespace) -> int:
    """``mocapd calibrate imu --guided``: the routine on the live sensors (stand, walk, elbows), then the file."""
    from mocapd.core.calibration_routine import CalibrationRoutine, RoutineOptions
    from mocapd.service.config import load_config
    from mocapd.service.config.imu import ImuConfig
    from mocapd.service.config.schema import validate

    try:
        if args.pose == "auto":
            raise ConfigError("--guided: say the stand's posture with --pose t-pose, a-pose or n-pose (not auto)")
        if args.facing_from is not None:
            raise ConfigError("--guided takes the facing from the steps (or --facing-heading), not --facing-from")
        check_name(args.person, "--person")
        config = load_config(args.config or Path("config.toml")).imu
        if args.port:
            config = validate(ImuConfig, {**config.model_dump(), "ports": list(args.port)}, "imu")
        sensors = config.suit_sensors(args.person)
        if not sensors:
            raise ConfigError("imu.assignment is empty: say which sensor sits on which bone")
        if any("/" in sid for sid in sensors):
            raise ConfigError("--guided: SlimeVR trackers need their own headings from --mount-yaw; calibrate them "
                              "without --guided")  # fmt: skip
        out = args.out or Path(config.calibration_dir) / f"{args.person}.imu.json"
        try:
            replacing = check_output_file(out, overwrite=True, create_folder=True).exists()
        except OutputError as exc:
            print(f"mocapd calibrate imu: {exc}")
            return 2
        options = RoutineOptions(pose=args.pose, window_s=float(args.window), facing_heading_deg=args.facing_heading,
                                 world_heading=args.world_heading, max_turn_deg=args.max_turn,
                                 max_acc_std=args.max_acc_std, step_timeout_s=args.step_timeout)  # fmt: skip
        routine = CalibrationRoutine(args.person, dict(sensors), options)
        asyncio.run(guided(config, routine, args.connect_timeout))
    except MocapdError as exc:
        print(f"mocapd calibrate imu: {exc}")
        return 1
    except ValueError:
        print(f"mocapd calibrate imu: --window {args.window!r}: give seconds")
        return 1
    if routine.calibration is None:
        return 1  # it said why
    return _write_and_say(routine.calibration, out, replacing)


def _write_and_say(calib: ImuCalibration, out: Path, replacing: bool) -> int:
    """Write the calibration file and print each sensor's stillness, residuals and the posture found."""
    try:
        write_text_atomic(out, json.dumps(calib.to_json_dict(), indent=2) + "\n")
    except OutputError as exc:
        print(f"mocapd calibrate imu: {exc}")
        return 2
    for sid, bone in calib.bones.items():
        own = f"  heading reset {calib.device_heading_deg[sid]:+.1f} deg" if sid in calib.device_heading_deg else ""
        hinge = f"  hinge misfit {calib.hinge_misfit_deg[sid]:.1f} deg" if sid in calib.hinge_misfit_deg else ""
        if sid in calib.gravity_misfit_deg:
            hinge += f"  gravity misfit {calib.gravity_misfit_deg[sid]:.1f} deg"
        print(f"{sid} {bone:14s} still within {calib.spread_deg[sid]:.2f} deg  mounting residual "
              f"{calib.residual_deg.get(sid, float('nan')):.1f} deg{hinge}{own}")  # fmt: skip
    print(f"posture ({calib.pose_hint} hint): " + ", ".join(f"{k.replace('_', ' ')} {v:g} deg"
                                                           for k, v in calib.posture.items()))  # fmt: skip
    print(f"wrote {out}" + (" (replaced the earlier calibration)" if replacing else ""))
    return 0


def _rms_residual(calib: ImuCalibration) -> float:
    """RMS of the mountings' residuals (degrees): how far the sensors stray from case-along-the-segment mountings."""
    return float(np.sqrt(np.mean(np.square(list(calib.residual_deg.values()) or [0.0]))))


_AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}


def _own_heading(sensors: dict[str, str], specs: list[str]) -> dict[str, float]:
    """Mounting yaw of every SlimeVR sensor of ``sensors`` (0 unless ``--mount-yaw SENSOR=DEG`` says)."""
    out = {sid: 0.0 for sid in sensors if "/" in sid}  # "<MAC>/<index>": a SlimeVR sensor
    for spec in specs:
        sensor, _, value = spec.rpartition("=")
        sid = sensor.upper()
        try:
            yaw = float(value)
        except ValueError:
            raise ConfigError(f"--mount-yaw {spec!r}: expected SENSOR=DEGREES") from None
        if not -360.0 <= yaw <= 360.0:  # nan too
            raise ConfigError(f"--mount-yaw {spec!r}: degrees from -360 to 360")
        if sid not in out:
            raise ConfigError(f"--mount-yaw {spec!r}: {sensor!r} is not an assigned SlimeVR sensor")
        out[sid] = yaw
    return out


def parse_facing(spec: str) -> tuple[str, np.ndarray]:
    """``SENSOR:[+-]AXIS`` → (sensor id, unit axis in the sensor frame)."""
    sensor, _, axis = spec.partition(":")
    sign = -1.0 if axis.startswith("-") else 1.0
    vec = _AXES.get(axis.lstrip("+-").lower())
    if vec is None or not sensor:
        raise ConfigError(f"--facing-from {spec!r}: expected SENSOR:AXIS, AXIS one of x, y, z, -x, -y, -z")
    return sensor.upper(), sign * np.array(vec)


def _heading_from(spec: str, recordings: dict[str, tuple[np.ndarray, np.ndarray]]) -> float:
    """Heading from ``SENSOR:[+-]AXIS`` and that sensor's mean T-pose orientation."""
    sensor, axis = parse_facing(spec)
    quats = recordings.get(sensor)
    if quats is None or len(quats[0]) == 0:
        raise ConfigError(f"--facing-from {spec!r}: no samples from sensor {sensor}")
    return facing_heading_from_sensor(quat_average(quats[0]), axis)
