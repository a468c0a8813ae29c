"""``mocapd resolve``: re-solve a recorded session offline at higher quality (the "second solve").

Two passes over the recorded raw inputs:

1. **Forward re-solve.** The same :class:`~mocapd.pipeline.scheduler.FixedLatencyScheduler`, tracker, suit binding
   and per-person solver the daemon ran, rebuilt from the manifest, fed every recorded keypoint frame and IMU sample
   (none skipped: live, a detector that falls behind drops frames and a late tick is counted missed, not solved),
   at every output tick of the recording (those the live daemon missed included), with a much larger LM budget
   (:attr:`ResolveOptions.max_iterations`, tighter tolerances), the IMU samples re-timed by one clock fit over
   the whole session (:func:`imu_times`). Offline nothing arrives late, so every solve sees the
   detections on both sides of its time. Where the objective rates the recorded live pose of a frame lower than
   the re-solve's, the live pose is kept (:attr:`ResolveOptions.keep_live`).
2. **Forward-backward smoothing.** Per subject, a Rauch–Tung–Striebel smoother (a Kalman filter forward, then
   the RTS pass backward) with a constant-velocity model over the root translation and over each bone's local
   rotation as a sign-continuous quaternion (renormalised after smoothing). The per-frame solves are the
   measurements. Unlike blending a forward and a backward solve (which converge to the same per-frame optimum
   once the LM budget is large), the smoother uses the frames on both sides of each frame, which is what
   removes the per-frame jitter of detector noise. Segments are split where a subject is unseen for longer
   than :attr:`ResolveOptions.max_gap_s`.

A camera recalibrated while recording (the bumped-camera watch applied a re-estimate: a ``camera`` event of the
session, :func:`camera_changes`) is replaced in the re-solve's scheduler: the solves after the event's time use the
new camera, as the live daemon's did, and so do those since the watch first doubted the camera (``doubt_ns``: live,
the camera was left out of those; the re-estimate describes it since it moved, which the re-solve can know).

Then every subject's poses go through the anatomical plausibility checks (:func:`plausibility`): a knee or elbow
bending the wrong way, or a pelvis facing backwards while the legs walk forwards, for more than a moment is counted
in the summary and said in its notes.

The noise levels (:class:`ResolveOptions`) were chosen on the synthetic rig; ``docs/sessions.md`` has the
measured joint errors of the live solve, the forward re-solve and the smoothed result against the known truth.
"""

from __future__ import annotations

import itertools
import zipfile
import zlib
from collections import defaultdict
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from tokenize import TokenError  # numpy's header parser raises it for a damaged .npy header
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mocapd.core.camera import Camera
from mocapd.core.heading import HeadingOptions
from mocapd.core.imu_calibration import ImuCalibration
from mocapd.core.keypoints import TrackTargets
from mocapd.core.kinematics import Kinematics
from mocapd.core.lr_flips import FlipOptions
from mocapd.core.motion import time_grid
from mocapd.core.people import PeopleTracker
from mocapd.core.per_skeleton import PerSkeleton, skeleton_key
from mocapd.core.plausibility import PlausibilityMonitor
from mocapd.core.prior import PcaPrior
from mocapd.core.rotations import quat_conjugate, quat_from_rotvec, quat_multiply, quat_normalize, rotvec_from_quat
from mocapd.core.skeleton import N_BONES, PARENTS, Skeleton
from mocapd.core.sorting import Detections2D, DetectionSorter
from mocapd.core.suit_binding import SuitBinder
from mocapd.core.tracking import SubjectTracker
from mocapd.errors import ConfigError, InputError, MocapdError, ModelError
from mocapd.io.input_files import open_input
from mocapd.io.session import EVENTS, MANIFEST, SUFFIX, Session
from mocapd.pipeline.clocksync import offline_clock_map
from mocapd.pipeline.hands import HandStage
from mocapd.pipeline.imu_ingest import TICK_HZ, ImuIngest
from mocapd.pipeline.scheduler import FixedLatencyScheduler, SchedulerOptions, Suit
from mocapd.protocols.session_format import ImuRecord, PersonRecord, PoseRecord
from mocapd.service.config import Config, parse_config
from mocapd.service.outputs.recorder import camera_from_dict

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class ResolveOptions:
    """How the offline re-solve differs from the live one."""

    max_iterations: int = 100
    """LM iteration cap per frame (live: ``solver.lm.max_iterations``, 20 by default)."""
    tolerance: float = 1e-10
    """Function and parameter tolerance of LM (live: 1e-6 and 1e-8)."""
    smooth: bool = True
    """Run the RTS smoother after the forward re-solve."""
    root_sigma_m: float = 0.006
    """Measurement noise of a solved root position (m, standard deviation)."""
    root_accel: float = 2.0
    """Process noise of the root: white-acceleration spectral density (m²/s³)."""
    rot_sigma: float = 0.01
    """Measurement noise of a solved local-rotation quaternion component (standard deviation)."""
    rot_accel: float = 3.0
    """Process noise of the quaternion components: white-acceleration spectral density (1/s³)."""
    max_gap_s: float = 0.25
    """A subject unseen for longer than this starts a new smoothing segment."""
    min_segment_s: float = 0.3
    """A segment shorter than this is left as solved. A constant-velocity smoother needs frames to learn a velocity
    from, and the short segments are a track's first frames (before body sizing gives the person their skeleton),
    where the solve still converges from the warm start: smoothing them averages the convergence, not noise."""
    keep_live: bool = True
    """Where the session recorded a live pose for a person at a solve's instant (on the same skeleton), the
    forward pass keeps it wherever the solve's own objective (reprojection, priors, IMU terms) rates it lower than
    the re-solve's pose, and warm-starts the next frame from it: the longer LM descends to the minimum nearest its
    own warm start, which can be worse than live's (the Pose2Sim demos without the guard: 16 of 1112 solves, the
    acrobat 15-20 px further from the held-out camera in frames 79-80; with it 10 live poses are kept, and the
    frames after them follow live's minimum). The re-solve is then never worse than live by its objective, frame by
    frame (``docs/accuracy-video.md``)."""
    refit_imu_clock: bool = True
    """Re-map every IMU sample's device time to the host clock with one fit over the whole session, instead of
    the buffer time the live (causal) clock map gave it."""


@dataclass
class SessionRig:
    """What the daemon ran with, rebuilt from a session manifest."""

    config: Config
    cameras: list[Camera]
    skeleton: Skeleton
    targets: TrackTargets
    prior: PcaPrior | None
    suits: list[Suit]
    options: SchedulerOptions
    keypoint_columns: tuple[str, ...] = ()
    """The recorded detections' columns when they go beyond the targets' (hand keypoints); empty: the targets'."""


def session_rig(session: Session) -> SessionRig:
    """What the daemon ran with, from the session's manifest and prior file; a damaged or incomplete manifest or
    prior is an :class:`~mocapd.errors.InputError` in one line naming the file (never a KeyError from deep inside,
    nor a camera's, calibration's or config key's message that does not say it comes from the manifest)."""
    m = session.manifest
    prior = _prior(session.path / Path(str(m["prior"])).name) if m.get("prior") else None  # beside the manifest
    where = session.path / MANIFEST
    try:
        return _session_rig(session, prior)
    except ConfigError as exc:
        lines = str(exc).splitlines() or [""]
        more = f" (and {len(lines) - 1} more)" if len(lines) > 1 else ""
        raise InputError(f"{where}: damaged: its copy of the config: {lines[0]}{more}") from None
    except MocapdError as exc:
        raise InputError(f"{where}: damaged: {exc}") from None
    except KeyError as exc:
        raise InputError(f"{where}: damaged or incomplete: no key {exc}") from None
    except (TypeError, ValueError, IndexError, AttributeError, OverflowError) as exc:
        raise InputError(f"{where}: damaged or incomplete: {type(exc).__name__}: {exc}") from None


SCHEDULER_RANGES: dict[str, tuple[float, float]] = {
    "rate_hz": (1.0, 1000.0),
    "latency_ns": (0.0, 60e9),
    "keypoint_max_age_ns": (0.0, 60e9),
    "keypoint_max_gap_ns": (0.0, 60e9),
    "match_px": (0.0, 1e5),
    "body_size_frames": (0.0, 1e6),
    "body_size_first_frames": (0.0, 1e6),
    "offset_ns": (-60e9, 60e9),
}
"""What a manifest's ``scheduler`` numbers may be (JSON also carries NaN and Infinity): wider than the config
allows, so a session of an older version still opens, but nothing divides by zero, overflows an integer or
spans more ticks than a run can have."""


def _number(value: object, key: str, rng: str | None = None) -> float:
    """``value`` when it is a number inside ``SCHEDULER_RANGES[rng or key]``, else InputError naming ``key``."""
    lo, hi = SCHEDULER_RANGES[rng or key]
    if isinstance(value, bool) or not isinstance(value, int | float) or not lo <= value <= hi:
        raise InputError(f"scheduler.{key} = {value!r}; allowed: a number in [{lo:g}, {hi:g}]")
    return value


def _prior(path: Path) -> PcaPrior:
    with open_input(path, "session pose prior", max_bytes=64 << 20):
        pass  # a regular file of sane size: numpy opens it by name (and would wait on a FIFO)
    try:
        with np.load(path, allow_pickle=False) as z:
            return PcaPrior(z["M"], z["mu"], z["sigma"])
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error, ModelError, TokenError) as exc:
        raise InputError(f"{path}: cannot read the session's pose prior (damaged?): {exc}") from None


def manifest_skeleton(manifest: Mapping[str, Any]) -> tuple[Skeleton, TrackTargets]:
    """The rig's skeleton and the keypoints' track targets a session recorded (its manifest's ``skeleton`` and
    ``targets``): what a re-solve, or a reader turning recorded poses into keypoints, solves on."""
    sk = manifest["skeleton"]
    skeleton = Skeleton(np.array(sk["offsets"]), root_height=float(sk["root_height"]), height=float(sk["height"]))
    t = manifest["targets"]
    targets = TrackTargets(tuple(t["names"]), np.array(t["bones"], dtype=np.intp), np.array(t["offsets"]))
    return skeleton, targets


def _session_rig(session: Session, prior: PcaPrior | None) -> SessionRig:
    m = session.manifest
    config = parse_config(m["config"])
    cameras = [camera_from_dict(c) for c in m["cameras"]]
    skeleton, targets = manifest_skeleton(m)
    suits = [
        Suit.from_calibration(s["id"], ImuCalibration.from_json_dict(s["calibration"]), skeleton) for s in m["suits"]
    ]
    s = m["scheduler"]
    offsets = s["camera_offsets_ns"]
    if len(offsets) != len(cameras):
        raise InputError(f"scheduler.camera_offsets_ns has {len(offsets)} entries for {len(cameras)} cameras")
    options = SchedulerOptions(
        rate_hz=float(_number(s["rate_hz"], "rate_hz")), latency_ns=int(_number(s["latency_ns"], "latency_ns")),
        keypoint_max_age_ns=int(_number(s["keypoint_max_age_ns"], "keypoint_max_age_ns")),
        keypoint_max_gap_ns=int(_number(s["keypoint_max_gap_ns"], "keypoint_max_gap_ns")),
        match_px=float(_number(s["match_px"], "match_px")),
        camera_offsets_ns=tuple(int(_number(v, "camera_offsets_ns", "offset_ns")) for v in offsets),
        imu_offsets_ns={str(k): int(_number(v, f"imu_offsets_ns.{k}", "offset_ns"))
                        for k, v in s["imu_offsets_ns"].items()},
        body_size_frames=int(_number(s.get("body_size_frames", 0), "body_size_frames")),
        # Sessions from before these existed re-solve as they were solved: no provisional size, no flips undone.
        body_size_first_frames=int(_number(s.get("body_size_first_frames", 0), "body_size_first_frames")),
        flips=FlipOptions(enabled=bool(s.get("lr_flips", False))),
        # Offline there is nothing to predict: always the delayed solve. Heading correction as recorded (on for
        # sessions from before it existed: it only ever uses the session's own keypoints and IMUs).
        heading=HeadingOptions(enabled=bool(s.get("heading_correction", True))),
    )  # fmt: skip
    columns = m.get("keypoint_columns", [])
    if not isinstance(columns, list) or not all(isinstance(n, str) for n in columns):
        raise InputError("keypoint_columns: not a list of keypoint names")
    return SessionRig(config, cameras, skeleton, targets, prior, suits, options, tuple(columns))


def session_scheduler(rig: SessionRig, opts: ResolveOptions) -> tuple[FixedLatencyScheduler, ImuIngest]:
    """The scheduler the daemon ran (tracker, suits, fingers) rebuilt from ``rig``, with ``opts``' LM budget."""
    cfg = rig.config
    lm = replace(cfg.solver.lm.options(), max_iterations=opts.max_iterations, function_tolerance=opts.tolerance,
                 parameter_tolerance=opts.tolerance)  # fmt: skip
    ingest = ImuIngest(capacity=max(cfg.imu.buffer_capacity, 1024))
    ingest.keep(sid for suit in rig.suits for sid in suit.sensors)
    tracker = PeopleTracker(
        SubjectTracker(
            DetectionSorter(
                rig.cameras, cfg.tracking.sorting.options(), keypoint_names=rig.keypoint_columns or rig.targets.names
            ),
            cfg.tracking.enrolment.options(),
        ),
        SuitBinder(rig.skeleton, cfg.tracking.binding.options(), names=rig.targets.names) if rig.suits else None,
    )
    sched = FixedLatencyScheduler(
        rig.cameras, rig.skeleton, rig.targets, tracker, prior=rig.prior, ingest=ingest, suits=rig.suits,
        options=rig.options, cost=cfg.solver.cost, lm=lm, backend=cfg.solver.backend,
        # Fingers when the recorded detections carry both hands' keypoints (as the live daemon solved them)
        hands=HandStage.from_names(rig.keypoint_columns or rig.targets.names,
                                   np.stack([c.projection_matrix for c in rig.cameras])) if rig.cameras else None,
    )  # fmt: skip
    return sched, ingest


def solve_times(session: Session, rate_hz: float, sensors: tuple[str, ...] = ()) -> NDArray[np.int64]:
    """The instants the live daemon solved, the ticks it missed included (:func:`recorded_instants`); a grid at
    ``rate_hz`` over the keypoints when no frame was recorded, over the IMU samples when there are no keypoints
    either (an imported IMU recording: ``mocapd import``): then over the span every one of the suits'
    ``sensors`` covers (:func:`imu_coverage`), where the take has such a span."""
    period = round(1e9 / rate_hz)
    t = np.array([f.t_solve_ns for f in session.poses()], dtype=np.int64)
    if t.size:
        return recorded_instants(t, period)
    t = np.array([k.capture_ns for k in session.keypoints()], dtype=np.int64)
    if t.size == 0:
        coverage = imu_coverage(session)
        if not coverage:
            return np.zeros(0, dtype=np.int64)
        t = np.array([t for span in coverage.values() for t in span], dtype=np.int64)
        common = common_span(coverage, sensors)
        if common is not None:
            t = np.array(common, dtype=np.int64)
    return time_grid(int(t.min()), int(t.max()), rate_hz)  # the last sample posed too


def recorded_instants(t_solve_ns: NDArray[np.int64], period_ns: int) -> NDArray[np.int64]:
    """The recorded solve instants, sorted and unique, with the gaps the live daemon left (missed ticks: more than
    1.5 periods between two frames) filled at the period.

    The recorded instants, not a grid from the first one: under ``latency_s = "auto"`` the live delay moves, and
    so do the instants (tick time minus delay), so a re-solve on a uniform grid would share no instant with the
    live solve it should be compared with, or replace.

    Parameters
    ----------
    t_solve_ns : (N,) int64
        The recorded frames' solve instants, in any order.
    period_ns : int
        The output period.

    Returns
    -------
    (M,) int64, M >= number of unique instants
    """
    t = np.unique(t_solve_ns)
    if t.size < 2:
        return t
    gaps = np.flatnonzero(np.diff(t) > 1.5 * period_ns)
    if gaps.size == 0:
        return t
    fill = [np.arange(t[i] + period_ns, t[i + 1] - period_ns // 2, period_ns, dtype=np.int64) for i in gaps]
    return np.sort(np.concatenate([t, *fill]))


def suit_sensors(suits: list[Suit]) -> tuple[str, ...]:
    """Every sensor of the suits, in suit order."""
    return tuple(sid for suit in suits for sid in suit.sensors)


def span_notes(session: Session, suits: list[Suit]) -> list[str]:
    """For an imported take (no recorded poses, no keypoints) whose suit sensors end (or start) at different
    moments: which span :func:`solve_times` solves, and which sensors bound it (seconds of the take)."""
    if not suits or session.poses() or session.keypoints():
        return []
    coverage = imu_coverage(session)
    if not coverage:
        return []
    first, last = min(a for a, _ in coverage.values()), max(b for _, b in coverage.values())
    origin = session.manifest.get("started_monotonic_ns")
    origin = origin if isinstance(origin, int) and not isinstance(origin, bool) else first
    notes = []
    for suit in suits:
        common = common_span(coverage, suit.sensors)
        if common is None or (common[0] - first < 20_000_000 and last - common[1] < 20_000_000):
            continue  # all within two samples of a 100 Hz take: nothing left out worth saying

        have = [s for s in suit.sensors if s in coverage]
        starts = max(have, key=lambda s: coverage[s][0])
        ends = min(have, key=lambda s: coverage[s][1])
        bounds = []
        if common[0] - first >= 20_000_000:
            bounds.append(f"{starts} ({suit.calibration.bones.get(starts, '?')}) starts "
                          f"{(common[0] - first) / 1e9:.2f} s after the first sample")  # fmt: skip
        if last - common[1] >= 20_000_000:
            bounds.append(f"{ends} ({suit.calibration.bones.get(ends, '?')}) ends "
                          f"{(last - common[1]) / 1e9:.2f} s before the take's last sample")  # fmt: skip
        notes.append(f"suit:{suit.id}: solved {(common[0] - origin) / 1e9:.2f}-{(common[1] - origin) / 1e9:.2f} s "
                     f"of the take, the span all {len(have)} of its sensors cover ({'; '.join(bounds)})")  # fmt: skip
    return notes


def imu_coverage(session: Session) -> dict[str, tuple[int, int]]:
    """Per sensor of the session's IMU stream: the buffer times of its first and last usable sample (ns)."""
    out: dict[str, tuple[int, int]] = {}
    for r in session.imu():
        if r.t_ns < 0:
            continue
        first, last = out.get(r.sensor, (r.t_ns, r.t_ns))
        out[r.sensor] = (min(first, r.t_ns), max(last, r.t_ns))
    return out


def common_span(coverage: dict[str, tuple[int, int]], sensors: tuple[str, ...]) -> tuple[int, int] | None:
    """The span all of ``sensors`` that have samples cover (ns): from the latest first sample to the earliest last.

    The sensors of one recording stop at different moments (MT Manager's exports of wireless MTw sensors end up to
    a second apart); solving beyond one sensor's end solves its bone from the prior, and the stance foot's contact
    from one leg: the tail of an imported take lurched and sank by centimetres. None: no such sensor, or they
    never overlap."""
    spans = [coverage[s] for s in sensors if s in coverage]
    if not spans:
        return None
    lo, hi = max(a for a, _ in spans), min(b for _, b in spans)
    return (lo, hi) if lo <= hi else None


def imu_times(records: list[ImuRecord], refit: bool = True) -> list[tuple[int, ImuRecord]]:
    """(host time, sample) of every usable IMU sample, sorted by time.

    With ``refit``, a sensor's samples that carry a device counter are re-timed by one
    fit over all of its (device counter, host arrival) pairs (:func:`~mocapd.pipeline.clocksync.offline_clock_map`:
    the lower envelope of the arrival delays over the whole session), where the live map only had the last
    seconds (and a starved host delays arrivals by up to seconds). Sensors without a counter, or whose counter
    reset during the session, keep their recorded buffer times.
    """
    by_sensor: dict[str, list[ImuRecord]] = defaultdict(list)
    for r in records:
        by_sensor[r.sensor].append(r)
    out: list[tuple[int, ImuRecord]] = []
    for recs in by_sensor.values():
        times = [r.t_ns for r in recs]
        if refit and all(r.device_ticks is not None for r in recs):
            ticks = np.array([r.device_ticks for r in recs], dtype=np.int64)
            mapped = offline_clock_map(ticks, np.array([r.host_ns for r in recs], dtype=np.int64), tick_hz=TICK_HZ)
            if mapped is not None:
                times = mapped.tolist()
        out.extend((t, r) for t, r in zip(times, recs, strict=True) if t >= 0)
    out.sort(key=lambda x: x[0])
    return out


def camera_changes(session: Session, cameras: list[Camera]) -> list[tuple[int, int, Camera]]:
    """(solve time ns, camera index, new camera) of every camera recalibrated while the session was recorded (its
    ``camera`` events), in time order: the camera to solve with after that instant (the event's ``doubt_ns`` where
    it has one: when the watch first doubted the camera, else its ``t_ns``: when the daemon swapped it). A damaged
    event (a camera that is not the rig's, or that changes more than its pose) is an InputError naming the
    stream."""
    out = []
    for e in session.events():
        if e.get("kind") != "camera":
            continue
        where = f"{session.path / (EVENTS + SUFFIX)}: damaged camera event at t_ns {e['t_ns']}"
        try:
            index, d = e["index"], e["camera"]
            if isinstance(index, bool) or not isinstance(index, int) or not 0 <= index < len(cameras):
                raise InputError(f"index {index!r} is not a camera of the session's {len(cameras)}")
            if not isinstance(d, dict):
                raise InputError("camera is not a table")
            cam = camera_from_dict(d)
        except KeyError as exc:
            raise InputError(f"{where}: no key {exc}") from None
        except (MocapdError, TypeError, ValueError) as exc:
            raise InputError(f"{where}: {exc}") from None
        old = cameras[index]
        if (cam.name, cam.width, cam.height) != (old.name, old.width, old.height) or not (
            np.array_equal(cam.K, old.K) and np.array_equal(cam.dist, old.dist)
        ):
            raise InputError(f"{where}: camera {cam.name} is not the session's {old.name} at another pose")
        t, doubt = e["t_ns"], e.get("doubt_ns")
        assert isinstance(t, int)  # decode_event checked it
        since = doubt if isinstance(doubt, int) and not isinstance(doubt, bool) and doubt <= t else t
        out.append((since, index, cam))
    return sorted(out, key=lambda x: x[0])


def live_poses(session: Session) -> dict[tuple[int, str], tuple[FloatArray, Skeleton | None]]:
    """(solve time ns, identity) -> (θ, skeleton: None for the rig's) of every pose the session recorded live for
    its solve's own instant (a predicted pose, for a later instant, is left out)."""
    return {
        (f.t_solve_ns, p.identity): (p.theta, p.skeleton)
        for f in session.poses()
        for p in f.people
        if p.t_pose_ns is None or p.t_pose_ns == f.t_solve_ns
    }


def forward_resolve(
    session: Session,
    opts: ResolveOptions,
    progress: Callable[[int], None] | None = None,
    counters: dict[str, int] | None = None,
) -> list[PoseRecord]:
    """Pass 1: every recorded input through the daemon's scheduler at the recorded solve times, the cameras
    recalibrated while recording replaced at their instants (:func:`camera_changes`), the live poses kept where
    the objective prefers them (:attr:`ResolveOptions.keep_live`); ``progress`` is called with 1 after each frame;
    ``counters`` is updated with the scheduler's at the end."""
    rig = session_rig(session)
    sched, ingest = session_scheduler(rig, opts)
    if opts.keep_live:
        live = live_poses(session)
        sched.reference_pose = lambda t, identity: live.get((t, identity))
    changes = camera_changes(session, rig.cameras)
    ic = 0
    o = rig.options
    kps = sorted(session.keypoints(), key=lambda k: (k.capture_ns, k.camera))
    imu = imu_times(session.imu(), opts.refit_imu_clock)
    ahead = o.keypoint_max_gap_ns + o.period_ns
    ik = ii = 0
    row = np.full(9, np.nan)
    out = []
    for t in solve_times(session, o.rate_hz, suit_sensors(rig.suits)):
        while ik < len(kps) and kps[ik].capture_ns <= t + ahead:
            k = kps[ik]
            sched.add_detections(k.camera, k.capture_ns, Detections2D(k.keypoints, k.confidences), k.arrival_ns)
            ik += 1
        while ii < len(imu) and imu[ii][0] <= t + ahead:
            ti, r = imu[ii]
            row[0:4], row[4:7] = r.quat, r.acc
            ingest.stream(r.sensor).buffer.push(ti, row)
            ii += 1
        while ic < len(changes) and changes[ic][0] < t:  # as live: from the first solve after the change
            sched.replace_camera(changes[ic][1], changes[ic][2])
            ic += 1
        frame = sched.tick(int(t) + o.latency_ns)
        people = tuple(
            PersonRecord(p.identity, p.suit, p.track, p.views, p.imus, p.iterations, p.converged, p.confidence,
                         p.theta, p.joints, p.skeleton, hands=p.hands)
            for p in frame.people
        )  # fmt: skip
        out.append(PoseRecord(frame.frame, frame.t_solve_ns, frame.tick_ns, frame.missing_cameras, people))
        if progress is not None:
            progress(1)
    if counters is not None:
        counters.update(sched.counters)
    return out


# ---------------------------------------------------------------------------------------------- smoothing
def rts_smooth(t_s: FloatArray, z: FloatArray, sigma: FloatArray, accel: FloatArray) -> FloatArray:
    """Constant-velocity RTS smoother of independent channels.

    Parameters
    ----------
    t_s : array, shape (n,)
        Increasing times (s).
    z : array, shape (n, c)
        Measurements.
    sigma : array, shape (c,)
        Measurement noise standard deviation per channel.
    accel : array, shape (c,)
        White-acceleration spectral density per channel (process noise).

    Returns
    -------
    array, shape (n, c)
        Smoothed values.
    """
    n, c = z.shape
    if n < 3:
        return z.copy()
    r = sigma**2
    x = np.zeros((n, c, 2))
    P = np.zeros((n, c, 2, 2))
    xp = np.zeros((n, c, 2))
    Pp = np.zeros((n, c, 2, 2))
    x[0, :, 0] = z[0]
    P[0, :, 0, 0] = r
    P[0, :, 1, 1] = 1e2  # the initial velocity is unknown
    F = np.tile(np.eye(2), (n, 1, 1))
    for k in range(1, n):
        dt = t_s[k] - t_s[k - 1]
        F[k, 0, 1] = dt
        Qk = accel[:, None, None] * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
        xp[k] = np.einsum("ij,cj->ci", F[k], x[k - 1])
        Pp[k] = np.einsum("ij,cjk,lk->cil", F[k], P[k - 1], F[k]) + Qk
        s = Pp[k, :, 0, 0] + r
        gain = Pp[k, :, :, 0] / s[:, None]  # (c, 2)
        x[k] = xp[k] + gain * (z[k] - xp[k, :, 0])[:, None]
        P[k] = Pp[k] - gain[:, :, None] * Pp[k, :, 0, :][:, None, :]
    xs = x.copy()
    for k in range(n - 2, -1, -1):
        G = np.einsum("cij,kj,ckl->cil", P[k], F[k + 1], np.linalg.inv(Pp[k + 1]))
        xs[k] = x[k] + np.einsum("cij,cj->ci", G, xs[k + 1] - xp[k + 1])
    return xs[:, :, 0]


def _segments(t_ns: NDArray[np.int64], max_gap_ns: float) -> list[slice]:
    cuts = np.flatnonzero(np.diff(t_ns) > max_gap_ns) + 1
    bounds = [0, *cuts.tolist(), t_ns.size]
    return [slice(a, b) for a, b in itertools.pairwise(bounds)]


def smooth_thetas(t_ns: NDArray[np.int64], thetas: FloatArray, opts: ResolveOptions) -> FloatArray:
    """Smoothed θ (n, 66) of one subject's frames (see the module docstring)."""
    out = thetas.copy()
    for seg in _segments(t_ns, opts.max_gap_s * 1e9):
        if t_ns[seg][-1] - t_ns[seg][0] < opts.min_segment_s * 1e9:
            continue
        th = thetas[seg]
        n = th.shape[0]
        q = _global_quats(quat_from_rotvec(th[:, 3:].reshape(n, N_BONES, 3)))
        for k in range(1, n):  # sign continuity along time
            flip = np.sum(q[k] * q[k - 1], axis=-1) < 0
            q[k, flip] *= -1.0
        z = np.concatenate([th[:, 0:3], q.reshape(n, -1)], axis=1)
        sigma = np.r_[np.full(3, opts.root_sigma_m), np.full(4 * N_BONES, opts.rot_sigma)]
        accel = np.r_[np.full(3, opts.root_accel), np.full(4 * N_BONES, opts.rot_accel)]
        zs = rts_smooth((t_ns[seg] - t_ns[seg][0]) / 1e9, z, sigma, accel)
        out[seg, 0:3] = zs[:, 0:3]
        local = _local_quats(quat_normalize(zs[:, 3:].reshape(n, N_BONES, 4)))
        out[seg, 3:] = rotvec_from_quat(local).reshape(n, -1)
    return out


def _global_quats(local: FloatArray) -> FloatArray:
    """Each bone's rotation in the world (n, N_BONES, 4) from the local ones (parents come before children).

    The smoother works on these, not on the local rotations: keypoints fix a bone's direction, not its twist, so
    the solve can turn an upper arm about its own axis from one frame to the next while the forearm's local
    rotation undoes it (the same pose). Blending two such local solutions puts the forearm where neither was
    (``resolve`` lost the waving forearms and heads that live kept, ``mocapd eval keypoints``); blending the
    world rotations of two poses with the same bone directions keeps the directions."""
    out = local.copy()
    for b, parent in enumerate(PARENTS):
        if parent >= 0:
            out[:, b] = quat_multiply(out[:, parent], local[:, b])
    return out


def _local_quats(world: FloatArray) -> FloatArray:
    """The inverse of :func:`_global_quats`."""
    out = world.copy()
    for b, parent in enumerate(PARENTS):
        if parent >= 0:
            out[:, b] = quat_multiply(quat_conjugate(world[:, parent]), world[:, b])
    return out


def smooth_frames(frames: list[PoseRecord], skeleton: Skeleton, opts: ResolveOptions) -> list[PoseRecord]:
    """Pass 2: every subject's θ smoothed over time; joints recomputed from the smoothed θ."""
    # One smoothing run per identity and skeleton: when body sizing gives a person their skeleton, θ changes meaning
    # (the root moves to the new hips), and smoothing across that step would smear it over both sides.
    where: dict[tuple[str, bytes], list[tuple[int, int]]] = defaultdict(list)  # -> (frame index, person index)
    for i, f in enumerate(frames):
        for j, p in enumerate(f.people):
            shape = b"" if p.skeleton is None else skeleton_key(p.skeleton)  # by value: decoded records are copies
            where[(p.identity, shape)].append((i, j))
    new_theta: dict[tuple[int, int], FloatArray] = {}
    for idx in where.values():
        t = np.array([frames[i].t_solve_ns for i, _ in idx], dtype=np.int64)
        th = np.array([frames[i].people[j].theta for i, j in idx])
        sm = smooth_thetas(t, th, opts)
        new_theta.update({key: sm[k] for k, key in enumerate(idx)})
    kins = PerSkeleton(Kinematics(skeleton), Kinematics)  # each person on their own (sized) skeleton

    def joints(p: PersonRecord, theta: FloatArray) -> FloatArray:
        positions: FloatArray = kins.get(p.skeleton).forward(theta).positions
        return positions

    out = []
    for i, f in enumerate(frames):
        people = tuple(
            replace(p, theta=new_theta[(i, j)], joints=joints(p, new_theta[(i, j)])) for j, p in enumerate(f.people)
        )
        out.append(replace(f, people=people))
    return out


def resolve(
    session: Session, opts: ResolveOptions | None = None, progress: Callable[[int], None] | None = None
) -> tuple[list[PoseRecord], dict[str, Any]]:
    """Both passes; returns the frames and a summary (frames, people solves, inputs used). ``progress`` is called
    with 1 per frame of the forward pass."""
    opts = opts or ResolveOptions()
    counters: dict[str, int] = {}
    frames = forward_resolve(session, opts, progress, counters)
    rig = session_rig(session)
    if opts.smooth:
        frames = smooth_frames(frames, rig.skeleton, opts)
    monitors = plausibility(frames)
    summary = {
        "frames": len(frames),
        "person_solves": sum(len(f.people) for f in frames),
        "live_poses_kept": counters.get("reference_kept", 0),
        "keypoint_frames": session.reports["keypoints"].records - 1 if "keypoints" in session.reports else 0,
        "imu_samples": session.reports["imu"].records - 1 if "imu" in session.reports else 0,
        "camera_changes": [{"camera": c.name, "t_ns": t} for t, _, c in camera_changes(session, rig.cameras)],
        "options": {k: getattr(opts, k) for k in opts.__dataclass_fields__},
        "plausibility": {identity: m.status() for identity, m in sorted(monitors.items())},
        "notes": [*span_notes(session, rig.suits),
                  *(f"{identity}: {line}" for identity, m in sorted(monitors.items()) for line in m.summary_lines())],
    }  # fmt: skip
    return frames, summary


def plausibility(frames: list[PoseRecord]) -> dict[str, PlausibilityMonitor]:
    """Every subject's solved poses through the anatomical plausibility checks (:mod:`mocapd.core.plausibility`:
    knees and elbows bending the wrong way, a pelvis facing backwards while the legs walk forwards), per identity."""
    monitors: dict[str, PlausibilityMonitor] = {}
    for f in frames:
        for p in f.people:
            monitors.setdefault(p.identity, PlausibilityMonitor()).step(f.t_solve_ns / 1e9, p.theta)
    return monitors


def write_resolved(session: Session, frames: list[PoseRecord], out: str | Path | None = None) -> Path:
    """Write the resolved frames as the session's ``poses-resolved`` stream, or to ``out`` (a stream file)."""
    from mocapd.io.session import RESOLVED, SUFFIX, write_pose_stream
    from mocapd.protocols.session_format import encode_pose

    payloads = [encode_pose(f) for f in frames]
    if out is None:
        return write_pose_stream(session.path, RESOLVED, payloads)
    p = Path(out)
    name = p.name.removesuffix(SUFFIX)
    p.parent.mkdir(parents=True, exist_ok=True)
    return write_pose_stream(p.parent, name, payloads)
