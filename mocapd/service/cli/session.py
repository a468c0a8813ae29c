"""``mocapd replay``, ``mocapd resolve``, ``mocapd export`` and ``mocapd session`` (recorded sessions)."""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
from dataclasses import asdict
from pathlib import Path
from typing import Any

from mocapd.core.skeleton import Skeleton
from mocapd.errors import ConfigError, InputError
from mocapd.io.session import RESOLVED, Session, open_session
from mocapd.pipeline.scheduler import PoseFrame
from mocapd.service.config import Config, load_config
from mocapd.service.daemon import PoseSink


def stream_sinks(config: Config, skeleton: Skeleton, output: str = "delayed") -> list[PoseSink]:
    """The streaming sinks a replay publishes through: the streams configured in ``config``, for poses on the
    session's ``skeleton``, announcing the recorded ``output`` mode."""
    from mocapd.service.outputs.udp import udp_sinks
    from mocapd.service.outputs.websocket import websocket_sinks

    return [*udp_sinks(config, skeleton), *websocket_sinks(config, skeleton, output=output)]


def _open(path: Path) -> Session:
    session = open_session(path)
    session.check()
    for line in session.recovery_lines():
        print(f"note: {line}", file=sys.stderr)
    return session


def _pose_stream(session: Session, resolved: bool) -> str:
    if resolved and not session.has_stream(RESOLVED):
        raise InputError(f"{session.path}: no resolved poses yet (run `mocapd resolve {session.path}`)")
    return RESOLVED if resolved else "poses"


def cmd_replay(args: argparse.Namespace) -> int:
    from mocapd.service.session.replay import replay
    from mocapd.service.session.solve import session_rig

    cfg = load_config(args.config)
    session = _open(args.session)
    frames = session.poses(_pose_stream(session, args.resolved))
    sinks = stream_sinks(cfg, session_rig(session).skeleton, frames[0].output if frames else "delayed")
    last = [0.0]

    def progress(frame: PoseFrame) -> None:
        t = (frame.t_solve_ns - frames[0].t_solve_ns) / 1e9
        if args.verbose and t - last[0] >= 1.0:
            last[0] = t
            print(f"t={t:6.1f} s  frame {frame.frame}  people [{', '.join(p.identity for p in frame.people)}]",
                  flush=True)  # fmt: skip

    print(f"mocapd replay: {len(frames)} frames through {len(sinks)} sink(s) at {args.speed:g}x", flush=True)
    stats = asyncio.run(replay(frames, sinks, speed=args.speed, on_frame=progress))
    print(json.dumps(asdict(stats)))
    return 0


def cmd_resolve(args: argparse.Namespace) -> int:
    from mocapd.service.session.solve import ResolveOptions, resolve, write_resolved
    from mocapd.service.session.truth import truth_report

    session = _open(args.session)
    opts = ResolveOptions(max_iterations=args.iterations, smooth=not args.no_smooth)
    frames, summary = resolve(session, opts)
    path = write_resolved(session, frames, args.output)
    summary["written"] = str(path)
    if "synthetic" in session.manifest.get("extra", {}):
        summary["error_vs_truth_mm"] = truth_report(session, {"live": session.poses(), "resolved": frames})
    print(json.dumps(summary, indent=2, default=str))
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    from mocapd.io.session_export import resample, subject_track, write_bvh, write_csv
    from mocapd.service.session.solve import session_rig

    if args.bvh is None and args.csv is None:
        print("error: nothing to export: give --bvh FILE and/or --csv FILE", file=sys.stderr)
        return 2
    session = _open(args.session)
    track = resample(subject_track(session.poses(_pose_stream(session, args.resolved)), args.subject), args.rate)
    # The subject's body-sized skeleton when one was recorded (the first seconds of a track, before sizing,
    # were solved on the rig's; their joint angles export on the sized one), else the rig's.
    skeleton = track.skeleton if track.skeleton is not None else session_rig(session).skeleton
    out: dict[str, Any] = {"subject": track.subject, "frames": int(track.thetas.shape[0]), "rate_hz": args.rate}
    if args.bvh is not None:
        write_bvh(args.bvh, skeleton, track, args.rate)
        out["bvh"] = str(args.bvh)
    if args.csv is not None:
        write_csv(args.csv, skeleton, track)
        out["csv"] = str(args.csv)
    print(json.dumps(out))
    return 0


def cmd_info(args: argparse.Namespace) -> int:
    from mocapd.io.session_export import subjects

    session = _open(args.session)
    m = session.manifest
    info = {
        "path": str(session.path),
        "closed_cleanly": session.closed_cleanly,
        "started_utc": m.get("started_utc"),
        "software": m.get("software"),
        "cameras": [c["name"] for c in m.get("cameras", [])],
        "suits": [s["id"] for s in m.get("suits", [])],
        "streams": {k: asdict(v) for k, v in session.reports.items()},
        "subjects": dict(subjects(session.poses())),
        "writer": m.get("writer"),
    }
    print(json.dumps(info, indent=2))
    return 0


def _guard(func: Any) -> Any:
    def run(args: argparse.Namespace) -> int:
        try:
            result: int = func(args)
        except (InputError, ConfigError) as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        return result

    return run


def register(subparsers: Any) -> None:
    """Add replay, resolve, export and session to the CLI."""
    rp = subparsers.add_parser("replay", help="stream a recorded session through the configured sinks, as if live")
    rp.add_argument("session", type=Path, help="session directory")
    rp.add_argument("--speed", type=float, default=1.0, help="playback speed (default 1 = recorded pace)")
    rp.add_argument("--resolved", action="store_true", help="replay the resolved poses instead of the live ones")
    rp.add_argument("--config", type=Path, default=None, help="config file with the stream sinks (default: shipped)")
    rp.add_argument("--verbose", action="store_true", help="print a line per second of session time")
    rp.set_defaults(func=_guard(cmd_replay))

    rs = subparsers.add_parser("resolve", help="re-solve a session offline: all frames, more iterations, smoothing")
    rs.add_argument("session", type=Path, help="session directory")
    rs.add_argument("-o", "--output", type=Path, default=None,
                    help="write the resolved stream here (default: SESSION/poses-resolved.mcs)")  # fmt: skip
    rs.add_argument("--iterations", type=int, default=100, help="LM iterations per frame (default 100)")
    rs.add_argument("--no-smooth", action="store_true", help="skip the forward-backward (RTS) smoother")
    rs.set_defaults(func=_guard(cmd_resolve))

    ex = subparsers.add_parser("export", help="export one subject of a session as BVH and/or CSV")
    ex.add_argument("session", type=Path, help="session directory")
    ex.add_argument("--bvh", type=Path, default=None, help="BVH file to write (21-bone skeleton, cm)")
    ex.add_argument("--csv", type=Path, default=None, help="CSV file to write (columns in docs/sessions.md)")
    ex.add_argument("--subject", default=None, help="identity, e.g. suit:suit0 or track:1 (default: most seen)")
    ex.add_argument("--rate", type=float, default=60.0, help="output frame rate, Hz (default 60)")
    ex.add_argument("--resolved", action="store_true", help="export the resolved poses instead of the live ones")
    ex.set_defaults(func=_guard(cmd_export))

    info = subparsers.add_parser("session", help="describe a session and check its streams (recovery report)")
    info.add_argument("session", type=Path, help="session directory")
    info.set_defaults(func=_guard(cmd_info))
