"""``mocapd calibrate``: camera calibration and calibration-file conversion.

``mocapd calibrate cameras``
    Intrinsics of every camera from board pictures (``--intrinsics DIR``: one sub-folder per camera), then, when
    ``--extrinsics DIR`` is given (one sub-folder per camera, the same file stem in several folders = the same
    moment), the rig's extrinsics with the board of ``--origin-frame`` lying on the floor at the world origin,
    refined by bundle adjustment. Writes mocapd's calibration TOML and prints a JSON report (per-view and
    per-camera reprojection errors, rejected views). ``--intrinsics-from FILE`` reuses existing intrinsics.

``mocapd calibrate cameras --from-people SOURCE``
    No board: the extrinsics from people walking through the volume (a recorded session, or ``pose2sim:<demo>``),
    metric from their height (``--height``, else 1.75 m), +Y up from their feet, with a quality report
    (:mod:`mocapd.service.people_calibration`).

``mocapd calibrate convert IN OUT``
    Converts between Qualisys ``.qca.txt``, Pose2Sim TOML, OpenCV YAML and mocapd TOML (format from the names;
    ``--to pose2sim`` writes Pose2Sim TOML). ``IN`` may be a recorded session: its cameras as the session ended,
    with every camera the daemon recalibrated while recording (the bumped-camera watch, ``docs/cameras.md``), so the
    next start has them.

Sub-folder names become camera names, without Pose2Sim's ``int_``/``ext_`` prefix and ``_img`` suffix.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from mocapd.errors import CalibrationError, ConfigError, InputError, MocapdError, ModelError, OutputError
from mocapd.io import lifecycle
from mocapd.io.output_files import check_output_file
from mocapd.service.cli.numbers import number

# The parser is built for every command: OpenCV, NumBa and SciPy (the board detection, the undistortion kernel, the
# bundle adjustment) are imported by the commands that calibrate, not by `mocapd --help`.
if TYPE_CHECKING:
    from mocapd.io.board_calibration import Board
    from mocapd.io.calibration_files import CalibrationSet

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff")


def camera_name(folder: Path) -> str:
    """Camera name of a picture folder: ``int_cam01_img`` → ``cam01``."""
    name = folder.name
    for prefix in ("int_", "ext_"):
        name = name.removeprefix(prefix)
    return name.removesuffix("_img")


def _camera_folders(root: Path) -> dict[str, Path]:
    if not root.is_dir():
        raise CalibrationError(f"{root} is not a folder: give a folder with one sub-folder of pictures per camera")
    folders = {camera_name(p): p for p in sorted(root.iterdir()) if p.is_dir()}
    if not folders:
        raise CalibrationError(f"{root} has no sub-folder: put each camera's pictures in its own sub-folder")
    return folders


def _images(folder: Path) -> list[Path]:
    # Every picture by its name, special files too: each is read through the media checks (a FIFO named x.jpg is
    # one line naming it, not a wait, and not a picture silently left out of the calibration).
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)


def calibrate_cameras(
    board: Board,
    intrinsics_dir: Path | None,
    extrinsics_dir: Path | None = None,
    *,
    intrinsics_from: Path | None = None,
    origin_frame: str | None = None,
    max_view_error_px: float = 1.0,
    fix_k3: bool = False,
) -> tuple[CalibrationSet, dict[str, Any]]:
    """Run the calibration described in the module docstring; returns the calibration and the report."""
    from mocapd.io.board_calibration import calibrate_intrinsics, detect_in_files
    from mocapd.io.calibration_files import CalibrationSet, CameraCalibration, read_any
    from mocapd.io.rig_calibration import Intrinsics, Observation, calibrate_rig

    report: dict[str, Any] = {"intrinsics": {}, "extrinsics": None}
    intr: dict[str, Intrinsics] = {}
    if intrinsics_from is not None:
        for cam in read_any(intrinsics_from).cameras:
            intr[cam.name] = Intrinsics(cam.K, cam.dist, cam.size)
    if intrinsics_dir is not None:
        for name, folder in _camera_folders(intrinsics_dir).items():
            dets, missed = detect_in_files(_images(folder), board)
            if not dets:
                raise CalibrationError(
                    f"camera {name}: the {board.cols}x{board.rows} {board.kind} was found in none of the "
                    f"{len(missed)} pictures in {folder}; check --cols/--rows (inner corners) and that the whole "
                    "board is visible and sharp"
                )
            res = calibrate_intrinsics(dets, board, max_view_error_px=max_view_error_px, rational_k3=not fix_k3)
            intr[name] = Intrinsics(res.K, res.dist, res.size)
            report["intrinsics"][name] = {
                "rms_px": round(res.rms_px, 4),
                "fx": res.K[0, 0],
                "fy": res.K[1, 1],
                "cx": res.K[0, 2],
                "cy": res.K[1, 2],
                "dist": res.dist.tolist(),
                "view_errors_px": res.view_errors_px,
                "rejected": res.rejected,
                "no_board_found": missed,
            }
    if not intr:
        raise CalibrationError("no intrinsics: give --intrinsics DIR or --intrinsics-from FILE")
    if extrinsics_dir is None:
        cams = tuple(CameraCalibration(n, i.size, i.K, i.dist) for n, i in sorted(intr.items()))
        return CalibrationSet(cams, "mocapd calibrate cameras (intrinsics only)"), report
    observations = []
    for name, folder in _camera_folders(extrinsics_dir).items():
        dets, _ = detect_in_files(_images(folder), board)
        observations += [Observation(name, Path(d.view).stem, d) for d in dets]
    rig = calibrate_rig(
        {n: i for n, i in intr.items() if any(o.camera == n for o in observations)},
        observations,
        board,
        origin_frame=origin_frame,
    )
    report["extrinsics"] = {
        "rms_before_px": rig.rms_before_px,
        "rms_after_px": rig.rms_after_px,
        "n_views": rig.n_observations,
        "origin_frame": origin_frame or "(frame seen by the most cameras)",
    }
    return rig.calibration, report


def _board(args: argparse.Namespace) -> Board:
    from mocapd.io.board_calibration import Board

    return Board(args.board, args.cols, args.rows, args.square_mm / 1000.0, args.marker_mm / 1000.0, args.dictionary)


def _run_cameras(args: argparse.Namespace) -> int:
    try:
        check_output_file(args.output, overwrite=args.force)
    except OutputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return _run_from_people(args) if args.from_people is not None else _run_board(args)


def _run_board(args: argparse.Namespace) -> int:
    if args.cols is None or args.rows is None or args.square_mm is None:
        print("error: --cols, --rows and --square-mm are required to calibrate from a board (or give "
              "--from-people SOURCE)", file=sys.stderr)  # fmt: skip
        return 2
    # The board detection can sit in one OpenCV call for minutes (a cluttered 1-megapixel picture: 40 s); it runs in
    # a worker so that Ctrl-C and SIGTERM still stop the command at once (issue 45).
    lifecycle.enter_phase("calibrating (nothing written yet)")
    try:
        calib, report = lifecycle.interruptible(
            calibrate_cameras,
            _board(args),
            args.intrinsics,
            args.extrinsics,
            intrinsics_from=args.intrinsics_from,
            origin_frame=args.origin_frame,
            max_view_error_px=args.max_view_error_px,
            fix_k3=args.fix_k3,
        )
    except InputError as exc:  # a picture that is no picture file: the input's fault, as every door's (exit 2)
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except CalibrationError as exc:
        print(f"calibration failed: {exc}", file=sys.stderr)
        return 1
    return _write_and_report(calib, args.output, json.dumps(report, indent=1, default=float))


def _run_from_people(args: argparse.Namespace) -> int:
    from mocapd.core.self_calibration import SelfCalibrationOptions
    from mocapd.io.calibration_files import read_any
    from mocapd.service import people_calibration as pc

    try:
        people = pc.load_people(args.from_people, args.intrinsics_from, args.fps, args.config)
        cams = people.cameras
        if args.intrinsics_from is not None:
            cams = pc.with_intrinsics(cams, read_any(args.intrinsics_from))
        if args.guess_intrinsics:
            cams = pc.guessed_cameras(cams, args.fov_deg)
        people = replace(people, cameras=cams)
        refine = args.refine_intrinsics or ("all" if args.guess_intrinsics else "none")
        origin = (0, 0) if args.origin_at is None else pc.moments_between(people.times_s, args.origin_at)
        opts = SelfCalibrationOptions(
            height_m=args.height, refine_focal=refine in ("focal", "all"), refine_principal_point=refine == "all",
            origin="people" if args.origin_at is None else "person",
            origin_moments=None if args.origin_at is None else origin, max_moments=args.max_moments,
        )  # fmt: skip
        reference = people.reference
        if args.reference is not None:
            reference = pc.reference_cameras(args.reference, cams)
        calib, report = pc.calibrate(people, opts, reference if args.reference is not None or args.compare else None)
    except (InputError, ConfigError, ModelError) as exc:  # a bad source, --config, or its detector's models
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except CalibrationError as exc:
        print(f"calibration failed: {exc}", file=sys.stderr)
        return 1
    text = json.dumps(report, indent=1, default=float) if args.json else pc.report_text(report, args.output)
    return _write_and_report(calib, args.output, text)


def _write_and_report(calib: CalibrationSet, output: Path, report: str) -> int:
    """Write the calibration either path computed, then print its report; exit 2 when it cannot be written."""
    from mocapd.io.calibration_files import write_mocapd_toml

    try:
        write_mocapd_toml(calib, output)
    except OutputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(report)
    return 0


def session_calibration(path: Path) -> CalibrationSet:
    """The cameras a recorded session ended with: its manifest's, each replaced by the last camera the daemon
    recalibrated it to while recording (the session's camera events)."""
    from mocapd.io.calibration_files import CalibrationSet, CameraCalibration
    from mocapd.io.session import open_session
    from mocapd.service.outputs.recorder import camera_from_dict
    from mocapd.service.session.solve import camera_changes

    session = open_session(path)
    try:
        cameras = [camera_from_dict(c) for c in session.manifest["cameras"]]
    except (KeyError, TypeError, ValueError, MocapdError) as exc:
        raise InputError(f"{path / 'manifest.json'}: damaged cameras: {exc}") from None
    for _, index, cam in camera_changes(session, cameras):
        cameras[index] = cam
    return CalibrationSet(tuple(CameraCalibration(c.name, (c.width, c.height), c.K, c.dist, c.R, c.t)
                                for c in cameras), source=f"session:{path}")  # fmt: skip


def _run_save(args: argparse.Namespace) -> int:
    from mocapd.service.cli.daemon import cmd_save_calibration

    return cmd_save_calibration(args)


def _run_convert(args: argparse.Namespace) -> int:
    from mocapd.io.calibration_files import (
        read_any,
        scale_calibration,
        write_mocapd_toml,
        write_opencv_yaml,
        write_pose2sim_toml,
    )

    try:
        check_output_file(args.output, inputs=[args.input], overwrite=args.force)
    except OutputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if (args.input / "manifest.json").is_file():  # a recorded session: its cameras as it ended
        if args.world_up is not None or args.scale != 1.0:
            print("error: a session's cameras are mocapd's (Y up, its image size): no --world-up or --scale",
                  file=sys.stderr)  # fmt: skip
            return 2
        try:
            calib = session_calibration(args.input)
        except InputError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
    else:
        try:
            calib = read_any(args.input, world_up=args.world_up)
            if args.scale != 1.0:
                calib = scale_calibration(calib, args.scale)
        except CalibrationError as exc:
            print(f"error: cannot read {args.input}: {exc}", file=sys.stderr)
            return 2
    target = args.to or ("opencv-yaml" if args.output.suffix in (".yml", ".yaml") else "mocapd")
    try:
        if target == "pose2sim":
            write_pose2sim_toml(calib, args.output)
        elif target == "opencv-yaml":
            write_opencv_yaml(calib, args.output)
        else:
            write_mocapd_toml(calib, args.output)
    except OutputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {len(calib.cameras)} camera(s) to {args.output} ({target})")
    return 0


def register(subparsers: Any) -> None:
    """Add ``mocapd calibrate ...`` to the CLI."""
    parser = subparsers.add_parser("calibrate", help="calibrate cameras, convert calibration files")
    sub = parser.add_subparsers(dest="calibrate_command", metavar="WHAT", required=True)
    cams = sub.add_parser("cameras", help="intrinsics and extrinsics from board pictures, or from people walking")
    cams.add_argument("--board", choices=["checkerboard", "charuco"], default="checkerboard")
    cams.add_argument(
        "--cols",
        type=number(2, 200, integer=True),
        help="checkerboard: inner corners per row; charuco: squares",
    )
    cams.add_argument(
        "--rows",
        type=number(2, 200, integer=True),
        help="checkerboard: inner corners per column; charuco: squares",
    )
    cams.add_argument("--square-mm", type=number(0.1, 10_000.0), help="square side, mm (board)")
    cams.add_argument("--marker-mm", type=number(0.0, 10_000.0), default=0.0, help="ChArUco marker side, mm")
    cams.add_argument("--dictionary", default="DICT_4X4_50", help="ChArUco ArUco dictionary")
    cams.add_argument("--intrinsics", type=Path, help="folder with one picture sub-folder per camera")
    cams.add_argument("--intrinsics-from", type=Path, help="reuse intrinsics from a calibration file")
    cams.add_argument("--extrinsics", type=Path, help="folder with one sub-folder per camera, same stem = same moment")
    cams.add_argument("--origin-frame", help="file stem of the moment the board lies on the floor at the origin")
    cams.add_argument(
        "--max-view-error-px", type=number(0.01, 1000.0), default=1.0, help="reject views above this RMS error, px"
    )
    cams.add_argument("--fix-k3", action="store_true", help="keep k3 = 0 (as Qualisys/Pose2Sim)")
    people = cams.add_argument_group("from people (no board)")
    people.add_argument(
        "--from-people",
        metavar="SOURCE",
        help="a recorded session directory, a detections .npz (with --intrinsics-from), or "
        "pose2sim:Demo_SinglePerson / pose2sim:Demo_MultiPerson",
    )
    people.add_argument(
        "--config",
        type=Path,
        default=None,
        help="pose2sim:<demo>: detect with this config's [detector] (e.g. presets/eval-video-landmarks-heavy.toml: "
        "BlazePose landmarks; default the shipped config's)",
    )
    people.add_argument(
        "--fps",
        type=number(1.0, 1000.0),
        default=30.0,
        help="moments per second of a detections .npz (default 30; for --origin-at)",
    )
    people.add_argument(
        "--height",
        type=number(0.5, 2.6),
        default=None,
        help="the people's mean height, m (default: 1.75, stated in the report)",
    )
    people.add_argument(
        "--guess-intrinsics",
        action="store_true",
        help="ignore the source's intrinsics: centred pinhole, --fov-deg, refined",
    )
    people.add_argument(
        "--fov-deg",
        type=number(10.0, 150.0),
        default=60.0,
        help="with --guess-intrinsics: field of view across the longer image side (default 60)",
    )
    people.add_argument(
        "--refine-intrinsics",
        choices=["none", "focal", "all"],
        default=None,
        help="also adjust the focal length (focal) and principal point (all); default: none, "
        "all with --guess-intrinsics",
    )
    people.add_argument(
        "--origin-at",
        type=number(0.0, 1e6),
        default=None,
        metavar="SECONDS",
        help="a person stands at the origin facing +Z during the second from SECONDS (default: the "
        "origin is the middle of where people walked, +Z along the first camera's view)",
    )
    people.add_argument(
        "--max-moments",
        type=number(10, 100_000, integer=True),
        default=400,
        help="moments used at most, evenly spaced (default 400)",
    )
    people.add_argument("--reference", type=Path, help="compare with this calibration (e.g. a board's)")
    people.add_argument(
        "--compare",
        action="store_true",
        help="compare with the source's own calibration (pose2sim demos: their board calibration)",
    )
    people.add_argument("--json", action="store_true", help="print the report as JSON")
    cams.add_argument("--output", "-o", type=Path, required=True, help="mocapd calibration TOML to write")
    cams.add_argument("--force", action="store_true", help="replace an existing --output file")
    cams.set_defaults(func=_run_cameras)
    conv = sub.add_parser("convert", help="convert qca.txt / Pose2Sim TOML / OpenCV YAML / mocapd TOML")
    conv.add_argument("input", type=Path, help="a calibration file, or a recorded session (its cameras as it ended)")
    conv.add_argument("output", type=Path)
    conv.add_argument("--to", choices=["mocapd", "pose2sim", "opencv-yaml"], default=None)
    conv.add_argument("--force", action="store_true", help="replace an existing OUTPUT file (never the input)")
    conv.add_argument("--world-up", choices=["y", "z"], default=None, help="up axis of the input's world")
    conv.add_argument("--scale", type=number(0.01, 100.0), default=1.0,
                      help="for images resized by this factor (0.5: half-size, or 2x2 binning); default 1")  # fmt: skip
    conv.set_defaults(func=_run_convert)
    save = sub.add_parser(
        "save", help="ask the running daemon to write the cameras it runs with (the camera watch's changes applied) "
        "to its calibration file ([calibration] save_to, else file; the old one kept as NAME.<time>.bak)")  # fmt: skip
    save.add_argument("--config", type=Path, default=None, help="the daemon's config file (for its http_port)")
    save.add_argument("--http-port", type=int, default=None, help="the daemon's status port (default: the config's)")
    save.set_defaults(func=_run_save)
