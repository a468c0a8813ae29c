"""``mocapd bench record``: the session recorder: write rate, bytes per minute, tick-loop cost, resolve speed.

A 4-subject synthetic session (4 cameras at 30 Hz, 4 suits of 13 IMUs at 100 Hz, poses of 4 people at 60 Hz):

- ``realtime``: the session's inputs are given to a real
  :class:`~mocapd.service.outputs.recorder.SessionRecorder` at their real pace for ``--seconds``, each call
  (``publish`` of a frame, the keypoint and IMU taps) timed; the baseline is the same calls on a sink that only
  appends to a list, timed in the same loop. Also: bytes per minute per stream,
  records dropped (0 expected), the writer's deepest queue.
- ``throughput``: the same records given as fast as possible to a writer with a large queue, until it has written
  them all (flushes and fsyncs included): records/s and MB/s the writer thread sustains.
- ``resolve``: ``mocapd resolve``'s two passes on the realtime session: output frames per second.

Usage: ``mocapd bench record [--seconds 10] [--repeats 3]`` (medians over repeats).
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mocapd.core.sorting import Detections2D
from mocapd.io.session import SessionWriter, open_session
from mocapd.io.xsens_serial import ImuSample
from mocapd.pipeline.scheduler import PersonPose, PoseFrame, Suit
from mocapd.service.bench.solver import synthetic_prior
from mocapd.service.config import load_config
from mocapd.service.daemon import Daemon, Rig
from mocapd.service.outputs.recorder import attach_recorder, synthetic_extra
from mocapd.service.session.solve import resolve
from mocapd.sim.world import SyntheticWorld

PEOPLE, CAMERAS, CAMERA_HZ, IMU_HZ, POSE_HZ = 4, 4, 30.0, 100.0, 60.0


@dataclass
class Event:
    t_ns: int
    kind: str  # "pose", "kp", "imu"
    args: tuple[Any, ...]


def session_events(world: SyntheticWorld, epoch: int, seconds: float) -> list[Event]:
    """The inputs and outputs of ``seconds`` of the session, in time order."""
    rng = np.random.default_rng(0)
    events: list[Event] = []
    period = round(1e9 / POSE_HZ)
    for k in range(int(seconds * POSE_HZ)):
        t = epoch + k * period
        people = []
        for p in range(PEOPLE):
            th = world.theta_at(p, (t - epoch) / 1e9)
            people.append(PersonPose(f"suit:suit{p}", p + 1, f"suit{p}", th, world.kin.forward(th).positions, 0.9,
                                     CAMERAS, 13, 6, True))  # fmt: skip
        events.append(Event(t, "pose", (PoseFrame(k + 1, t, t + 150_000_000, people, 0),)))
    cam_period = round(1e9 / CAMERA_HZ)
    for c in range(CAMERAS):
        for k in range(int(seconds * CAMERA_HZ)):
            t = epoch + c * cam_period // CAMERAS + k * cam_period
            dets: Detections2D = world.detections(c, (t - epoch) / 1e9, rng)
            events.append(Event(t + 50_000_000, "kp", (c, t, dets, t + 50_000_000)))
    n = int(seconds * IMU_HZ)
    for suit in world.suits:
        quats, accs = world.imu_motion(suit, IMU_HZ)
        for s, sid in enumerate(suit.sensor_ids):
            for k in range(n):
                t = epoch + round(k * 1e9 / IMU_HZ)
                q, a = tuple(quats[s, k % quats.shape[1]]), tuple(accs[s, k % accs.shape[1]])
                sample = ImuSample(f"{sid:08X}", t + 2_000_000, k * 100, k & 0xFFFF, q, a, None)
                events.append(Event(t + 2_000_000, "imu", (sample, q, t)))
    events.sort(key=lambda e: e.t_ns)
    return events


class ListSink:
    """The baseline: a sink and taps that only keep what they are given."""

    def __init__(self) -> None:
        self.items: list[Any] = []

    def publish(self, frame: PoseFrame) -> None:
        self.items.append(frame)

    def on_detections(self, camera: int, capture_ns: int, dets: Detections2D, arrival_ns: int) -> None:
        self.items.append(dets)

    def on_imu(self, s: ImuSample, quat: tuple[float, ...] | None, t: int | None) -> None:
        self.items.append(s)


def _call(target: Any, e: Event) -> None:
    if e.kind == "pose":
        target.publish(*e.args)
    elif e.kind == "kp":
        target.on_detections(*e.args)
    else:
        target.on_imu(*e.args)


def _daemon(world: SyntheticWorld) -> Daemon:
    cfg = load_config()
    suits = [Suit.from_calibration(s.id, world.calibration(s), world.skeleton) for s in world.suits]
    rig = Rig(world.cameras, [], world.skeleton, world.targets, synthetic_prior(), suits)
    return Daemon(cfg, rig)


def realtime(world: SyntheticWorld, epoch: int, events: list[Event], seconds: float, path: Path) -> dict[str, Any]:
    daemon = _daemon(world)
    syn = daemon.config.synthetic.model_copy(update={"people": PEOPLE, "suits": PEOPLE})
    names = [c.name for c in world.cameras]
    rec = attach_recorder(daemon.config, daemon, path, extra={"synthetic": synthetic_extra(syn, names, epoch)})
    assert rec is not None
    rec.writer.open()
    base = ListSink()
    cost: dict[str, list[int]] = {"pose": [], "kp": [], "imu": []}
    baseline: dict[str, list[int]] = {"pose": [], "kp": [], "imu": []}
    start = time.monotonic_ns()
    for i, e in enumerate(events):
        due = start + (e.t_ns - events[0].t_ns)
        delay = (due - time.monotonic_ns()) / 1e9
        if delay > 0:
            time.sleep(delay)
        first, second = (base, rec) if i % 2 else (rec, base)  # neither always pays for waking up
        t0 = time.perf_counter_ns()
        _call(first, e)
        t1 = time.perf_counter_ns()
        _call(second, e)
        t2 = time.perf_counter_ns()
        (baseline if first is base else cost)[e.kind].append(t1 - t0)
        (cost if first is base else baseline)[e.kind].append(t2 - t1)
    rec.writer.close()
    c = rec.writer.counters
    sizes = {p.stem: p.stat().st_size for p in path.glob("*.mcs")}
    return {
        "session_s": seconds,
        "records": c.written,
        "dropped": c.dropped,
        "max_queue": c.max_queue,
        "records_per_s": round(c.written / seconds, 1),
        "bytes_per_minute": {k: round(v / seconds * 60) for k, v in sizes.items()}
        | {"total": round(sum(sizes.values()) / seconds * 60)},
        "mb_per_minute": round(sum(sizes.values()) / seconds * 60 / 1e6, 2),
        "call_us": {k: _pct(v) for k, v in cost.items()},
        "baseline_list_append_us": {k: _pct(v) for k, v in baseline.items()},
    }


def _pct(ns: list[int]) -> dict[str, float]:
    a = np.array(ns) / 1e3
    return {"median": round(float(np.median(a)), 2), "p95": round(float(np.percentile(a, 95)), 2), "n": len(ns)}


def throughput(events: list[Event], path: Path, copies: int) -> dict[str, float]:
    from mocapd.service.outputs.recorder import SessionRecorder

    w = SessionWriter(path, {"format": "mocapd-session", "version": 1}, queue_size=10_000_000)
    rec = SessionRecorder(w)
    w.open()
    t0 = time.perf_counter()
    for _ in range(copies):
        for e in events:
            _call(rec, e)
    w.close()
    dt = time.perf_counter() - t0
    return {"records_per_s": round(w.counters.written / dt), "mb_per_s": round(w.counters.bytes / dt / 1e6, 2),
            "records": w.counters.written, "dropped": w.counters.dropped}  # fmt: skip


def run(seconds: float = 10.0, repeats: int = 3, resolve_seconds: float = 4.0) -> dict[str, Any]:
    """The recorder's realtime cost, throughput and resolve speed on the 4-subject synthetic session."""
    load0 = os.getloadavg()
    world = SyntheticWorld(CAMERAS, PEOPLE, PEOPLE, seed=0)
    epoch = time.monotonic_ns()
    events = session_events(world, epoch, seconds)
    tmp = Path(tempfile.mkdtemp(prefix="bench-record-"))
    try:
        rt = [realtime(world, epoch, events, seconds, tmp / f"rt{i}") for i in range(repeats)]
        tp = [throughput(events, tmp / f"tp{i}", 3) for i in range(repeats)]
        short = session_events(world, epoch, resolve_seconds)
        realtime(world, epoch, short, resolve_seconds, tmp / "resolve")
        s = open_session(tmp / "resolve")
        s.check()
        t0 = time.perf_counter()
        frames, summary = resolve(s)
        dt = time.perf_counter() - t0
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    median = rt[int(np.argsort([r["call_us"]["pose"]["median"] for r in rt])[len(rt) // 2])]
    out = {
        "rig": {"subjects": PEOPLE, "pose_hz": POSE_HZ, "cameras": CAMERAS, "camera_hz": CAMERA_HZ,
                "imus": 13 * PEOPLE, "imu_hz": IMU_HZ},
        "realtime_median_run": median,
        "realtime_pose_publish_median_us_per_run": [r["call_us"]["pose"]["median"] for r in rt],
        "throughput": {"records_per_s": float(np.median([t["records_per_s"] for t in tp])),
                       "mb_per_s": float(np.median([t["mb_per_s"] for t in tp])), "runs": tp},
        "resolve": {"session_s": resolve_seconds, "frames": len(frames),
                    "person_solves": summary["person_solves"], "wall_s": round(dt, 2),
                    "frames_per_s": round(len(frames) / dt, 1),
                    "person_solves_per_s": round(summary["person_solves"] / dt, 1)},
        "load_average": {"start": [round(x, 2) for x in load0], "end": [round(x, 2) for x in os.getloadavg()]},
        "cpus": os.cpu_count(),
    }  # fmt: skip
    return out
