"""``mocapd replay``, ``mocapd resolve``, ``mocapd export`` and ``mocapd session`` (recorded sessions)."""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

from mocapd.errors import InputError, MocapdError
from mocapd.io import lifecycle
from mocapd.io.output_files import check_distinct, check_output_file
from mocapd.service.cli.numbers import number

# The parser is built for every command: the session files, the pipeline and the config schema (NumPy, SciPy,
# NumBa, onnxruntime, OpenCV, pydantic) are imported by the command that runs, not by `mocapd --help`.
if TYPE_CHECKING:
    from mocapd.core.skeleton import Skeleton
    from mocapd.io.session import Session
    from mocapd.io.session_export import SubjectTrack
    from mocapd.pipeline.camera_views import CameraViews
    from mocapd.pipeline.scheduler import PoseFrame
    from mocapd.protocols.session_format import PoseRecord
    from mocapd.service.config import Config
    from mocapd.service.daemon import PoseSink


def stream_sinks(
    config: Config, skeleton: Skeleton, camera_views: CameraViews | None = None, output: str = "delayed"
) -> list[PoseSink]:
    """The streaming sinks a replay publishes through: the streams configured in ``config``, for poses on the
    session's ``skeleton`` (the WebSocket stream with the session's camera panels when ``camera_views``),
    announcing the recorded ``output`` mode."""
    from mocapd.service.outputs.udp import udp_sinks
    from mocapd.service.outputs.websocket import websocket_sinks

    return [*udp_sinks(config, skeleton), *websocket_sinks(config, skeleton, camera_views=camera_views, output=output)]


def session_files(session: Path) -> list[Path]:
    """The files of a session that its commands read (an output must be none of them)."""
    from mocapd.io.session import FRAMES, MANIFEST, RESOLVED, STREAMS, SUFFIX

    return [session / MANIFEST, session / "prior.npz",
            *(session / f"{name}{SUFFIX}" for name in (*STREAMS, RESOLVED, FRAMES))]  # fmt: skip


def resolved_path(out: Path) -> Path:
    """Where ``resolve -o OUT`` writes (:func:`~mocapd.service.session.solve.write_resolved`: a ``.mcs`` file)."""
    from mocapd.io.session import SUFFIX

    return out.parent / f"{out.name.removesuffix(SUFFIX)}{SUFFIX}"


def _open(path: Path) -> Session:
    from mocapd.io.session import open_session

    session = open_session(path)
    session.check()
    for line in session.recovery_lines():
        print(f"note: {line}", file=sys.stderr)
    for line in session.manifest.get("notes", []):  # what the recorder noticed (knees bending the wrong way)
        print(f"note: {line}", file=sys.stderr)
    return session


def _undecodable_notes(session: Session) -> None:
    """A note per stream read so far with records whose checksum was intact but whose payload did not decode
    (skipped, like corrupt ones; known only once the records were decoded, after :func:`_open`'s notes)."""
    for r in session.reports.values():
        if r.undecodable:
            print(f"note: {session.path}/{r.name}.mcs: {r.undecodable} intact records did not decode (skipped)",
                  file=sys.stderr)  # fmt: skip


def _poses(session: Session, args: argparse.Namespace, again: str) -> list[PoseRecord]:
    """The frames to replay or export: the live ``poses``, the resolved ones (``--resolved``), or a stream file
    ``mocapd resolve -o FILE`` wrote (``--poses FILE``). A session whose live stream holds no pose but which is
    resolved (an imported take always is so) names the command that reads the resolved poses."""
    from mocapd.io.session import RESOLVED

    if args.poses is not None:
        return session.require_poses_file(args.poses)
    if args.resolved:
        if not session.has_stream(RESOLVED):
            raise InputError(f"{session.path}: no resolved poses yet: run `mocapd resolve {session.path}` first")
        return session.require_poses(RESOLVED)
    try:
        return session.require_poses("poses")
    except InputError as exc:
        if not session.has_stream(RESOLVED):
            raise
        raise InputError(f"{exc}; the session is resolved: `{again} --resolved`") from None


def _again(command: str, args: argparse.Namespace, options: tuple[str, ...]) -> str:
    """The command line the user typed (for a message naming the next one to type)."""
    out = [f"mocapd {command} {args.session}"]
    for name in options:
        value = getattr(args, name, None)
        if value is not None and value is not False:
            out.append(f"--{name.replace('_', '-')}" + ("" if value is True else f" {value}"))
    return " ".join(out)


def cmd_replay(args: argparse.Namespace) -> int:
    from mocapd.service.config import load_config
    from mocapd.service.config.udp import describe_streams
    from mocapd.service.session.replay import ReplayStats, replay, replay_camera_views
    from mocapd.service.session.solve import session_rig

    cfg = load_config(args.config)
    session = _open(args.session)
    frames = _poses(session, args, _again("replay", args, ("speed", "config")))
    _undecodable_notes(session)
    rig = session_rig(session)
    views, events = replay_camera_views(session, rig, frames)
    output = frames[0].output if frames else "delayed"
    sinks: list[PoseSink] = [views, *stream_sinks(cfg, rig.skeleton, views, output)]
    last = [0.0]

    def progress(frame: PoseFrame) -> None:
        t = (frame.t_solve_ns - frames[0].t_solve_ns) / 1e9
        if args.verbose and t - last[0] >= 1.0:
            last[0] = t
            print(f"t={t:6.1f} s  frame {frame.frame}  people [{', '.join(p.identity for p in frame.people)}]",
                  flush=True)  # fmt: skip

    print(f"mocapd replay: {len(frames)} frames through {len(sinks) - 1} sink(s) at {args.speed:g}x", flush=True)
    for line in describe_streams(cfg.udp):  # where the engines' streams go, as `mocapd run` says it
        print(line, flush=True)

    async def main(stop: asyncio.Event) -> ReplayStats:
        lifecycle.enter_phase("replaying")
        return await replay(frames, sinks, speed=args.speed, on_frame=progress, events=events, stop=stop)

    stats = lifecycle.run_until_stopped(main)
    print(json.dumps(asdict(stats)))
    return 0


def cmd_resolve(args: argparse.Namespace) -> int:
    from mocapd.io.progress import Progress
    from mocapd.service.session.solve import (
        ResolveOptions,
        resolve,
        session_rig,
        solve_times,
        suit_sensors,
        write_resolved,
    )
    from mocapd.service.session.truth import synthetic_of, truth_report

    if args.output is not None:  # the default, SESSION/poses-resolved.mcs, is the session's own: renewed
        check_output_file(resolved_path(args.output), inputs=session_files(args.session), overwrite=args.force)
    session = _open(args.session)
    rig = session_rig(session)
    try:
        truth = synthetic_of(session) is not None  # checked before the solve: a damaged table is known at once
    except InputError as exc:
        truth = False
        print(f"note: {exc} (no error against the truth)", file=sys.stderr)
    # The inputs of the solve the session had: a camera rig's keypoints, a suit's IMU samples.
    for stream, needed in (("keypoints", rig.cameras), ("imu", rig.suits)):
        if needed:
            session.require_stream(stream)
    opts = ResolveOptions(max_iterations=args.iterations, smooth=not args.no_smooth)
    n_frames = len(solve_times(session, rig.options.rate_hz, suit_sensors(rig.suits)))
    # A stop signal raises StopRequested here: the output is written at the end, atomically (exit 128 + the signal).
    lifecycle.enter_phase("re-solving the session (nothing written yet)")
    with Progress(n_frames, "resolve") as bar:
        frames, summary = resolve(session, opts, bar)
    _undecodable_notes(session)
    for line in summary["notes"]:  # anatomically impossible stretches (a mirrored facing, a swapped sensor)
        print(f"note: {line}", file=sys.stderr)
    path = write_resolved(session, frames, args.output)
    summary["written"] = str(path)
    read = f"--poses {path}" if args.output is not None else "--resolved"
    summary["next"] = f"mocapd export {session.path} {read} --csv take.csv --bvh take.bvh"
    if truth:
        summary["error_vs_truth_mm"] = truth_report(session, {"live": session.poses(), "resolved": frames})
    print(json.dumps(summary, indent=2, default=str))
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    from mocapd import __version__
    from mocapd.io.progress import Progress
    from mocapd.io.session_export import (
        FLEETING_S,
        lasting_subjects,
        resample,
        subject_track,
        write_bvh,
        write_csv,
        write_gltf,
    )
    from mocapd.service.session.solve import session_rig

    if args.bvh is None and args.csv is None and args.gltf is None and args.fbx is None:
        print("error: nothing to export: give --bvh FILE, --csv FILE, --gltf FILE and/or --fbx FILE", file=sys.stderr)
        return 2
    outputs = [(o, p) for o, p in (("--bvh", args.bvh), ("--csv", args.csv), ("--gltf", args.gltf), ("--fbx", args.fbx))
               if p is not None]  # fmt: skip
    check_distinct(outputs)  # before any work: a path that cannot be written is known at once
    for _, path in outputs:
        check_output_file(path, inputs=session_files(args.session), overwrite=args.force)
    blender = _find_blender(args) if args.fbx is not None else None  # before any work: no Blender is one line
    session = _open(args.session)
    poses = _poses(session, args, _again("export", args, ("gltf", "fbx", "bvh", "csv", "subject")))
    _undecodable_notes(session)
    rig: list[Skeleton] = []

    def skeleton_of(track: SubjectTrack) -> Skeleton:
        # The subject's body-sized skeleton when one was recorded (the first seconds of a track, before sizing,
        # were solved on the rig's; their joint angles export on the sized one), else the rig's.
        if track.skeleton is not None:
            return track.skeleton
        if not rig:
            rig.append(session_rig(session).skeleton)
        return rig[0]

    lifecycle.enter_phase("exporting")  # a stop signal unwinds the export (exit 128 + the signal)
    # glTF/FBX: every subject but fleeting tracks, unless one is named; BVH and CSV: one (default: the one seen most).
    everyone, fleeting = ([args.subject], {}) if args.subject is not None else lasting_subjects(poses)
    many = args.gltf is not None or args.fbx is not None  # every subject resampled, once for both
    if many:
        for who, seen in fleeting.items():
            print(
                f"note: {who} left out of the glTF/FBX: seen for {seen}, under {FLEETING_S:g} s (a fleeting track, "
                f"which would stand frozen through the take); --subject {who} exports it",
                file=sys.stderr,
            )
    steps = 1 + sum(f is not None for f in (args.bvh, args.csv)) + (len(everyone) + 1 if many else 0)
    with Progress(steps, "export") as bar:
        track = resample(subject_track(poses, args.subject), args.rate)
        bar(1)
        skeleton = skeleton_of(track)
        out: dict[str, Any] = {"subject": track.subject, "frames": int(track.thetas.shape[0]), "rate_hz": args.rate}
        if args.bvh is not None:
            write_bvh(args.bvh, skeleton, track, args.rate)
            out["bvh"] = str(args.bvh)
            bar(1)
        if args.csv is not None:
            write_csv(args.csv, skeleton, track, origin_ns=_origin_ns(session))
            out["csv"] = str(args.csv)
            bar(1)
        if many:
            tracks = []
            raw = [subject_track(poses, who) for who in everyone]
            origin = min(int(r.t_ns[0]) for r in raw)  # one frame grid for every subject
            for r in raw:
                t = resample(r, args.rate, origin)
                tracks.append((t, skeleton_of(t)))
                bar(1)
        if args.gltf is not None:
            write_gltf(args.gltf, tracks, f"mocapd {__version__}")
            out["gltf"] = str(args.gltf)
            out["gltf_subjects"] = {t.subject: int(t.thetas.shape[0]) for t, _ in tracks}
        if args.fbx is not None:
            from mocapd.io.fbx_export import export_fbx

            report = export_fbx(args.fbx, tracks, rate_hz=args.rate, units=args.fbx_units, up=args.fbx_up,
                                take=Path(args.session).resolve().name, blender=blender)  # fmt: skip
            out["fbx"] = str(args.fbx)
            out["fbx_subjects"] = {t.subject: int(t.thetas.shape[0]) for t, _ in tracks}
            out["fbx_nodes"], out["fbx_blender"] = report["nodes"], report["blender"]
        if many:
            bar(1)
            if fleeting:
                out["left_out"] = fleeting
    print(json.dumps(out))
    return 0


def _origin_ns(session: Session) -> int | None:
    """Host time of the session's start (an imported take: of its recording's first sample): the CSV's
    ``source_s`` counts from it."""
    origin = session.manifest.get("started_monotonic_ns")
    return origin if isinstance(origin, int) and not isinstance(origin, bool) else None


def _find_blender(args: argparse.Namespace) -> Any:
    """Blender for ``--fbx``, found before the session is read (:mod:`mocapd.io.fbx_export`)."""
    from mocapd.io.fbx_export import find_blender

    return find_blender(args.blender)


def cmd_info(args: argparse.Namespace) -> int:
    from mocapd.io.session_export import subjects
    from mocapd.service.session.solve import session_rig

    session = _open(args.session)
    m = session.manifest
    poses = session.poses()  # before "streams": its records that do not decode are counted in its report
    _undecodable_notes(session)
    try:
        session_rig(session)  # the manifest's rig and the prior file: what replay and resolve will read
        rig = "ok"
    except MocapdError as exc:
        rig = str(exc)
        print(f"note: {exc}", file=sys.stderr)
    info = {
        "path": str(session.path),
        "closed_cleanly": session.closed_cleanly,
        "cut": session.cut,
        "started_utc": m.get("started_utc"),
        "software": m.get("software"),
        "cameras": _names(m.get("cameras"), "name"),
        "suits": _names(m.get("suits"), "id"),
        "streams": {k: asdict(v) for k, v in session.reports.items()},
        "subjects": dict(subjects(poses)),
        "writer": m.get("writer"),
        "rig": rig,
    }
    print(json.dumps(info, indent=2))
    return 0


def _names(items: object, key: str) -> list[str]:
    """Names of a manifest's cameras or suits; "?" where a damaged manifest has none (``session`` still reports)."""
    if not isinstance(items, list):
        return []
    return [str(x[key]) if isinstance(x, dict) and key in x else "?" for x in items]


def _guard(func: Any) -> Any:
    def run(args: argparse.Namespace) -> int:
        try:
            result: int = func(args)
        except MocapdError as exc:  # input, config, model: each a one-line message
            print(f"error: {exc}", file=sys.stderr)
            return 2
        return result

    return run


def register(subparsers: Any) -> None:
    """Add replay, resolve, export and session to the CLI."""
    rp = subparsers.add_parser("replay", help="stream a recorded session through the configured sinks, as if live")
    rp.add_argument("session", type=Path, help="session directory")
    rp.add_argument(
        "--speed", type=number(0.01, 1000.0), default=1.0, help="playback speed (default 1 = recorded pace)"
    )
    rp.add_argument("--resolved", action="store_true", help="replay the resolved poses instead of the live ones")
    rp.add_argument("--poses", type=Path, default=None, metavar="FILE",
                    help="replay this pose stream file (written by `mocapd resolve SESSION -o FILE`)")  # fmt: skip
    rp.add_argument("--config", type=Path, default=None, help="config file with the stream sinks (default: shipped)")
    rp.add_argument("--verbose", action="store_true", help="print a line per second of session time")
    rp.set_defaults(func=_guard(cmd_replay))

    rs = subparsers.add_parser("resolve", help="re-solve a session offline: all frames, more iterations, smoothing")
    rs.add_argument("session", type=Path, help="session directory")
    rs.add_argument("-o", "--output", type=Path, default=None, metavar="FILE",
                    help="write the resolved pose stream to FILE instead of SESSION/poses-resolved.mcs (to keep "
                    "several re-solves side by side); `mocapd export SESSION --poses FILE` reads it")  # fmt: skip
    rs.add_argument(
        "--iterations", type=number(1, 10_000, integer=True), default=100, help="LM iterations per frame (default 100)"
    )
    rs.add_argument("--no-smooth", action="store_true", help="skip the forward-backward (RTS) smoother")
    rs.add_argument("--force", action="store_true", help="replace an existing -o file")
    rs.set_defaults(func=_guard(cmd_resolve))

    ex = subparsers.add_parser("export", help="export a session's subjects as glTF/FBX, one of them as BVH and/or CSV")
    ex.add_argument("session", type=Path, help="session directory")
    ex.add_argument("--bvh", type=Path, default=None, help="BVH file to write (21-bone skeleton, cm)")
    ex.add_argument("--csv", type=Path, default=None, help="CSV file to write (columns in docs/sessions.md)")
    ex.add_argument("--gltf", type=Path, default=None,
                    help="glTF 2.0 binary (.glb) to write: skinned armature + one animation per subject")  # fmt: skip
    ex.add_argument("--subject", default=None,
                    help="identity, e.g. suit:suit0 or track:1 (BVH/CSV: the most seen; glTF/FBX: all)")  # fmt: skip
    ex.add_argument("--fbx", type=Path, default=None,
                    help="FBX to write through Blender: every subject's armature + skinned mesh, one take")  # fmt: skip
    ex.add_argument("--fbx-units", choices=("cm", "m"), default="cm",
                    help="FBX lengths: cm (default; Unreal, Maya) or m; Unity and Blender read both")  # fmt: skip
    ex.add_argument("--fbx-up", choices=("y", "z"), default="y",
                    help="FBX up axis: y (default; Maya, Unity, MotionBuilder) or z (Blender, 3ds Max)")  # fmt: skip
    ex.add_argument("--blender", default=None,
                    help="Blender for --fbx: a blender executable or a Python with bpy (default: $MOCAPD_BLENDER, "
                    "the checkout's .venv-bpy, blender on PATH)")  # fmt: skip
    ex.add_argument("--rate", type=number(1.0, 1000.0), default=60.0, help="output frame rate, Hz (default 60)")
    ex.add_argument("--resolved", action="store_true", help="export the resolved poses instead of the live ones")
    ex.add_argument("--poses", type=Path, default=None, metavar="FILE",
                    help="export this pose stream file (written by `mocapd resolve SESSION -o FILE`)")  # fmt: skip
    ex.add_argument("--force", action="store_true", help="replace existing output files (refused otherwise)")
    ex.set_defaults(func=_guard(cmd_export))

    info = subparsers.add_parser("session", help="describe a session and check its streams (recovery report)")
    info.add_argument("session", type=Path, help="session directory")
    info.set_defaults(func=_guard(cmd_info))
