"""A camera knocked mid-take in the running daemon, on the synthetic rig (issue 43, "cameras that stay calibrated").

Developer benchmark, not a ``mocapd bench`` verb (those are the benchmarks a user runs).

The real daemon (``mocapd demo --synthetic``'s assembly, suits off, recording a session) runs until every camera
has a baseline; then one camera of the simulated world is turned on its mount (:meth:`SyntheticWorld.bump`; the
rig's calibration unchanged) and the take goes on until the camera watch has named it, re-estimated it, applied
the re-estimate (``[calibration.watch] apply``) and the camera agrees with the others again. Measured: the time
from the knock to *bumped*, to the re-estimate and to the change applied (solve times, counted from the first solve
that can see a turned frame), and the published poses' keypoint-site error against the synthetic truth before the
knock, between it and the camera left out, while it is left out, and after the change; then ``mocapd resolve`` of the
recorded session (its camera event followed) and of a copy without its events (the old calibration throughout).

    python -m tools.bench_camera_bump --degrees 2 --axis x --after 8

Prints one JSON document.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import shutil
import tempfile
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mocapd.core.rotations import matrix_from_rotvec
from mocapd.io.session import EVENTS, SUFFIX, open_session
from mocapd.pipeline.scheduler import PoseFrame
from mocapd.protocols.session_format import PoseRecord
from mocapd.service.assembly import RunOptions, assembled
from mocapd.service.config import Config, load_config
from mocapd.service.daemon import Daemon
from mocapd.service.demo.synthetic import synthetic_config
from mocapd.service.session.solve import ResolveOptions, resolve
from mocapd.sim.world import SyntheticWorld

AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}
"""Turns in the camera's own frame: x tilts it (up/down), y pans it, z rolls it about its optical axis."""


class Frames:
    """A pose sink keeping every published frame."""

    name = "bump-frames"

    def __init__(self) -> None:
        self.frames: list[PoseFrame] = []

    def publish(self, frame: PoseFrame) -> None:
        self.frames.append(frame)

    async def start(self) -> None:
        return None

    async def aclose(self) -> None:
        return None


@dataclass
class BumpedTake:
    """What one run gave: the instants (host ns) and the published frames, for :func:`phase_errors`."""

    bump_ns: int  # host time the camera turned (its first frame rendered turned)
    seen_ns: int  # the earliest solve time whose keypoints can come from a turned frame (see bumped_take)
    epoch_ns: int
    events: list[tuple[int, str, str, dict[str, Any]]]  # the watch's (solve ns, camera, what, details)
    changes: list[dict[str, Any]]  # /status camera_changes
    frames: list[PoseFrame]
    states_after: list[str]
    session: Path | None
    world: SyntheticWorld
    in_doubt_ns: list[int] = field(default_factory=list)  # solve times of the person solves without the camera
    used_ns: list[int] = field(default_factory=list)  # ... and with it, since the bump
    status_after: dict[str, Any] = field(default_factory=dict)  # /status camera_watch at the end


def bump_config(cameras: int = 4, apply: bool = True) -> Config:
    """The synthetic rig of the shipped config: ``cameras`` cameras, two people, no suits, the watch on, any free
    ports."""
    cfg = load_config()
    cfg = cfg.model_copy(update={
        "daemon": cfg.daemon.model_copy(update={"http_port": 0}),
        "websocket": cfg.websocket.model_copy(update={"port": 0}),
        "synthetic": cfg.synthetic.model_copy(update={"suits": 0}),
    })  # fmt: skip
    rig = synthetic_config(cfg, cameras)
    watch = rig.calibration.watch.model_copy(update={"enabled": True, "apply": apply})
    return rig.model_copy(update={"calibration": rig.calibration.model_copy(update={"watch": watch})})


async def wait_until(cond: Any, timeout_s: float, what: str) -> None:
    loop = asyncio.get_running_loop()
    end = loop.time() + timeout_s
    while not cond():
        if loop.time() > end:
            raise TimeoutError(f"timed out waiting for {what}")
        await asyncio.sleep(0.05)


async def bumped_take(
    config: Config,
    *,
    camera: int = 1,
    degrees: float = 2.0,
    axis: str = "x",
    after_s: float = 8.0,
    record: Path | None = None,
    timeout_s: float = 120.0,
    at_end: Callable[[Daemon], Awaitable[None]] | None = None,
) -> BumpedTake:
    """Run the daemon of ``config`` (a synthetic rig), turn ``camera`` by ``degrees`` about ``axis`` once every
    camera has a baseline, and go on until the change is applied (or, with ``apply`` off, re-estimated) and then
    ``after_s`` more seconds; then ``at_end`` (the daemon still running), if given."""
    frames = Frames()
    with assembled(config, RunOptions(sinks=[frames], record=record)) as demo:
        d = demo.daemon
        world = demo.built.world
        assert d.camera_watch is not None and world is not None, "the synthetic rig with the camera watch"
        task = asyncio.create_task(d.run())
        try:
            await asyncio.wait_for(d.ready.wait(), 300)
            watch = d.camera_watch.watch
            n = len(watch.cameras)
            await wait_until(lambda: watch.states() == ["ok"] * n, timeout_s, "every camera's baseline")
            bump_ns = d.clock()
            # A synthetic frame captured at t is rendered (with the world's cameras then) at t + detection_delay_s,
            # and a solve at t blends the frames around t: solves from here on may see the turned camera.
            syn = config.synthetic
            seen_ns = bump_ns - round((syn.detection_delay_s + 1.0 / syn.camera_rate_hz) * 1e9)
            world.bump(camera, matrix_from_rotvec(np.radians(degrees) * np.array(AXES[axis])))
            doubt: list[int] = []
            used: list[int] = []
            hook = d.scheduler.observation_hook
            assert hook is not None

            def spy(t: int, uv: Any, conf: Any, person: str) -> Any:
                out = hook(t, uv, conf, person)
                if np.any(conf[camera] > 0):
                    (doubt if np.all(out[camera] == 0) else used).append(t)
                return out

            d.scheduler.observation_hook = spy
            if watch.options.apply:
                await wait_until(lambda: bool(d.camera_changes), timeout_s, "the re-estimate applied")
            else:
                await wait_until(lambda: watch.proposal(camera) is not None, timeout_s, "the re-estimate")
            await asyncio.sleep(after_s)
            changes = d.status()["camera_changes"]
            states = watch.states()
            events = list(watch.events)
            status = d.camera_watch.status()
            if at_end is not None:
                await at_end(d)
        finally:
            d.request_stop()
            await asyncio.wait_for(task, 30)
        return BumpedTake(bump_ns, seen_ns, demo.built.epoch_ns, events, changes, frames.frames, states, record,
                          world, doubt, used, status)  # fmt: skip


def person_errors_mm(
    world: SyntheticWorld, epoch_ns: int, frames: list[PoseFrame] | list[PoseRecord]
) -> list[tuple[int, float]]:
    """(solve time, keypoint-site error mm) of every published person against the nearest true person."""
    out = []
    for f in frames:
        for p in f.people:
            e, _ = world.nearest_site_error(p.theta, p.skeleton, (f.t_solve_ns - epoch_ns) / 1e9)
            out.append((f.t_solve_ns, e * 1e3))
    return out


def phase_errors(errors: list[tuple[int, float]], bounds: dict[str, tuple[int, int]]) -> dict[str, dict[str, float]]:
    """Median, p95 and max error (mm) per phase (solve-time span [a, b)) and the person-frames ``n``."""
    out: dict[str, dict[str, float]] = {}
    for name, (a, b) in bounds.items():
        v = np.array([e for t, e in errors if a <= t < b])
        out[name] = (
            {"n": int(v.size), "median": round(float(np.median(v)), 1), "p95": round(float(np.percentile(v, 95)), 1),
             "max": round(float(v.max()), 1)} if v.size else {"n": 0}
        )  # fmt: skip
    return out


def report(take: BumpedTake, camera: int = 1, settle_s: float = 1.0) -> dict[str, Any]:
    """The times and the phases' errors of a take (see the module docstring)."""
    name = f"cam{camera}"
    first = {what: t for t, cam, what, _ in reversed(take.events) if cam == name}
    named, estimated = first.get("bumped"), first.get("re-estimated")
    applied = take.changes[0]["t_solve_ns"] if take.changes else None
    out: dict[str, Any] = {
        "noticed_s": None if named is None else round((named - take.seen_ns) / 1e9, 2),
        "re_estimated_s": None if estimated is None else round((estimated - take.seen_ns) / 1e9, 2),
        "applied_s": None if applied is None else round((applied - take.seen_ns) / 1e9, 2),
        "first_left_out_s": round((min(take.in_doubt_ns) - take.seen_ns) / 1e9, 2) if take.in_doubt_ns else None,
        "change": take.changes[0] if take.changes else None,
        "states_after": take.states_after,
    }
    if applied is not None:
        truth = take.world.cameras[camera]
        R = np.array(take.changes[0]["R"])
        out["applied_vs_truth_deg"] = round(
            float(np.degrees(np.arccos(np.clip((np.trace(R @ truth.R.T) - 1) / 2, -1, 1)))), 3
        )
    start = take.frames[0].t_solve_ns if take.frames else take.bump_ns
    end = take.frames[-1].t_solve_ns + 1 if take.frames else take.bump_ns
    left_out = min(take.in_doubt_ns) if take.in_doubt_ns else take.seen_ns
    back = applied if applied is not None else end
    bounds = {
        "before": (start + 2_000_000_000, take.seen_ns),  # after enrolment and body sizing
        "bumped, still in the solve": (take.seen_ns, left_out),
        "left out": (left_out, back),
        "applied": (back + round(settle_s * 1e9), end),
    }
    out["published_mm"] = phase_errors(person_errors_mm(take.world, take.epoch_ns, take.frames), bounds)
    if take.session is not None:
        session = open_session(take.session)
        opts = ResolveOptions(max_iterations=20, smooth=False)
        followed, summary = resolve(session, opts)
        out["resolve_camera_changes"] = summary["camera_changes"]
        out["resolved_mm"] = phase_errors(person_errors_mm(take.world, take.epoch_ns, followed), bounds)
        with tempfile.TemporaryDirectory() as tmp:
            copy = Path(tmp) / "session"
            shutil.copytree(take.session, copy)
            (copy / f"{EVENTS}{SUFFIX}").unlink()
            ignored, _ = resolve(open_session(copy), opts)
        out["resolved_without_events_mm"] = phase_errors(person_errors_mm(take.world, take.epoch_ns, ignored), bounds)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cameras", type=int, default=4)
    ap.add_argument("--camera", type=int, default=1, help="the camera turned")
    ap.add_argument("--degrees", type=float, default=2.0)
    ap.add_argument("--axis", choices=sorted(AXES), default="x", help="x tilt, y pan, z roll (camera frame)")
    ap.add_argument("--after", type=float, default=8.0, help="seconds run after the change is applied")
    ap.add_argument("--no-apply", action="store_true", help="[calibration.watch] apply = false")
    ap.add_argument("--no-record", action="store_true", help="no session (no resolve numbers)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        record = None if args.no_record else Path(tmp) / "session"
        config = bump_config(args.cameras, not args.no_apply)
        take = asyncio.run(bumped_take(config, camera=args.camera, degrees=args.degrees, axis=args.axis,
                                       after_s=args.after, record=record))  # fmt: skip
        print(json.dumps(report(take, args.camera), indent=1))


if __name__ == "__main__":
    main()
