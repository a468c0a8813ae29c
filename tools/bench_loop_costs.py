"""Per-function cost of the event loop's work (synthetic and camera rigs) against a git revision's code, in one process.

Developer benchmark, not a ``mocapd bench`` verb.

The whole pipeline's rate on a shared machine is noise; this times each piece of the loop's own work on the same
input with the revision's module and the working tree's, alternately (``--rounds`` rounds, each timing both once),
and prints the median of each and their ratio, with the CPU it ran on. The revision's modules are loaded from
``git show REV:path`` under another name, beside the working tree's. Pieces:

* ``watch``: :class:`~mocapd.core.camera_watch.CameraWatch` over 20 s of two people at 60 solves a second (a
  check 10 times a second), per ``observe`` call; ``screen``: the same with each person named as the daemon names
  them (their solves screened ``screen_hz`` times a second) against the revision's, and the working tree's at
  screening rates of 60 to 10 Hz (median of a third of the rounds, µs per call); ``people``: both sides with
  the people named; ``levels``: its per-check
  ``_levels`` alone; ``left_out``,
  ``all_in``: ``residuals_left_out`` (per person and check) and ``residuals_all_in`` (per solve) over its moments,
  and ``residuals_left_out`` of people roughed up (40 % of the keypoints unseen or under the confidence floor);
  ``pool``: a check's people pooled per camera (``np.nanmedian`` of 2 people x 4 cameras before, per check).
* ``mtdata2``: :func:`~mocapd.protocols.mtdata2.decode_mtdata2` per message, on an MTw-like stream (packet
  counter, sample time, quaternion, acceleration: the simulated suit's) and on the real MTi captures in
  ``tests/data/xbus_einride`` (with UTC time and GNSS outputs).
* ``heading``: :func:`~mocapd.core.heading.observe_headings` per observation of a 13-sensor suit (COCO-17
  keypoints of a posed body); ``estimator``: :meth:`~mocapd.core.heading.HeadingEstimator.observe` of its 13
  sensors with full 4 s windows (80 samples each).

* ``collapse``: :func:`~mocapd.core.lr_collapse.collapsed_pairs` per person and solve, on the camera watch's
  take (two people walking, detector-like noise and limb swaps), with no previous pose; the candidates (view and
  pair) a call checks are reported beside it.

* ``nearest``: the tracker's other-views check of one camera (``tracking._nearest_is``: a subject's keypoints
  projected and compared with a view's people) per call, the demo's people seen by 4 distorted cameras, the
  revision's tracking module.

* ``sim``: :meth:`~mocapd.sim.xsens.SimDevice.next_message` per message, the simulated suit's stored outputs
  (packet counter, fine sample time, quaternion, acceleration at 100 Hz), the motion's packets cached.

* ``frames``: :meth:`~mocapd.sim.world.SyntheticWorld.detections` per camera frame of the demo's world (the
  shipped ``[synthetic]`` people and motion, four cameras).

* ``imu_inputs``: :meth:`~mocapd.service.imu_inputs.ImuInputs.on_sample` per sample of a sensor with a device
  heading (every suit sensor once the heading estimator has turned it), on the real MTw recording of
  ``tests/data/opensense_mtw`` as a simulated MTw's bytes decode to (600 samples); ``dispatch``: the same bytes
  through the session and :class:`~mocapd.io.xsens_serial.XsensSerialDevice`'s dispatch to its callback, per
  sample (1 to 4 messages a read); ``ingest``: :meth:`~mocapd.pipeline.imu_ingest.ImuIngest.add` of those samples
  (clock map, ring buffer), the revision's ring buffer with the revision's ingest; ``imu_path``: all of it, bytes
  to buffer through the device's dispatch and ``on_sample`` with a device heading (each side its own modules).

* ``speed``: :func:`~mocapd.pipeline.time_alignment.keypoint_speed` of one camera's kept frames (256 frames of a
  synthetic 4-camera rig's 30 Hz detections of 2 people, what a timeline keeps), per call; ``offsets``: the
  cameras' whole offset estimate (:func:`~mocapd.pipeline.scheduler.estimate_camera_offsets` of the 4 cameras:
  their speeds, then the lag searches), per call, the speeds the revision's or the working tree's.

* ``arrive``: :meth:`~mocapd.pipeline.scheduler.FixedLatencyScheduler.add_detections` per keypoint set (2 people of
  the synthetic ring seen by 4 cameras with lens distortion, the delay following the detector), the revision's
  scheduler with the revision's latency accounting.

* ``sample``: :meth:`~mocapd.pipeline.keypoint_timeline.DetectionTimeline.sample` per look-up, 60 Hz look-ups
  between one camera's 30 Hz frames of 2 people (with their undistorted copies; a matching per bracket, a blend
  per look-up), the revision's timeline module, and at 60 Hz frames (a matching and a blend per look-up); ``blend``: its
  :func:`~mocapd.pipeline.keypoint_timeline.interpolate_people` alone, pairs given.

* ``collapse``: :func:`~mocapd.core.lr_collapse.collapsed_pairs` per person solve (a walking person seen by 4
  cameras, one view with the right arm put on the left one, the previous pose given), the revision's module.

* ``triangulate``: :func:`~mocapd.core.camera.weighted_dlt_rows` (4 cameras, 17 points: a left-out check's) and
  :func:`~mocapd.core.camera.triangulate_arrays` of 4 points (two candidates of the collapse check) and of 17 by the
  normal equations (a camera watch screen's), per call, the revision's camera module; ``collapse`` then runs the
  revision's collapse check with the revision's triangulation.

* ``solve``: :meth:`~mocapd.core.solver.PoseSolver.solve` per call, a walking person seen by 4 cameras (no IMU: the
  camera rig's, the compiled LM loop), the revision's solver with the revision's observations and rotations; its
  glue alone: ``push_history`` (the IMU sites of a camera-only person) and ``principal_pose``.

* ``validate``: :class:`~mocapd.core.observations.ValidatedObservations` per person solve (4 cameras' 17 keypoints,
  no IMU: the camera rig's), the revision's module.

* ``plausibility``: :meth:`~mocapd.core.plausibility.PlausibilityMonitor.step` per solved pose, the revision's
  module: the demo's two people (the shipped ``[synthetic]`` motion) at 60 Hz, and a person walking a circle
  (:func:`~mocapd.core.synthetic.moving_sequence`, whose elbows bend the wrong way a third of the time: the
  monitor's slower path).

* ``track``: :meth:`~mocapd.core.tracking.SubjectTracker.update` per output tick (the scheduler's sort stage): the
  demo's two people seen by 4 cameras with lens distortion at 60 Hz, two ticks a detector pass, both enrolled;
  the revision's tracking module with the revision's sorting module (and the pairing kernel without pruning).

Run: ``PYTHONPATH=$PWD python tools/bench_loop_costs.py --rev main [--rounds 15] [--only watch,levels]``.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def module_at(rev: str, path: str, name: str) -> ModuleType:
    """The module at ``path`` (relative to the repository) as it is at git revision ``rev``, as ``name``."""
    source = subprocess.run(["git", "show", f"{rev}:{path}"], cwd=ROOT, check=True, capture_output=True).stdout
    spec = importlib.util.spec_from_loader(name, loader=None)
    assert spec is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up by name
    exec(compile(source, f"{rev}:{path}", "exec"), module.__dict__)
    return module


def cpu_model() -> str:
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.startswith("model name"):
            return line.split(":", 1)[1].strip()
    return "unknown"


def alternate(runs: dict[str, Callable[[], float]], rounds: int) -> dict[str, Any]:
    """Each run (returning seconds per call) once per round, in turn; the median of each and new/old."""
    times: dict[str, list[float]] = {k: [] for k in runs}
    for _ in range(rounds):
        for k, run in runs.items():
            times[k].append(run())
    med = {k: float(np.median(v)) for k, v in times.items()}
    return {"median_us": {k: round(1e6 * v, 2) for k, v in med.items()},
            "new_over_old": round(med["new"] / med["old"], 3)}  # fmt: skip


def _watch_take(seconds: float) -> tuple[list[Any], list[tuple[int, Any, Any]]]:
    sys.path.insert(0, str(ROOT))
    from mocapd.core.synthetic import ring_rig
    from tests.test_camera_watch import take

    truth = ring_rig(4)
    return truth, take(truth, seconds, seed=3, fps=60.0)


def bench_watch(rev: str, rounds: int, only: set[str]) -> dict[str, Any]:
    from mocapd.core import camera_watch as new

    old = module_at(rev, "mocapd/core/camera_watch.py", "_old_camera_watch")
    old_camera = module_at(rev, "mocapd/core/camera.py", "_old_camera")
    for name in ("triangulate_projections", "triangulate_arrays", "weighted_dlt_rows", "dehomogenized"):
        if name in old.__dict__:  # the revision's watch with the revision's triangulation
            old.__dict__[name] = getattr(old_camera, name)
    truth, moments = _watch_take(20.0)
    out: dict[str, Any] = {}

    def observe_all(mod: ModuleType, named: bool = False, screen_hz: float | None = None) -> Callable[[], float]:
        def run() -> float:
            w = mod.CameraWatch(truth, None if screen_hz is None else mod.WatchOptions(screen_hz=screen_hz))
            t0 = time.thread_time()
            for k, (t, uv, cf) in enumerate(moments):
                if named:  # the two people named, as the daemon's hook names them
                    w.observe(t, uv, cf, f"track:{k % 2}")
                else:
                    w.observe(t, uv, cf)
            return (time.thread_time() - t0) / len(moments)

        return run

    def levels(mod: ModuleType) -> Callable[[], float]:
        w = mod.CameraWatch(truth)
        for t, uv, cf in moments:
            w.observe(t, uv, cf)
        t_last = moments[-1][0]

        def run() -> float:
            t0 = time.thread_time()
            for _ in range(50):
                w._levels(t_last)
            return (time.thread_time() - t0) / 50

        return run

    def per_moment(fn: Callable[..., Any]) -> Callable[[], float]:
        def run() -> float:
            P = np.stack([c.projection_matrix for c in truth])
            t0 = time.thread_time()
            for _, uv, cf in moments[::10]:
                fn(P, uv, cf, min_confidence=0.3, min_keypoints=6)
            return (time.thread_time() - t0) / len(moments[::10])

        return run

    if "left_out" in only:
        out["residuals_left_out"] = alternate(
            {"old": per_moment(old.residuals_left_out), "new": per_moment(new.residuals_left_out)}, rounds
        )
    if "left_out" in only:  # people roughed up (tests/test_camera_watch_bitwise: keypoints unseen, under the floor)
        from tests.test_camera_watch_bitwise import _people

        rough = _people(4, seed=4)

        def left_out_rough(mod: ModuleType) -> Callable[[], float]:
            def run() -> float:
                t0 = time.thread_time()
                for P, uv, cf in rough:
                    mod.residuals_left_out(P, uv, cf, min_confidence=0.3, min_keypoints=6)
                return (time.thread_time() - t0) / len(rough)

            return run

        out["residuals_left_out_rough"] = alternate({"old": left_out_rough(old), "new": left_out_rough(new)}, rounds)
    if "all_in" in only:
        out["residuals_all_in"] = alternate(
            {"old": per_moment(old.residuals_all_in), "new": per_moment(new.residuals_all_in)}, rounds
        )
    if "pool" in only:
        res = np.array([[8.1, np.nan, 9.3, 7.7], [8.4, 10.2, np.nan, 7.9]])

        def pool(fn: Callable[[Any], Any]) -> Callable[[], float]:
            def run() -> float:
                t0 = time.thread_time()
                for _ in range(500):
                    fn(res)
                return (time.thread_time() - t0) / 500

            return run

        out["pool_people"] = alternate(
            {"old": pool(lambda r: np.nanmedian(r, axis=0)), "new": pool(new._column_nanmedians)}, rounds
        )
    if "watch" in only:
        out["watch_observe"] = alternate({"old": observe_all(old), "new": observe_all(new)}, rounds)
    if "screen" in only:
        # The daemon's hook as it is now (each person named: screened screen_hz times a second) against the
        # revision's (every solve screened), then the working tree's at other screening rates.
        out["watch_observe_people"] = alternate({"old": observe_all(old), "new": observe_all(new, True)}, rounds)
        rates = {f"{hz:g}": observe_all(new, True, hz) for hz in (60.0, 30.0, 20.0, 15.0, 10.0)}
        out["watch_observe_by_screen_hz"] = {
            k: round(1e6 * float(np.median([run() for _ in range(max(rounds // 3, 3))])), 2) for k, run in rates.items()
        }
    if "people" in only:  # both sides as the daemon calls them now (each person named)
        out["watch_observe_named"] = alternate({"old": observe_all(old, True), "new": observe_all(new, True)}, rounds)
    if "levels" in only:
        out["watch_levels"] = alternate({"old": levels(old), "new": levels(new)}, rounds)
    return out


def bench_mtdata2(rev: str, rounds: int) -> dict[str, Any]:
    from mocapd.protocols import mtdata2 as new
    from mocapd.protocols.xbus import MID, XbusParser

    old = module_at(rev, "mocapd/protocols/mtdata2.py", "_old_mtdata2")
    rng = np.random.default_rng(0)
    mtw = []
    for k in range(1300):
        q = rng.normal(size=4)
        mtw.append(
            new.encode_packet(new.DataId.PACKET_COUNTER, k)
            + new.encode_packet(new.DataId.SAMPLE_TIME_FINE, 100 * k)
            + new.encode_packet(new.DataId.QUATERNION, tuple(q / np.linalg.norm(q)))
            + new.encode_packet(new.DataId.ACCELERATION, tuple(rng.normal(0.0, 9.81, 3)))
        )
    parser = XbusParser()
    for i in range(1, 6):
        parser.receive_data((ROOT / "tests" / "data" / "xbus_einride" / str(i) / "output.bin").read_bytes())
    real = [m.payload for m in parser.events_received() if m.mid == MID.MTDATA2]

    def decode(mod: ModuleType, payloads: list[bytes]) -> Callable[[], float]:
        def run() -> float:
            t0 = time.thread_time()
            for _ in range(5):
                for p in payloads:
                    mod.decode_mtdata2(p)
            return (time.thread_time() - t0) / (5 * len(payloads))

        return run

    return {
        "mtdata2_mtw": alternate({"old": decode(old, mtw), "new": decode(new, mtw)}, rounds),
        "mtdata2_real_mti": alternate({"old": decode(old, real), "new": decode(new, real)}, rounds),
    }


def bench_heading(rev: str, rounds: int) -> dict[str, Any]:
    sys.path.insert(0, str(ROOT))
    from mocapd.core import heading as new
    from mocapd.core.imu import IMU_SET_13
    from tests.test_heading import _posed

    old = module_at(rev, "mocapd/core/heading.py", "_old_heading")
    skeleton, targets, q_true, points = _posed(3, "coco17")
    vectors = new.bone_vectors(skeleton, targets, IMU_SET_13)  # type: ignore[arg-type]
    ok = np.ones(len(points), dtype=bool)

    def observe(mod: ModuleType) -> Callable[[], float]:
        def run() -> float:
            t0 = time.thread_time()
            for _ in range(200):
                mod.observe_headings(q_true, vectors, points, ok)
            return (time.thread_time() - t0) / 200

        return run

    def estimator(mod: ModuleType) -> Callable[[], float]:
        rng = np.random.default_rng(0)
        est = mod.HeadingEstimator(mod.HeadingOptions())
        sensors = [f"s{i}" for i in range(13)]
        t = 0
        for _ in range(100):  # full windows
            t += 50_000_000
            est.observe(t, sensors, rng.normal(0.0, 0.1, 13), np.full(13, 0.05))
        yaws = rng.normal(0.0, 0.1, (100, 13))

        def run() -> float:
            nonlocal t
            t0 = time.thread_time()
            for y in yaws:
                t += 50_000_000
                est.observe(t, sensors, y, np.full(13, 0.05))
            return (time.thread_time() - t0) / len(yaws)

        return run

    return {
        "observe_headings": alternate({"old": observe(old), "new": observe(new)}, rounds),
        "heading_estimator_observe": alternate({"old": estimator(old), "new": estimator(new)}, rounds),
    }


def bench_imu(rev: str, rounds: int, only: set[str]) -> dict[str, Any]:
    sys.path.insert(0, str(ROOT))
    from mocapd.service import imu_inputs as new_inputs
    from mocapd.service.config.imu import ImuConfig
    from tests.test_imu_sample_path import MTW, device_samples, real_mtw_reads

    streaming, reads = real_mtw_reads(sorted(MTW.glob("*.txt"))[0])
    samples = device_samples(streaming, reads)
    out: dict[str, Any] = {}

    def on_sample(mod: ModuleType) -> Callable[[], float]:
        def run() -> float:
            inputs = mod.ImuInputs(ImuConfig())
            inputs.turn_headings({samples[0].sensor: np.array([np.cos(0.35), 0.0, 0.0, np.sin(0.35)])})
            t0 = time.thread_time()
            for s in samples:
                inputs.on_sample(s)
            return (time.thread_time() - t0) / len(samples)

        return run

    def streamed(serial: ModuleType, make_inputs: Callable[[], Callable[[Any], None]]) -> Callable[[], float]:
        """The real MTw reads through a measuring session and ``serial``'s device, into ``make_inputs()``."""
        from mocapd.protocols.xsens_session import State, XsensSession, output_settings

        def run() -> float:
            device = serial.XsensSerialDevice(serial.XsensPortConfig("/dev/ttyMTW"), make_inputs())
            session = XsensSession(output_settings(100))
            session.state = State.MEASURING
            session._events.append(streaming)
            device._dispatch(session, [], 0)
            t0 = time.thread_time()
            for now, data in reads:
                session.receive_data(data, now)
                device._dispatch(session, [], now)
            return (time.thread_time() - t0) / len(samples)

        return run

    def dispatch(mod: ModuleType) -> Callable[[], float]:
        return streamed(mod, lambda: lambda s: None)

    def old_ingest_module() -> ModuleType:
        old_ring = module_at(rev, "mocapd/pipeline/ringbuffer.py", "_old_ringbuffer")
        old_ingest = module_at(rev, "mocapd/pipeline/imu_ingest.py", "_old_imu_ingest")
        old_ingest.__dict__.update(RingBuffer=old_ring.RingBuffer, IMU_FIELDS=old_ring.IMU_FIELDS)
        return old_ingest

    def ingest(mod: ModuleType) -> Callable[[], float]:
        def run() -> float:
            ing = mod.ImuIngest(capacity=512)
            t0 = time.thread_time()
            for s in samples:
                ing.add(
                    s.sensor,
                    s.host_ns,
                    device_ticks=s.device_ticks,
                    packet_counter=s.packet_counter,
                    quat=s.quat,
                    acc=s.acc,
                )
            return (time.thread_time() - t0) / len(samples)

        return run

    if "ingest" in only:
        from mocapd.pipeline import imu_ingest as new_ingest

        out["imu_ingest_add"] = alternate({"old": ingest(old_ingest_module()), "new": ingest(new_ingest)}, rounds)

    def path(serial: ModuleType, inputs_mod: ModuleType) -> Callable[[], float]:
        def make_inputs() -> Callable[[Any], None]:
            inputs = inputs_mod.ImuInputs(ImuConfig())
            inputs.turn_headings({samples[0].sensor: np.array([np.cos(0.35), 0.0, 0.0, np.sin(0.35)])})
            on: Callable[[Any], None] = inputs.on_sample
            return on

        return streamed(serial, make_inputs)

    if "imu_path" in only:
        from mocapd.io import xsens_serial as new_serial

        old_serial = module_at(rev, "mocapd/io/xsens_serial.py", "_old_xsens_serial")
        old_ingest = old_ingest_module()
        old_inputs = module_at(rev, "mocapd/service/imu_inputs.py", "_old_imu_inputs")
        old_inputs.__dict__.update(ImuIngest=old_ingest.ImuIngest)
        out["imu_path"] = alternate({"old": path(old_serial, old_inputs), "new": path(new_serial, new_inputs)}, rounds)
    if "dispatch" in only:
        from mocapd.io import xsens_serial as new_serial

        old_serial = module_at(rev, "mocapd/io/xsens_serial.py", "_old_xsens_serial")
        out["xsens_dispatch"] = alternate({"old": dispatch(old_serial), "new": dispatch(new_serial)}, rounds)
    if "imu_inputs" in only:
        old = module_at(rev, "mocapd/service/imu_inputs.py", "_old_imu_inputs")
        out["imu_inputs_on_sample"] = alternate({"old": on_sample(old), "new": on_sample(new_inputs)}, rounds)
    return out


def _old_time_alignment(rev: str) -> ModuleType:
    """The revision's ``time_alignment``, with the revision's ``person_distances``."""
    old_timeline = module_at(rev, "mocapd/pipeline/keypoint_timeline.py", "_old_keypoint_timeline")
    old = module_at(rev, "mocapd/pipeline/time_alignment.py", "_old_time_alignment")
    old.__dict__.update(person_distances=old_timeline.person_distances)
    return old


def bench_offsets(rev: str, rounds: int, only: set[str]) -> dict[str, Any]:
    sys.path.insert(0, str(ROOT))
    from mocapd.pipeline import scheduler
    from mocapd.pipeline import time_alignment as new
    from tools.bench_offset_estimate import recorded_frames

    old = _old_time_alignment(rev)
    names, frames = recorded_frames(256 / 30)
    out: dict[str, Any] = {}

    def speed(mod: ModuleType) -> Callable[[], float]:
        def run() -> float:
            t0 = time.thread_time()
            for times, dets in frames:
                mod.keypoint_speed(np.asarray(times, dtype=np.int64), dets)
            return (time.thread_time() - t0) / len(frames)

        return run

    def offsets(mod: ModuleType) -> Callable[[], float]:
        def run() -> float:
            real = scheduler.__dict__["keypoint_speed_steps"]
            scheduler.__dict__["keypoint_speed_steps"] = mod.keypoint_speed_steps  # the estimate's speeds: the module's
            try:
                t0 = time.thread_time()
                scheduler.estimate_camera_offsets(names, frames, ())
                return time.thread_time() - t0
            finally:
                scheduler.__dict__["keypoint_speed_steps"] = real

        return run

    if "speed" in only:
        out["keypoint_speed_256_frames"] = alternate({"old": speed(old), "new": speed(new)}, rounds)
    if "offsets" in only:
        out["camera_offset_estimate"] = alternate({"old": offsets(old), "new": offsets(new)}, rounds)
    return out


def _scheduler(sched_mod: ModuleType, world: Any) -> Any:
    """``sched_mod``'s scheduler over ``world``'s people, its cameras given lens distortion, latency "auto"."""
    import dataclasses

    from mocapd.core.people import PeopleTracker
    from mocapd.core.sorting import DetectionSorter
    from mocapd.core.suit_binding import SuitBinder
    from mocapd.core.tracking import SubjectTracker, TrackingOptions
    from mocapd.pipeline.latency import AutoLatencyOptions

    cameras = [dataclasses.replace(c, dist=np.array([-0.21, 0.08, 0.0012, -0.0007, -0.012])) for c in world.cameras]
    tracker = PeopleTracker(SubjectTracker(DetectionSorter(cameras), TrackingOptions()),
                            SuitBinder(world.skeleton, names=world.targets.names))  # fmt: skip
    options = sched_mod.SchedulerOptions(auto_latency=AutoLatencyOptions())
    return sched_mod.FixedLatencyScheduler(cameras, world.skeleton, world.targets, tracker, options=options)


def bench_arrival(rev: str, rounds: int) -> dict[str, Any]:
    from mocapd.pipeline import scheduler as new
    from mocapd.sim.world import SyntheticWorld

    old_latency = module_at(rev, "mocapd/pipeline/latency.py", "_old_latency")
    old = module_at(rev, "mocapd/pipeline/scheduler.py", "_old_scheduler")
    old.__dict__.update(LatencyStats=old_latency.LatencyStats, AutoLatency=old_latency.AutoLatency)
    world = SyntheticWorld(4, 2, 0, seed=3)
    rng = np.random.default_rng(0)
    sets = [(c, world.detections(c, k / 30, rng)) for k in range(150) for c in range(4)]

    def arrive(mod: ModuleType) -> Callable[[], float]:
        sched = _scheduler(mod, world)
        t = 10**12

        def run() -> float:
            nonlocal t
            t0 = time.thread_time()
            for c, dets in sets:
                t += 8_000_000
                sched.add_detections(c, t, dets, t + 30_000_000)
            return (time.thread_time() - t0) / len(sets)

        return run

    return {"add_detections": alternate({"old": arrive(old), "new": arrive(new)}, rounds)}


def bench_sample(rev: str, rounds: int) -> dict[str, Any]:
    from mocapd.core.sorting import Detections2D
    from mocapd.pipeline import keypoint_timeline as new
    from mocapd.sim.world import SyntheticWorld

    old = module_at(rev, "mocapd/pipeline/keypoint_timeline.py", "_old_keypoint_timeline")
    world = SyntheticWorld(4, 2, 0, seed=3)
    rng = np.random.default_rng(0)
    period = round(1e9 / 30)
    frames = []
    for k in range(120):
        d = world.detections(0, k / 30, rng)
        frames.append((k * period, Detections2D(d.keypoints, d.confidences, d.keypoints * 0.98 + 3.0)))
    looks = list(range(frames[1][0], frames[-1][0], round(1e9 / 60)))

    def sample(mod: ModuleType) -> Callable[[], float]:
        def run() -> float:
            tl = mod.DetectionTimeline(frames[0][1].keypoints.shape[1])
            for t, d in frames:
                tl.push(t, d)
            t0 = time.thread_time()
            for t in looks:
                tl.sample(t)
            return (time.thread_time() - t0) / len(looks)

        return run

    a, b = frames[10][1], frames[11][1]
    pairs = new.match_people(a, b, 80.0)

    def blend(mod: ModuleType) -> Callable[[], float]:
        def run() -> float:
            t0 = time.thread_time()
            for k in range(300):
                mod.interpolate_people(a, b, k / 300, 80.0, pairs=pairs)
            return (time.thread_time() - t0) / 300

        return run

    def sample_new_brackets(mod: ModuleType) -> Callable[[], float]:
        """Frames at 60 Hz (tracked keypoints), look-ups between each two: a matching and a blend per look-up."""

        def run() -> float:
            tl = mod.DetectionTimeline(frames[0][1].keypoints.shape[1])
            for t, d in frames:
                tl.push(t // 2, d)
            t0 = time.thread_time()
            for t, _ in frames[1:-1]:
                tl.sample(t // 2 + period // 4)
            return (time.thread_time() - t0) / (len(frames) - 2)

        return run

    return {
        "timeline_sample": alternate({"old": sample(old), "new": sample(new)}, rounds),
        "timeline_sample_new_brackets": alternate(
            {"old": sample_new_brackets(old), "new": sample_new_brackets(new)}, rounds
        ),
        "interpolate_people": alternate({"old": blend(old), "new": blend(new)}, rounds),
    }


def bench_collapse(rev: str, rounds: int) -> dict[str, Any]:
    from mocapd.core import lr_collapse as new
    from mocapd.core.keypoints import coco17_targets
    from mocapd.core.kinematics import Kinematics
    from mocapd.core.lr_flips import COCO17_LR_PAIRS, undistorted
    from mocapd.core.skeleton import Skeleton
    from mocapd.core.synthetic import moving_sequence, ring_rig

    old = module_at(rev, "mocapd/core/lr_collapse.py", "_old_lr_collapse")
    old_camera = module_at(rev, "mocapd/core/camera.py", "_old_camera")
    if "triangulate_arrays" in old.__dict__:  # the revision's triangulation with the revision's collapse check
        old.__dict__["triangulate_arrays"] = old_camera.triangulate_arrays
    sk = Skeleton.from_height(1.75)
    kin, targets = Kinematics(sk), coco17_targets(sk)
    cams = ring_rig(4, radius=4.5)
    rng = np.random.default_rng(0)
    people = []
    for theta in moving_sequence(sk, 40, seed=3):
        X = kin.targets(kin.forward(theta), targets.bones, targets.offsets)
        uv = np.stack([c.project(X) for c in cams]) + rng.normal(0.0, 1.0, (4, 17, 2))
        uv[1, [8, 10]] = uv[1, [7, 9]] + 1.5
        P, und = undistorted(cams, uv)
        people.append((P, und, np.full((4, 17), 0.9), X))

    def collapse(mod: ModuleType) -> Callable[[], float]:
        def run() -> float:
            t0 = time.thread_time()
            for P, und, conf, X in people:
                mod.collapsed_pairs(P, und, conf, COCO17_LR_PAIRS, X)
            return (time.thread_time() - t0) / len(people)

        return run

    return {"collapsed_pairs": alternate({"old": collapse(old), "new": collapse(new)}, rounds)}


def bench_triangulate(rev: str, rounds: int) -> dict[str, Any]:
    from mocapd.core import camera as new
    from mocapd.core.synthetic import ring_rig

    old = module_at(rev, "mocapd/core/camera.py", "_old_camera")
    cams = ring_rig(4, radius=4.5)
    P = np.stack([c.projection_matrix for c in cams])
    rng = np.random.default_rng(0)
    X = rng.normal(0.0, 0.5, (17, 3)) + np.array([0.0, 1.0, 0.0])
    h = P[:, None, :, :3] @ X[None, :, :, None] + P[:, None, :, 3:]
    uv = h[..., :2, 0] / h[..., 2:, 0] + rng.normal(0.0, 1.0, (4, 17, 2))
    w = rng.uniform(0.3, 1.0, (4, 17))
    w[1, 2:6] = 0.0
    few = (uv[:, :4], np.where(np.arange(4)[:, None] == 1, 0.0, w[:, :4]))  # the collapse check's 2 candidates

    def per_call(fn: Callable[[], Any]) -> Callable[[], float]:
        def run() -> float:
            t0 = time.thread_time()
            for _ in range(300):
                fn()
            return (time.thread_time() - t0) / 300

        return run

    def tri(mod: ModuleType, u: Any, ww: Any, normal: bool = False) -> Callable[[], float]:
        return per_call(lambda: mod.triangulate_arrays(P, u, ww, 3 if normal else 2, normal_equations=normal))

    return {
        "weighted_dlt_rows_17": alternate({"old": per_call(lambda: old.weighted_dlt_rows(P, uv, w)),
                                           "new": per_call(lambda: new.weighted_dlt_rows(P, uv, w))}, rounds),
        "triangulate_arrays_4": alternate({"old": tri(old, *few), "new": tri(new, *few)}, rounds),
        "triangulate_arrays_17_normal": alternate({"old": tri(old, uv, w, True), "new": tri(new, uv, w, True)},
                                                  rounds),
    }  # fmt: skip


def bench_solve(rev: str, rounds: int) -> dict[str, Any]:
    from mocapd.core import solver as new
    from mocapd.core.keypoints import coco17_targets
    from mocapd.core.kinematics import Kinematics
    from mocapd.core.skeleton import Skeleton
    from mocapd.core.synthetic import moving_sequence, ring_rig

    old = module_at(rev, "mocapd/core/solver.py", "_old_solver")
    old_obs = module_at(rev, "mocapd/core/observations.py", "_old_observations")
    old_rot = module_at(rev, "mocapd/core/rotations.py", "_old_rotations")
    old.__dict__.update(ValidatedObservations=old_obs.ValidatedObservations, rotvec_principal=old_rot.rotvec_principal)
    sk = Skeleton.from_height(1.75)
    kin, targets = Kinematics(sk), coco17_targets(sk)
    cams = ring_rig(4, radius=4.5)
    rng = np.random.default_rng(0)
    thetas = moving_sequence(sk, 120, seed=3)
    frames = []
    for th in thetas:
        X = kin.targets(kin.forward(th), targets.bones, targets.offsets)
        uv = np.stack([c.project(X) for c in cams]) + rng.normal(0.0, 1.0, (4, 17, 2))
        frames.append(new.Observations(keypoints=uv, confidences=np.full((4, 17), 0.9), dt=1 / 30))

    def solve(mod: ModuleType) -> Callable[[], float]:
        s = mod.PoseSolver(sk, cams, targets)
        s.reset(thetas[0])

        def run() -> float:
            s.reset(thetas[0])
            t0 = time.thread_time()
            for obs in frames:
                s.solve(obs)
            return (time.thread_time() - t0) / len(frames)

        return run

    def glue(mod: ModuleType, fn: str) -> Callable[[], float]:
        s = mod.PoseSolver(sk, cams, targets)
        theta = thetas[5]
        calls: dict[str, Callable[[], Any]] = {
            "imu_sites": lambda: s.push_history(theta),
            "principal_pose": lambda: mod.principal_pose(theta),
        }
        call = calls[fn]

        def run() -> float:
            t0 = time.thread_time()
            for _ in range(500):
                call()
            return (time.thread_time() - t0) / 500

        return run

    return {
        "pose_solver_solve_cameras": alternate({"old": solve(old), "new": solve(new)}, rounds),
        "push_history_cameras": alternate({"old": glue(old, "imu_sites"), "new": glue(new, "imu_sites")}, rounds),
        "principal_pose": alternate({"old": glue(old, "principal_pose"), "new": glue(new, "principal_pose")}, rounds),
    }


def bench_validate(rev: str, rounds: int) -> dict[str, Any]:
    from mocapd.core import observations as new

    old = module_at(rev, "mocapd/core/observations.py", "_old_observations")
    rng = np.random.default_rng(0)
    kp, conf = rng.uniform(0.0, 1000.0, (4, 17, 2)), rng.uniform(0.0, 1.0, (4, 17))

    def validate(mod: ModuleType) -> Callable[[], float]:
        obs = mod.Observations(keypoints=kp, confidences=conf, dt=1 / 30)

        def run() -> float:
            t0 = time.thread_time()
            for _ in range(300):
                mod.ValidatedObservations(obs, 4, 17, 0)
            return (time.thread_time() - t0) / 300

        return run

    return {"validated_observations": alternate({"old": validate(old), "new": validate(new)}, rounds)}


def bench_plausibility(rev: str, rounds: int) -> dict[str, Any]:
    from mocapd.core import plausibility as new
    from mocapd.core.skeleton import Skeleton
    from mocapd.core.synthetic import moving_sequence
    from mocapd.service.config import load_config
    from mocapd.sim.world import SyntheticWorld

    old = module_at(rev, "mocapd/core/plausibility.py", "_old_plausibility")
    syn = load_config().synthetic
    world = SyntheticWorld(4, syn.people, syn.suits, seed=syn.seed, motion=syn.motion)
    demo = [[world.theta_at(p, k / 60.0) for k in range(600)] for p in range(syn.people)]
    circle = [list(moving_sequence(Skeleton.from_height(1.75), 600, seed=3))]

    def step(mod: ModuleType, people: list[list[Any]]) -> Callable[[], float]:
        def run() -> float:
            monitors = [mod.PlausibilityMonitor() for _ in people]
            t0 = time.thread_time()
            for m, poses in zip(monitors, people, strict=True):
                for k, th in enumerate(poses):
                    m.step(k / 60.0, th)
            return (time.thread_time() - t0) / sum(len(p) for p in people)

        return run

    return {
        "plausibility_step_demo": alternate({"old": step(old, demo), "new": step(new, demo)}, rounds),
        "plausibility_step_circle": alternate({"old": step(old, circle), "new": step(new, circle)}, rounds),
    }


def bench_track(rev: str, rounds: int) -> dict[str, Any]:
    import dataclasses
    import inspect
    from types import SimpleNamespace

    from mocapd.core import _sorting_kernel
    from mocapd.core import sorting as new_sorting
    from mocapd.core import tracking as new_tracking
    from mocapd.service.config import load_config
    from mocapd.sim.world import SyntheticWorld

    old_sorting = module_at(rev, "mocapd/core/sorting.py", "_old_sorting")
    old_tracking = module_at(rev, "mocapd/core/tracking.py", "_old_tracking")
    names = ("Candidate", "Detections2D", "DetectionSorter", "mean_keypoint_distance")
    old_tracking.__dict__.update({k: getattr(old_sorting, k) for k in names})
    if "prune" in inspect.signature(_sorting_kernel.candidate_pairs.py_func).parameters:  # the old kernel's path
        kernel: Callable[..., Any] = _sorting_kernel.candidate_pairs

        def unpruned(*args: Any) -> Any:
            return kernel(*args, False)

        old_sorting.__dict__["_sorting_kernel"] = SimpleNamespace(candidate_pairs=unpruned)
    syn = load_config().synthetic
    world = SyntheticWorld(4, syn.people, 0, seed=syn.seed, motion=syn.motion)
    cams = [dataclasses.replace(c, dist=np.array([-0.21, 0.08, 0.0012, -0.0007, -0.012])) for c in world.cameras]
    rng = np.random.default_rng(0)
    ticks = [[world.detections(c, k / 60.0, rng, syn.noise_px) for c in range(4)] for k in range(360)]

    def update(sorting: ModuleType, tracking: ModuleType) -> Callable[[], float]:
        tracker = tracking.SubjectTracker(sorting.DetectionSorter(cams), tracking.TrackingOptions())
        for k, dets in enumerate(ticks[:120]):  # both people enrolled
            tracker.update(k * 16_666_667, dets, [k // 2] * 4)
        t = 120

        def run() -> float:
            nonlocal t
            t0 = time.thread_time()
            for dets in ticks[120:]:
                tracker.update(t * 16_666_667, dets, [t // 2] * 4)
                t += 1
            return (time.thread_time() - t0) / (len(ticks) - 120)

        return run

    return {"tracker_update": alternate({"old": update(old_sorting, old_tracking),
                                         "new": update(new_sorting, new_tracking)}, rounds)}  # fmt: skip


def bench_nearest(rev: str, rounds: int) -> dict[str, Any]:
    import dataclasses

    from mocapd.core import tracking as new
    from mocapd.core.sorting import DetectionSorter
    from mocapd.service.config import load_config
    from mocapd.sim.world import SyntheticWorld

    old = module_at(rev, "mocapd/core/tracking.py", "_old_tracking")
    syn = load_config().synthetic
    world = SyntheticWorld(4, syn.people, 0, seed=syn.seed, motion=syn.motion)
    cams = [dataclasses.replace(c, dist=np.array([-0.21, 0.08, 0.0012, -0.0007, -0.012])) for c in world.cameras]
    partner = DetectionSorter(cams)._partner(17)
    rng = np.random.default_rng(0)
    calls = [(cams[k % 4], world.sites_at(0, k / 60.0), world.detections(k % 4, k / 60.0, rng, syn.noise_px))
             for k in range(200)]  # fmt: skip

    def nearest(mod: ModuleType) -> Callable[[], float]:
        def run() -> float:
            t0 = time.thread_time()
            for cam, points, dets in calls:
                mod._nearest_is(cam, points, dets, 0, partner, 0.3)
            return (time.thread_time() - t0) / len(calls)

        return run

    return {"tracker_nearest_is": alternate({"old": nearest(old), "new": nearest(new)}, rounds)}


def bench_sim(rev: str, rounds: int) -> dict[str, Any]:
    from mocapd.sim import xsens as new

    old = module_at(rev, "mocapd/sim/xsens.py", "_old_sim_xsens")

    def per_message(mod: ModuleType) -> Callable[[], float]:
        device = mod.SimDevice(mod.synthetic_motion(n=600))
        device.due_ns(0)
        for _ in range(600):  # every motion packet cached, as in a running suit
            device.next_message(device._next_ns)

        def run() -> float:
            t0 = time.thread_time()
            for _ in range(2000):
                device.next_message(device._next_ns)
            return (time.thread_time() - t0) / 2000

        return run

    return {"sim_next_message": alternate({"old": per_message(old), "new": per_message(new)}, rounds)}


def bench_frames(rev: str, rounds: int) -> dict[str, Any]:
    sys.path.insert(0, str(ROOT))
    from mocapd.service.config import load_config
    from mocapd.sim import world as new

    old = module_at(rev, "mocapd/sim/world.py", "_old_sim_world")
    syn = load_config().synthetic

    def per_frame(mod: ModuleType) -> Callable[[], float]:
        w = mod.SyntheticWorld(4, syn.people, syn.suits, seed=syn.seed, motion=syn.motion)
        rng = np.random.default_rng(0)

        def run() -> float:
            t0 = time.thread_time()
            for k in range(400):
                w.detections(k % 4, k / 120.0, rng, syn.noise_px)
            return (time.thread_time() - t0) / 400

        return run

    return {"synthetic_frame": alternate({"old": per_frame(old), "new": per_frame(new)}, rounds)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rev", default="main", help="the git revision to compare against (default main)")
    ap.add_argument("--rounds", type=int, default=15)
    ap.add_argument(
        "--only",
        default="watch,screen,levels,left_out,all_in,pool,mtdata2,heading,imu_inputs,dispatch,ingest,imu_path,speed,offsets,arrive,sample,collapse,triangulate,solve,validate,sim,frames,plausibility,track,nearest",
        help="comma-separated pieces (default: all)",
    )
    args = ap.parse_args()
    only = set(args.only.split(","))
    report: dict[str, Any] = {"cpu": cpu_model(), "rev": args.rev, "rounds": args.rounds, "clock": "thread CPU"}
    report.update(bench_watch(args.rev, args.rounds, only))
    if "heading" in only:
        report.update(bench_heading(args.rev, args.rounds))
    if "mtdata2" in only:
        report.update(bench_mtdata2(args.rev, args.rounds))
    report.update(bench_imu(args.rev, args.rounds, only))
    report.update(bench_offsets(args.rev, args.rounds, only))
    if "arrive" in only:
        report.update(bench_arrival(args.rev, args.rounds))
    if "sample" in only:
        report.update(bench_sample(args.rev, args.rounds))
    if "collapse" in only:
        report.update(bench_collapse(args.rev, args.rounds))
    if "triangulate" in only:
        report.update(bench_triangulate(args.rev, args.rounds))
    if "solve" in only:
        report.update(bench_solve(args.rev, args.rounds))
    if "validate" in only:
        report.update(bench_validate(args.rev, args.rounds))
    if "plausibility" in only:
        report.update(bench_plausibility(args.rev, args.rounds))
    if "track" in only:
        report.update(bench_track(args.rev, args.rounds))
    if "nearest" in only:
        report.update(bench_nearest(args.rev, args.rounds))
    if "sim" in only:
        report.update(bench_sim(args.rev, args.rounds))
    if "frames" in only:
        report.update(bench_frames(args.rev, args.rounds))
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
