"""``mocapd import mtw|mvnx`` (existing recordings as sessions) and ``mocapd calibrate imu --from SESSION``.

::

    mocapd import mtw FILE... -o SESSION --assign SENSOR=BONE... [--suit NAME] [--height M] [--imu-set lower]
    mocapd import mvnx FILE -o SESSION [--assign SENSOR=BONE...] [--suit NAME] [--height M]
    mocapd calibrate imu --from SESSION [--facing-heading DEG | --facing-from SENSOR:AXIS]
                         [--window START:END] [--pose t-pose|a-pose|n-pose|auto] [--person NAME] [--suit NAME]
    mocapd resolve SESSION          # solves the suit IMU-only
    mocapd export SESSION --resolved --bvh take.bvh --csv take.csv
    mocapd eval ground [--parts synthetic,standing,...] [--optical-data DIR]   # root drift/strides, JSON (docs/imu.md)

``import mtw`` takes MT Manager text exports, one file per sensor (:mod:`mocapd.io.mt_export`), ``import mvnx``
an MVN export (its sensors are assigned from their segment labels unless ``--assign`` says otherwise). Both print
a JSON summary. See ``docs/imu.md`` ("Existing recordings") and :mod:`mocapd.service.session.importer`.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from mocapd.core.body_dims import SEGMENTS, default_lengths
from mocapd.core.names import check_name
from mocapd.core.skeleton import REFERENCE_HEIGHT
from mocapd.errors import MocapdError, OutputError
from mocapd.io.output_files import check_output_dir, check_output_file, write_text_atomic
from mocapd.service.cli.numbers import number

if TYPE_CHECKING:
    from mocapd.eval.ground import GroundEvalOptions
    from mocapd.io.mvnx import MvnBody


def _segments(args: argparse.Namespace) -> dict[str, float]:
    """The segment lengths given on the command line (``--thigh`` ...)."""
    return {k: v for k in SEGMENTS if (v := getattr(args, f"seg_{k}", None)) is not None}


def _summary(path: Path, manifest: dict[str, Any]) -> dict[str, Any]:
    from mocapd.service.session.calibrate import calibrate_command

    imp = manifest["imported"]
    return {
        "session": str(path),
        "from": imp["from"],
        "suit": imp["suit"],
        "duration_s": imp["duration_s"],
        "sensors": {
            sid: {
                k: v
                for k, v in info.items()
                if k in ("file", "label", "samples", "rate_hz", "orientation", "acceleration")
            }
            for sid, info in imp["sensors"].items()
        },
        "assignment": imp["assignment"],
        "unassigned": sorted(set(imp["sensors"]) - set(imp["assignment"])),
        "skeleton": manifest["skeleton"]["from"],
        "next": calibrate_command(path, manifest),
    }


def cmd_import_mtw(args: argparse.Namespace) -> int:
    from mocapd.io.mt_export import read_mt_export
    from mocapd.service.session.importer import (
        imported_manifest,
        parse_assign_pairs,
        streams_from_mt_exports,
        write_imported_session,
    )

    check_output_dir(args.output, what="session directory")  # before reading: a bad -o is known at once
    exports = [(p.name, read_mt_export(p, rate_hz=args.rate)) for p in _export_files(args.files)]
    streams = streams_from_mt_exports(exports)
    manifest = imported_manifest(
        streams, parse_assign_pairs(args.assign), source="mt-manager", suit=args.suit,
        height=REFERENCE_HEIGHT if args.height is None else args.height,
        imu_set=args.imu_set or None, segments=_segments(args),
    )  # fmt: skip
    path = write_imported_session(args.output, streams, manifest)
    _note_unassigned(manifest)
    print(json.dumps(_summary(path, manifest), indent=2))
    return 0


def _export_files(paths: list[Path]) -> list[Path]:
    """The files named, a folder standing for its MT Manager exports (``*.txt``, ``*.csv``)."""
    out: list[Path] = []
    for p in paths:
        if p.is_dir():
            found = sorted(f for f in p.iterdir() if f.is_file() and f.suffix.lower() in (".txt", ".csv"))
            if not found:
                raise MocapdError(f"{p}: a folder without MT Manager exports (.txt, .csv)")
            out += found
        else:
            out.append(p)
    return out


def _note_unassigned(manifest: dict[str, Any], automatic: bool = False) -> None:
    """Say which imported sensors have no bone: they are kept in the session, but nothing calibrates or solves them.
    ``automatic``: the bones came from an MVNX file's segment labels (no ``--assign``)."""
    imp = manifest["imported"]
    extra = sorted(set(imp["sensors"]) - set(imp["assignment"]))
    if not extra:
        return
    if automatic:
        # MVN's own segments, assigned automatically: the ones left have no bone of mocapd's (the shoulders'
        # clavicle sensors), and an --assign would replace the automatic assignment of every other sensor.
        labels = ", ".join(f"{sid} ({imp['sensors'][sid].get('label', '?')})" for sid in extra)
        print(f"note: {len(extra)} sensor(s) on segments mocapd's skeleton does not have, kept in the session but "
              f"not calibrated or solved: {labels}", file=sys.stderr)  # fmt: skip
        return
    print(f"note: {len(extra)} sensor(s) have no bone, kept in the session but not calibrated or solved: "
          f"{', '.join(extra)}; give each a bone with --assign SENSOR=BONE, or leave its file out",
          file=sys.stderr)  # fmt: skip


def _mvnx_body(args: argparse.Namespace, mvn: MvnBody | None) -> tuple[float, dict[str, float], str | None]:
    """The wearer's height and segments for an MVNX import, and ``"mvnx"`` where the file's body was used.

    MVN's own body (the file's segment points: MVN Studio's calibration of the person) is the default, each
    segment given on the command line in its place; a ``--height`` given alone scales the default proportions as
    for any import (the file's body is then left out, and a note says so). A file without segment points: the
    command line's, or the 1.75 m default."""
    from mocapd.core.body_dims import LIMITS
    from mocapd.service.session.importer import MAX_HEIGHT_M, MIN_HEIGHT_M

    given = _segments(args)
    lengths = "" if mvn is None else ", ".join(f"{k} {v:.3f}" for k, v in mvn.segments.items())
    if mvn is not None and not (
        MIN_HEIGHT_M <= mvn.height <= MAX_HEIGHT_M and all(LIMITS[0] <= v <= LIMITS[1] for v in mvn.segments.values())
    ):  # comparisons with nan are False: a nan is refused too
        print(f"note: the MVNX file's own body is not one mocapd can use (height {mvn.height:.3f} m, {lengths}; "
              f"allowed: a height of {MIN_HEIGHT_M:g}-{MAX_HEIGHT_M:g} m, segments of {LIMITS[0]:g}-{LIMITS[1]:g} "
              "m): the skeleton comes from --height and the segments given instead", file=sys.stderr)  # fmt: skip
        mvn = None
    if mvn is None:
        return (REFERENCE_HEIGHT if args.height is None else args.height), given, None
    if args.height is not None and not given:
        print(f"note: --height {args.height:g} m scales the default proportions; the MVNX file's own body (height "
              f"{mvn.height:.3f} m, {lengths}) is not used: leave --height out to use it", file=sys.stderr)  # fmt: skip
        return args.height, {}, None
    replaced = f"; from the command line instead: {', '.join(sorted(given))}" if given else ""
    print(f"note: the wearer's body from the MVNX file (MVN's calibrated segments): height {mvn.height:.3f} m, "
          f"{lengths}{replaced}", file=sys.stderr)  # fmt: skip
    return (mvn.height if args.height is None else args.height), {**mvn.segments, **given}, "mvnx"


def cmd_import_mvnx(args: argparse.Namespace) -> int:
    from mocapd.io.mvnx import read_mvnx
    from mocapd.service.session.importer import (
        imported_manifest,
        mvnx_assignment,
        parse_assign_pairs,
        streams_from_mvnx,
        write_imported_session,
    )

    check_output_dir(args.output, what="session directory")
    recording = read_mvnx(args.file)
    streams = streams_from_mvnx(recording, args.file.name)
    assignment = parse_assign_pairs(args.assign) if args.assign else mvnx_assignment(streams)
    height, segments, body_from = _mvnx_body(args, recording.body())
    manifest = imported_manifest(
        streams,
        assignment,
        source="mvnx",
        suit=args.suit,
        height=height,
        imu_set=args.imu_set or None,
        segments=segments,
        body_from=body_from,
    )
    path = write_imported_session(args.output, streams, manifest)
    _note_unassigned(manifest, automatic=not args.assign)
    print(json.dumps(_summary(path, manifest), indent=2))
    return 0


def calibrate_from_session(args: argparse.Namespace) -> int:
    """``mocapd calibrate imu --from SESSION``: see :mod:`mocapd.service.session.calibrate`."""
    from mocapd.core.imu_calibration import ImuCalibration
    from mocapd.io.session import open_session
    from mocapd.service.cli.imu import parse_facing
    from mocapd.service.config import load_config
    from mocapd.service.session.calibrate import calibrate_session, store_in_session

    try:
        session = open_session(args.from_session)
        span, window_s = _window(args.window)
        suit = args.suit or session.manifest.get("imported", {}).get("suit") or args.person
        if not suit:
            raise MocapdError("name the suit (--suit) or the person (--person)")
        person = args.person or suit
        check_name(suit, "--suit" if args.suit else f"{session.path}: the suit's name")
        check_name(person, "--person")  # it names the calibration file: no '/', no newline
        # A take's calibration stays with the take: a file in the working directory's calibration/ would become a
        # suit of any daemon started there. A rig's calibration_dir gets it only when its config is named.
        if args.out is not None:
            out = args.out
        elif args.config is not None:
            out = Path(load_config(args.config).imu.calibration_dir) / f"{person}.imu.json"
        else:
            out = session.path / "calibration" / f"{person}.imu.json"
        replacing = check_output_file(out, inputs=[session.path], overwrite=True, create_folder=True).exists()
        result = calibrate_session(
            session,
            person=person,
            facing_heading_deg=args.facing_heading,
            facing_from=parse_facing(args.facing_from) if args.facing_from else None,
            world_heading=args.world_heading,
            window_s=window_s,
            span=span,
            pose=args.pose,
            suit=suit,
            estimate_posture=not args.pose_exact,
            max_turn_deg=args.max_turn,
            max_acc_std=args.max_acc_std,
            motion=not (args.no_motion or args.pose_exact),  # exact: the hint held, every mounting error kept
            knee_extension=args.knee_extension,
        )
        calib: ImuCalibration = result.calibration
        info = {"window_s": [round(v, 3) for v in result.window_s], "pose": result.pose,
                "facing_heading_deg": round(calib.facing_heading_deg, 2), "facing_from": result.facing,
                "posture_deg": calib.posture,
                "mount_residual_deg": {s: round(v, 1) for s, v in calib.residual_deg.items()},
                "hinges": {name: h.as_dict() for name, h in result.hinges.items()},
                "hinge_misfit_deg": {s: round(v, 1) for s, v in calib.hinge_misfit_deg.items()},
                "hinge_axes": result.functional,
                "knee_extension": result.knee_extension,
                "gravity_misfit_deg": {s: round(v, 1) for s, v in calib.gravity_misfit_deg.items()},
                "stance_gravity": result.stances}  # fmt: skip
        store_in_session(session, suit, calib, info)
        write_text_atomic(out, json.dumps(calib.to_json_dict(), indent=2) + "\n")
    except OutputError as exc:  # a path that cannot be written: an argument error, as argparse's (exit 2)
        print(f"mocapd calibrate imu: {exc}", file=sys.stderr)
        return 2
    except MocapdError as exc:
        print(f"mocapd calibrate imu: {exc}", file=sys.stderr)
        return 1
    if replacing:  # a recalibration renews the person's file: said, not done silently
        print(f"note: replaced the earlier calibration {out}", file=sys.stderr)
    print(json.dumps({"session": str(session.path), "suit": suit, "calibration": str(out), "posture": result.pose,
                      "window_s": info["window_s"], "facing_heading_deg": info["facing_heading_deg"],
                      "facing_from": result.facing, "hinges_checked": sorted(result.hinges),
                      "still_spread_deg": {s: round(v, 2) for s, v in calib.spread_deg.items()},
                      "posture_deg": calib.posture,
                      "mount_residual_deg": {s: round(v, 1) for s, v in calib.residual_deg.items()},
                      "hinge_axes": result.functional,
                      "hinge_misfit_deg": info["hinge_misfit_deg"],
                      "knee_extension": result.knee_extension,
                      "stance_gravity": result.stances,
                      "gravity_misfit_deg": info["gravity_misfit_deg"],
                      "next": f"mocapd resolve {session.path}"}, indent=2))  # fmt: skip
    return 0


def _window(spec: str) -> tuple[tuple[float, float] | None, float]:
    """``--window``: ``START:END`` (span, 1 s window) or ``SECONDS`` (window length, whole session)."""
    start, sep, end = str(spec).partition(":")
    try:
        if sep:
            span = (float(start) if start else 0.0, float(end) if end else float("inf"))
            if not span[0] < span[1]:
                raise ValueError
            return span, 1.0
        length = float(spec)
        if not length > 0:
            raise ValueError
        return None, length
    except ValueError:
        raise MocapdError(f"--window {spec!r}: expected START:END (seconds of the session) or SECONDS") from None


def _guard(func: Any) -> Any:
    def run(args: argparse.Namespace) -> int:
        try:
            result: int = func(args)
        except MocapdError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        return result

    return run


GROUND_PARTS = ("synthetic", "walking", "standing", "cameras_back", "mtw", "mvnx", "optical")


def cmd_eval_ground(args: argparse.Namespace) -> int:
    from mocapd.eval.ground import GroundEvalOptions, run

    parts = tuple(args.parts.split(",")) if args.parts else GroundEvalOptions().parts
    unknown = sorted(set(parts) - set(GROUND_PARTS))
    if unknown:
        raise MocapdError(f"--parts: unknown {unknown}; choose from {', '.join(GROUND_PARTS)}")
    opts = GroundEvalOptions(seed=args.seed, split=args.split, parts=parts, standing_s=args.standing_seconds,
                             optical_dir=args.optical_data)  # fmt: skip
    out = run(opts, args.data_root)
    if "optical" in parts:
        out["optical"].update(_optical_through_commands(opts, args.data_root))
    print(json.dumps(out, indent=2))
    return 0


def _optical_through_commands(opts: GroundEvalOptions, data_root: Path | None) -> dict[str, Any]:
    """The optical walk as a suit owner runs it (import mtw -> calibrate imu --from -> resolve -> export), measured
    as the library path's rows are (issue 42: "``eval ground`` measures exactly that path"); in a scratch folder."""
    import tempfile

    from mocapd.eval.data import default_data_root
    from mocapd.eval.ground_optical import HEIGHT_M, default_dir
    from mocapd.service.cli.optical_walk import through_commands

    directory = opts.optical_dir or default_dir(default_data_root() if data_root is None else Path(data_root))
    with tempfile.TemporaryDirectory(prefix="mocapd-optical-") as work:
        row = through_commands(directory, Path(work) / "walk", HEIGHT_M, [])
    return {f"mocapd through the commands, height {HEIGHT_M} m": row}


def register(subparsers: Any) -> None:
    """Add ``import mtw``, ``import mvnx`` and ``eval ground`` to the CLI."""
    from mocapd.service.cli.imu import _subcommand_group

    ev = _subcommand_group(subparsers, "eval", "evaluations that print JSON", "eval")
    g = ev.add_parser("ground", help="root drift without cameras: synthetic rig, walking clips, real MTw/MVNX")
    g.add_argument(
        "--parts",
        default="",
        help="comma-separated subset of synthetic,walking,standing,cameras_back,mtw,mvnx (the default: all of "
        "them) and optical (a real walk against Vicon; its data are not shipped: see --optical-data)",
    )
    g.add_argument(
        "--optical-data",
        type=Path,
        default=None,
        metavar="DIR",
        help="the optical part's recording: the data/sample folder of github.com/gait-tech/gaittoolbox (GPL-3.0) "
        "(default <data root>/imu/gaittoolbox)",
    )
    g.add_argument("--split", default="evaluation", help="clip split for the walking part (default evaluation)")
    g.add_argument("--standing-seconds", type=float, default=60.0, help="length of the standing-still test")
    g.add_argument("--seed", type=int, default=0)
    g.add_argument("--data-root", type=Path, default=None, help="recorded data (default ../shared/data, $MOCAPD_DATA)")
    g.set_defaults(func=_guard(cmd_eval_ground))

    imp = subparsers.add_parser(
        "import", help="existing recordings as sessions: IMU (MT Manager exports, MVNX), other detectors' 2D keypoints"
    )
    what = imp.add_subparsers(dest="import_what", metavar="FORMAT", required=True)

    def common(p: argparse.ArgumentParser, mvnx: bool = False) -> None:
        p.add_argument("-o", "--output", type=Path, required=True,
                       help="session directory to create (new, or an empty directory)")  # fmt: skip
        p.add_argument("--assign", action="append", default=[], metavar="SENSOR=BONE",
                       help="which sensor sits on which bone, e.g. 00B42279=Hips (repeat)")  # fmt: skip
        p.add_argument("--suit", default="suit0", help="the suit's name in the session (default suit0)")
        body = p.add_argument_group(
            "the wearer's body",
            "a height, and any segment lengths measured (each one not given is scaled from the "
            "height; the session records which: manifest skeleton.from)"
            + ("; an MVNX file's own body (MVN's calibration of the wearer) is the default" if mvnx else ""),
        )
        default = (
            "the body MVN calibrated, from the file's segment points; else " if mvnx else ""
        ) + f"{REFERENCE_HEIGHT:g}"
        body.add_argument("--height", type=number(0.5, 2.5), default=None, metavar="M",
                          help=f"the wearer's height, m (default {default})")  # fmt: skip
        at = default_lengths()
        for name, what in SEGMENTS.items():
            mvn = "MVN's, else " if mvnx else ""
            helps = f"{what}, m (default: {mvn}from --height; {at[name]:.3f} at {REFERENCE_HEIGHT:g} m)"
            body.add_argument(f"--{name.replace('_', '-')}", type=number(0.01, 1.5), default=None, metavar="M",
                              dest=f"seg_{name}", help=helps)  # fmt: skip
        p.add_argument(
            "--imu-set",
            default="",
            choices=("", "13", "6", "lower"),
            help="check that the assignment forms this sensor set (lower: pelvis, thighs, shanks, feet)",
        )

    mtw = what.add_parser("mtw", help="MT Manager text exports, one file per sensor (the id in its name)")
    mtw.add_argument("files", type=Path, nargs="+",
                     help="export files (.txt/.csv) of one recording, or a folder of them")  # fmt: skip
    mtw.add_argument(
        "--rate", type=number(1.0, 2000.0), default=None, help="update rate (Hz) when the files do not say it"
    )
    common(mtw)
    mtw.set_defaults(func=_guard(cmd_import_mtw))

    mvnx = what.add_parser("mvnx", help="an Xsens MVN export (.mvnx)")
    mvnx.add_argument("file", type=Path, help="the .mvnx file")
    common(mvnx, mvnx=True)
    mvnx.set_defaults(func=_guard(cmd_import_mvnx))
    _register_keypoints(what)


def _register_keypoints(what: Any) -> None:
    from mocapd.core.keypoint_sets import SETS
    from mocapd.io.calibration_units import UNITS
    from mocapd.io.keypoint_files import FORMATS, MAX_FPS, MIN_FPS

    kp = what.add_parser(
        "keypoints",
        help="2D keypoints of another detector (OpenPose, MMPose/RTMPose, Pose2Sim, MediaPipe, FreeMoCap), one input "
        "per camera",
    )
    kp.add_argument("inputs", nargs="+", metavar="[CAMERA=]PATH",
                    help="per camera: an OpenPose JSON folder, an MMPose or MediaPipe JSON file (or folder); or one "
                    "Pose2Sim project folder, or one FreeMoCap 2D array (.npy); CAMERA names the calibration's camera "
                    "(default: the folder's or file's name, cam01_json -> cam01)")  # fmt: skip
    kp.add_argument("-o", "--output", type=Path, required=True,
                    help="session directory to create (new, or an empty directory)")  # fmt: skip
    kp.add_argument("--calibration", type=Path, default=None, metavar="FILE",
                    help="the cameras' calibration, any format mocapd reads (docs/cameras.md); a Pose2Sim "
                    "project's own by default")  # fmt: skip
    kp.add_argument(
        "--fps",
        type=number(MIN_FPS, MAX_FPS),
        default=None,
        help="the frame rate of the keypoints (a Pose2Sim project's Config.toml frame_rate by default)",
    )
    kp.add_argument("--timestamps", action="append", default=[], metavar="[CAMERA=]FILE",
                    help="frame times instead of --fps: a text file of one time (s) per line (line k: frame k) or "
                    "'frame time_s' pairs; CAMERA= for one camera's (repeat), else every camera's; --fps is then "
                    "the output rate (default: the times' median rate)")  # fmt: skip
    kp.add_argument("--format", default="auto", choices=FORMATS, help="the inputs' layout (default: told from them)")
    kp.add_argument(
        "--keypoints",
        default=None,
        choices=tuple(SETS),
        help="the keypoint set of the files (default: told from their length or their metadata)",
    )
    kp.add_argument("--up", default=None, choices=("y", "z", "-y", "auto"),
                    help="the calibration world's up axis (default: the format's: z for Pose2Sim TOML, Qualisys, "
                    "EasyMocap and the Shelf/Campus JSON, -y for CMU Panoptic (write --up=-y), y for mocapd and OpenCV "
                    "files); a Z-up world's floor z = 0 becomes mocapd's y = 0; auto: up and the floor measured "
                    "on the people (upright on average, their ankles low), for a world whose up is unknown or "
                    "tilted")  # fmt: skip
    kp.add_argument("--units", default=None, choices=tuple(UNITS),
                    help="the calibration's translation unit (default: the format's: mm for VoxelPose's JSON, cm for "
                    "CMU Panoptic, else m)")  # fmt: skip
    kp.add_argument(
        "--floor",
        type=number(-100.0, 100.0),
        default=0.0,
        metavar="M",
        help="the floor's height up the world's up axis, metres (default 0: the floor at the origin)",
    )
    kp.add_argument(
        "--height",
        type=number(0.5, 2.5),
        default=REFERENCE_HEIGHT,
        metavar="M",
        help=f"the people's height before body sizing measures them, m (default {REFERENCE_HEIGHT:g})",
    )
    kp.set_defaults(func=_guard(cmd_import_keypoints))


def cmd_import_keypoints(args: argparse.Namespace) -> int:
    from mocapd.io.calibration_files import on_floor, read_any
    from mocapd.io.keypoint_files import read_keypoint_inputs, read_timestamps
    from mocapd.service.session.keypoint_import import (
        keypoint_take,
        keypoints_manifest,
        median_rate,
        write_keypoint_session,
    )

    check_output_dir(args.output, what="session directory")
    inp = read_keypoint_inputs(list(args.inputs), args.format, args.keypoints)
    calib_path = args.calibration or inp.calibration
    if calib_path is None:
        raise MocapdError("give the cameras' calibration (--calibration FILE)")
    timestamps = read_timestamps(args.timestamps) if args.timestamps else None
    fps = args.fps if args.fps is not None else inp.fps
    if fps is None and timestamps:
        fps = median_rate(timestamps)
    if fps is None:
        raise MocapdError("give the keypoints' frame rate (--fps HZ) or their times (--timestamps FILE)")
    if args.up == "auto":
        if args.floor != 0.0:
            raise MocapdError("--up auto measures the floor on the people: leave --floor out")
        calib, world = _levelled(read_any(calib_path, world_up="y", units=args.units), inp, fps, timestamps,
                                 args.height)  # fmt: skip
    else:
        calib, world = on_floor(read_any(calib_path, world_up=args.up, units=args.units), args.floor), None
    take = keypoint_take(inp, calib, fps, timestamps)
    manifest = keypoints_manifest(take, fps=fps, height=args.height, source=", ".join(args.inputs),
                                  layout=inp.layout, calibration=str(calib_path))  # fmt: skip
    path = write_keypoint_session(args.output, take, manifest)
    imp = manifest["imported"]
    print(json.dumps({"session": str(path), "layout": inp.layout, "keypoint_set": take.source_set,
                      "solved_as": take.keypoint_format, "fps": fps, "calibration": str(calib_path),
                      "cameras": {c.name: {"input": str(i.source), "frames": take.frames[i.name]}
                                  for c, i in zip(take.cameras, inp.cameras, strict=True)},
                      "duration_s": imp["duration_s"], **({"world": world} if world else {}),
                      "next": f"mocapd resolve {path}"}, indent=2))  # fmt: skip
    return 0


def _levelled(calib: Any, inp: Any, fps: float, timestamps: Any, height: float) -> tuple[Any, dict[str, Any]]:
    """``--up auto``: the calibration's world turned so that the people's up is +Y and moved so that their floor
    is y = 0 (:mod:`mocapd.core.people_up`), with what was measured."""
    from mocapd.core.keypoints import keypoint_format
    from mocapd.core.people_up import level_rotation, up_and_floor
    from mocapd.io.calibration_files import on_floor, turned
    from mocapd.service.session.keypoint_import import keypoint_take, people_in_take

    take = keypoint_take(inp, calib, fps, timestamps)
    up, floor, used = up_and_floor(people_in_take(take), keypoint_format(take.keypoint_format).keypoints, height)
    world = {"up": [round(float(v), 4) for v in up], "floor_m": round(floor, 3), "from": "people",
             "person_instants": used}  # fmt: skip
    return on_floor(turned(calib, level_rotation(up)), floor), world
