"""The fixed-latency scheduler (seed 003 §3.4.2): sample every buffer at ``t = now - latency``, sort, solve, publish.

Cameras are not synchronised with each other or with the IMUs, and the detector runs slower than the solver, so
the solver runs at its own output rate a fixed delay behind wall time. At each tick:

1. **sample**: every camera's :class:`~mocapd.pipeline.keypoint_timeline.DetectionTimeline` at ``t`` (linear
   interpolation; detections older than ``keypoint_max_age`` are dropped, never extrapolated) and every suit's
   IMU ring buffers at ``t`` (slerp) and at ``t - dt`` (accelerations, which the solver wants for the previous
   frame); each look-up's outcome is counted per device;
2. **sort**: the sampled 2D people into tracked people (:class:`~mocapd.core.people.PeopleTracker`: detection
   sorting, enrolment, suit binding);
3. **solve**: one warm-started :class:`~mocapd.core.solver.PoseSolver` per identity;
4. **publish**: a :class:`PoseFrame` (frame counter, solve time, per person θ, joint positions, confidence, and
   the instant each pose is for).

Two things happen around the solve for people wearing a suit:

- **heading correction** (:mod:`mocapd.core.heading`): while at least two cameras see the wearer, each sensor's
  heading offset is estimated from the triangulated keypoints and applied to its bone orientations (and the
  accelerations rotated with them); while they do not, the offsets stay frozen;
- **predicted output** (``options.prediction.output == "predicted"``, :mod:`mocapd.pipeline.prediction`): the
  solved pose is carried forward from ``t`` to the suit's newest IMU instant with what the IMUs measured since;
  the published person carries that instant (``t_pose_ns``) and the solve it came from (``solved``). People
  without a suit keep the delayed pose.

**Solving at half rate** (the governor's last step, :mod:`mocapd.pipeline.governor`): with
:attr:`~FixedLatencyScheduler.solve_every` at 2 the people are solved on every other tick only; the ticks between
still publish a frame, each person of the last solve carried on to the tick's solve time at the velocity of their
last two solves (:mod:`mocapd.core.carry`, ``PersonPose.filled``; counted in ``ticks_solved`` / ``ticks_filled``).
The solver's motion terms and the suits' accelerations then see the true interval between a person's solves
(:attr:`~FixedLatencyScheduler.solve_dt`).

In the daemon a tick is split in two: :meth:`FixedLatencyScheduler.sample` (step 1) on the event loop, which owns
the buffers, and :meth:`FixedLatencyScheduler.solve` (steps 2-4) on the daemon's tick thread, the people of a tick
on a pool of solve threads where there are cores for it; :meth:`FixedLatencyScheduler.tick` runs both in one thread
(tests, ``resolve``).

Each device has a configured time offset (its clock runs ``offset`` ahead of the host's: its samples are filed at
``t_device - offset``). Time is passed in (``now_ns``); the stage timer is injected (wall and CPU clocks), so the
scheduler runs the same in the daemon and in tests on synthetic timelines.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Executor
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mocapd.core import _kernel
from mocapd.core.body_size import can_size, estimate_skeleton
from mocapd.core.camera import Camera, triangulate_projections
from mocapd.core.camera_mounting import CameraMountingEstimator, MountingOptions
from mocapd.core.carry import carry_pose
from mocapd.core.hand_skeleton import HandPose
from mocapd.core.heading import BoneVectors, HeadingEstimator, HeadingOptions, bone_vectors, observe_headings, yaw_quat
from mocapd.core.imu import ImuMount
from mocapd.core.imu_calibration import ImuCalibration
from mocapd.core.imu_start import initial_pose_from_imus
from mocapd.core.keypoints import TrackTargets
from mocapd.core.kinematics import Kinematics
from mocapd.core.lr_collapse import collapsed_pairs, drop_collapsed
from mocapd.core.lr_flips import FlipMemo, FlipOptions, apply_swaps, choose_swaps, lr_pairs
from mocapd.core.people import PeopleTracker, Person
from mocapd.core.per_skeleton import PerSkeleton
from mocapd.core.plausibility import PlausibilityMonitor
from mocapd.core.prior import PcaPrior
from mocapd.core.rotations import matrix_from_quat, quat_multiply, quat_normalize, quat_slerp
from mocapd.core.skeleton import N_BONES, Skeleton
from mocapd.core.solver import LMOptions, Observations, PoseSolver
from mocapd.core.sorting import Detections2D
from mocapd.core.terms import CostOptions
from mocapd.core.warm_start import initial_pose
from mocapd.errors import InputError
from mocapd.pipeline.fusion import FusionStage, Mode
from mocapd.pipeline.hands import HandStage
from mocapd.pipeline.imu_ingest import ImuIngest
from mocapd.pipeline.keypoint_timeline import USABLE, DetectionTimeline, SampleStatus
from mocapd.pipeline.latency import AutoLatency, AutoLatencyOptions, LatencyStats
from mocapd.pipeline.mattes import MatteSource
from mocapd.pipeline.prediction import PosePredictor, PredictionOptions, SuitState
from mocapd.pipeline.ringbuffer import IMU_FIELDS, LookupStatus, RingBuffer
from mocapd.pipeline.time_alignment import (
    Steps,
    drain,
    estimate_imu_lag_steps,
    estimate_lag_steps,
    keypoint_speed_steps,
)

FloatArray = NDArray[np.float64]
log = logging.getLogger(__name__)
IntArray = NDArray[np.int64]
GRAVITY = 9.81
HEIGHT_EVERY = 3  # ticks between two of them: 20 Hz at 60 Hz output covers the 0.3-5 Hz band it is compared in
HEIGHT_HISTORY_S = 12.0  # solved heights kept per suit for the IMU offset estimate (the IMU buffers hold ~5 s)
SIZE_MIN_CONFIDENCE = 0.3  # keypoints below this confidence take no part in the body-size triangulation
HEADING_EVERY_NS = 50_000_000  # at least this between two heading observations of a suit (20 Hz: plenty for a
# window of seconds; every tick would triangulate and observe three times as often for nothing)
READ_WAIT_S = 0.02  # the longest the event loop waits for the tick thread to read the scheduler's state
STAGES = ("detect", "sample", "sort", "solve", "predict", "publish", "end_to_end", "imu_to_publish")


@dataclass(frozen=True)
class SchedulerOptions:
    """How the scheduler samples and solves (the ``[daemon]`` section of config.toml)."""

    rate_hz: float = 60.0
    """Output rate (ticks per second)."""
    latency_ns: int = 150_000_000
    """Fixed delay between wall time and solve time (unused with ``auto_latency``)."""
    auto_latency: AutoLatencyOptions | None = None
    """Set: the delay follows the detector (:class:`~mocapd.pipeline.latency.AutoLatency`, ``latency_s = "auto"``)
    instead of ``latency_ns``."""
    keypoint_max_age_ns: int = 100_000_000
    """Detections further than this from the solve time are not used (held or nearest frame)."""
    keypoint_max_gap_ns: int = 250_000_000
    """Two detected frames further apart than this are not interpolated across."""
    match_px: float = 80.0
    """Largest mean keypoint motion (pixels) of one person between two detected frames of a camera."""
    camera_offsets_ns: tuple[int, ...] = ()
    """Per camera: how far its time stamps run ahead of the host clock (empty: all zero)."""
    imu_offsets_ns: dict[str, int] = field(default_factory=dict)
    """Per IMU sensor id: how far its buffered times run ahead of the host clock."""
    body_size_frames: int = 0
    """Size each tracked person's skeleton from this many ticks of their triangulated keypoints (0: everyone
    keeps the configured skeleton)."""
    body_size_first_frames: int = 0
    """Before that, a provisional size from this many ticks (0: none; the configured skeleton until then)."""
    prediction: PredictionOptions = field(default_factory=PredictionOptions)
    """What is published for suit wearers: the delayed solve, or it carried to the IMUs' newest instant."""
    heading: HeadingOptions = field(default_factory=HeadingOptions)
    """Per-sensor heading correction from the cameras."""
    mounting: MountingOptions = field(default_factory=lambda: MountingOptions(enabled=False))
    """Each suit's mountings refined once from the cameras' first seconds of its wearer
    (:mod:`mocapd.core.camera_mounting`; off unless ``[daemon] mounting_from_cameras``)."""
    flips: FlipOptions = field(default_factory=FlipOptions)
    """Per-view left/right flips of the detections, undone before the solve (:mod:`mocapd.core.lr_flips`)."""

    @property
    def period_ns(self) -> int:
        return round(1e9 / self.rate_hz)

    @property
    def dt(self) -> float:
        return 1.0 / self.rate_hz


@dataclass(frozen=True)
class Suit:
    """One person's IMU suit: its calibration and the solver's IMU mounts in the order measurements are given."""

    id: str
    calibration: ImuCalibration
    mounts: tuple[ImuMount, ...]
    sensors: tuple[str, ...]  # sensor id per mount

    @staticmethod
    def from_calibration(suit_id: str, calibration: ImuCalibration, skeleton: Skeleton) -> Suit:
        """Mounts at the default sensor sites of the calibrated bones (orientation comes from the calibration)."""
        from mocapd.core.imu import default_mounts

        sensors = tuple(sorted(calibration.bones))
        mounts = default_mounts(tuple(calibration.bones[s] for s in sensors), skeleton)
        return Suit(suit_id, calibration, mounts, sensors)


@dataclass(frozen=True)
class PersonPose:
    """One solved person."""

    identity: str
    track: int
    suit: str | None
    theta: FloatArray  # (66,)
    joints: FloatArray  # (21, 3) global joint positions, metres
    confidence: float  # mean detector confidence of the keypoints used, scaled down below two views
    views: int
    imus: int  # IMUs with a measurement this frame
    iterations: int
    converged: bool
    skeleton: Skeleton | None = None  # the skeleton theta is on (None: the rig's)
    t_pose_ns: int | None = None  # the instant the pose is for (None: the frame's t_solve_ns)
    solved: PersonPose | None = None  # a predicted pose: the delayed solve it was carried from (else None)
    hands: HandPose | None = None  # the fingers (mocapd.core.hand_skeleton), when hand keypoints were solved
    filled: bool = False  # not solved this tick: the last solve carried on (solve_every > 1, mocapd.core.carry)


@dataclass(frozen=True)
class PoseFrame:
    """What one tick publishes."""

    frame: int
    t_solve_ns: int
    tick_ns: int  # the wall time the tick was scheduled for
    people: list[PersonPose]
    missing_cameras: int
    output: str = "delayed"  # the output mode: "delayed" or "predicted" (suit wearers carried forward)

    def pose_time_ns(self, person: PersonPose) -> int:
        """The instant ``person``'s pose is for (its own when predicted, else the solve time)."""
        return self.t_solve_ns if person.t_pose_ns is None else person.t_pose_ns


class TickPlan:
    """The output clock: tick times ``start + k · period``.

    A tick that runs late (the process was not scheduled in time: a busy or shared machine) still runs, for its own
    scheduled time, as long as it is at most ``max_late_ns`` late: the fixed latency leaves every input in place
    for it, the frame keeps its even solve-time spacing and the consumer sees a short burst instead of a hole
    (counted in :attr:`late`). Ticks further behind than that are skipped and counted in :attr:`missed`: after a
    real stall, solving the backlog would only delay the frames that are on time.
    """

    def __init__(self, period_ns: int, start_ns: int, max_late_ns: int = 0) -> None:
        self.period_ns = period_ns
        self.next_ns = start_ns
        self.max_late_ns = max_late_ns
        self.missed = 0
        self.late = 0

    def advance(self, now_ns: int) -> int:
        """After running the tick due at :attr:`next_ns`: schedule the next one; returns ticks skipped now."""
        self.next_ns += self.period_ns
        skipped = 0
        behind = now_ns - self.max_late_ns - self.next_ns
        if behind > 0:
            skipped = -(-behind // self.period_ns)
            self.next_ns += skipped * self.period_ns
        if now_ns > self.next_ns:
            self.late += 1  # the next tick is already due: it runs at once, late but within the bound
        self.missed += skipped
        return skipped


@dataclass(frozen=True)
class TickInputs:
    """What :meth:`FixedLatencyScheduler.sample` took for one tick (the tick's own copies)."""

    now_ns: int  # the wall time the tick was scheduled for
    t_solve_ns: int  # the instant solved for: now - latency
    detections: list[Detections2D]  # per camera, at t_solve_ns (fill ticks: empty between two frames)
    missing: int  # cameras without usable keypoints
    suits: dict[str, SuitSample]  # per suit, at t_solve_ns
    frames: list[int] = field(default_factory=list)  # per camera, the detection frame sampled (its capture time)
    fill: bool = False  # a tick between two solves (solve_every > 1): the people are carried, not solved


PERSON_STAGES = ("unflip", "solve", "size", "total")
"""Per person and tick: the flip search, the LM solve, the body sizing and the whole person job (CPU, ms)."""


@dataclass
class SuitSample:
    orientations: FloatArray  # (n_imu, 4) measured global bone orientations (heading-corrected)
    raw: FloatArray  # (n_imu, 4) the same before heading correction (what the heading estimate is made from)
    sensor_quats: FloatArray  # (n_imu, 4) sensor orientations at t, device frame (where the prediction starts)
    accelerations: FloatArray  # (n_imu, 3) global accelerations at t - dt, gravity removed
    mask: NDArray[np.bool_]  # (n_imu,)
    has_acceleration: bool  # accelerations of the previous frame are known for every masked IMU


class FixedLatencyScheduler:
    """Samples, sorts, solves and publishes one frame per :meth:`tick`.

    Parameters
    ----------
    cameras : list of Camera
        The rig; camera ``i``'s detections arrive through :meth:`add_detections` with index ``i``.
    skeleton, targets, prior, cost, lm, backend
        The per-person solver's set-up (see :class:`~mocapd.core.solver.PoseSolver`).
    people : PeopleTracker
        Detection sorting and suit binding.
    ingest : ImuIngest, optional
        The IMU buffers (filled by the IMU inputs); needed when ``suits`` are given.
    suits : list of Suit
    options : SchedulerOptions
    fusion, fusion_mode, mattes
        The learned fusion (issue 30, :mod:`mocapd.pipeline.fusion`), how its joints enter each person's solve
        ("solver": not at all; "both": as E_J observations on the frames it runs; "learned": the skeleton fitted
        to them alone) and the cameras' foreground mattes it carves.
    hands : HandStage, optional
        The per-person finger solve, given when the detections carry hand keypoints (their columns after the
        body's); None: hands off, and nothing of it runs.
    wall_clock, cpu_clock : callables returning int ns
        Stage timers (defaults: ``time.perf_counter_ns`` and the thread's CPU time). The solve time itself is
        always the ``now_ns`` given to :meth:`tick`.
    """

    def __init__(
        self,
        cameras: list[Camera],
        skeleton: Skeleton,
        targets: TrackTargets,
        people: PeopleTracker,
        *,
        prior: PcaPrior | None = None,
        ingest: ImuIngest | None = None,
        suits: list[Suit] | None = None,
        options: SchedulerOptions | None = None,
        cost: CostOptions | None = None,
        lm: LMOptions | None = None,
        backend: str = "compiled",
        fusion: FusionStage | None = None,
        fusion_mode: Mode = "solver",
        mattes: MatteSource | None = None,
        hands: HandStage | None = None,
        wall_clock: Callable[[], int] = time.perf_counter_ns,
        cpu_clock: Callable[[], int] = time.thread_time_ns,
    ) -> None:
        self.options = options if options is not None else SchedulerOptions()
        o = self.options
        if o.camera_offsets_ns and len(o.camera_offsets_ns) != len(cameras):
            raise InputError(f"camera_offsets_ns: {len(o.camera_offsets_ns)} offsets for {len(cameras)} cameras")
        if suits and ingest is None:
            raise InputError("suits need the IMU ingest that buffers their sensors")
        self.cameras = list(cameras)  # its own list: replace_camera changes it
        self.skeleton = skeleton
        self.targets = targets
        self.people = people
        self.prior = prior
        self.ingest = ingest
        self.suits = {s.id: s for s in suits or []}
        self.cost = cost
        self.lm = lm
        self.backend = backend
        if fusion_mode != "solver" and (fusion is None or mattes is None):
            raise InputError(f"fusion mode {fusion_mode!r} needs the learned fusion's networks and a matte source")
        self.fusion = fusion if fusion_mode != "solver" else None
        self.fusion_mode = fusion_mode
        self.mattes = mattes
        #: the finger solve (:mod:`mocapd.pipeline.hands`) when the detections carry hand keypoints; None: off
        self.hands = hands
        self._tick_mattes: list[NDArray[np.float32] | None] | None = None  # read once per tick, when needed
        self._tick_t = 0
        self.kin = Kinematics(skeleton)
        # every column of the detections (the hands' after the body's): a camera without a sample gets an empty one
        columns = len(targets) if hands is None else max(len(targets), int(hands.columns.max()) + 1)
        self.timelines = [
            DetectionTimeline(
                columns, max_age_ns=o.keypoint_max_age_ns, max_gap_ns=o.keypoint_max_gap_ns, match_px=o.match_px
            )
            for _ in cameras
        ]
        self.solvers: dict[str, PoseSolver] = {}
        #: the delay behind wall time now: fixed, or following the detector
        self.auto_latency = AutoLatency(len(cameras), o.auto_latency) if o.auto_latency is not None else None
        self.latency_ns = o.latency_ns if self.auto_latency is None else self.auto_latency.latency_ns
        self.frame = 0
        self.published = 0  # frames published (record_publish): ``frame`` runs ahead while one is on its way
        self.latency = {s: LatencyStats() for s in STAGES}
        self.cpu_ns = dict.fromkeys(STAGES[1:6], 0)
        self.keypoint_status = [dict.fromkeys((s.value for s in SampleStatus), 0) for _ in cameras]
        self.imu_status: dict[str, dict[str, int]] = {}
        self.counters = {"ticks": 0, "person_solves": 0, "not_converged": 0, "detections_rejected": 0,
                         "bodies_sized": 0, "body_size_failed": 0, "lr_swaps": 0, "lr_collapsed": 0,
                         "lr_pairs_searched": 0, "lr_pairs_reused": 0,
                         "learned_observations": 0, "predictions_skipped": 0,
                         "ticks_solved": 0, "ticks_filled": 0, "reference_kept": 0}  # fmt: skip
        #: people are solved on every ``solve_every``-th tick (the governor's last step sets 2); on the ticks between,
        #: each is their last solve carried on at the velocity of their last two (:mod:`mocapd.core.carry`)
        self.solve_every = 1
        self._since_solve = 0  # ticks sampled since the last solving one
        # Per identity: its last solve (instant, pose) and the θ and instant of the one before (None: none).
        self._solved: dict[str, tuple[int, PersonPose, FloatArray | None, int]] = {}
        self._lr_pairs = lr_pairs(list(getattr(targets, "names", ())))
        #: per identity, the flip search's results of the previous tick (pairs whose inputs did not change are not
        #: searched again, :class:`~mocapd.core.lr_flips.FlipMemo`)
        self._flip_memos: dict[str, FlipMemo] = {}
        # The hands follow the wrists' labels (the detector placed each hand's crop from its arm)
        target_names = tuple(getattr(targets, "names", ()))
        wrists = [p for p, (left, _) in enumerate(self._lr_pairs) if target_names[left] == "left_wrist"]
        self._wrist_pair = wrists[0] if wrists else None
        self._projections = (np.stack([c.projection_matrix for c in cameras]) if cameras
                             else np.zeros((0, 3, 4)))  # fmt: skip
        self._q_ib = {s.id: np.array([s.calibration.q_ib[sid] for sid in s.sensors]) for s in suits or []}
        self.heading = HeadingEstimator(o.heading)
        self.mounting = CameraMountingEstimator(o.mounting)
        self._mounting_at: dict[str, int] = {}  # solve time of each suit's last mounting observation
        self._last_mounting: dict[str, dict[str, object]] = {}
        self.predictor = PosePredictor(o.prediction)
        # Per suit: the keypoint pairs rigid with each sensor's bone (on the person's own skeleton once sized).
        self._heading_vectors = {
            s.id: _vectors_per_skeleton(skeleton, targets, tuple(m.bone for m in s.mounts)) for s in suits or []
        }
        self._seen_suits: set[str] = set()  # suits whose wearer enough cameras saw this tick
        # Per identity: knees/elbows bending the wrong way, a pelvis backwards while walking (issue 28).
        self.plausibility: dict[str, PlausibilityMonitor] = {}
        self._heading_at: dict[str, int] = {}  # solve time of each suit's last heading observation
        self._suit_samples: dict[str, SuitSample] = {}  # the latest tick's, where predict() starts from
        self._imu_width = sum(f.width for f in IMU_FIELDS)  # quat 0:4, acc 4:7 (IMU_FIELDS order)
        self._previous_acc: dict[str, tuple[int, FloatArray, NDArray[np.bool_]]] = {}
        self.suggested_offsets: dict[str, dict[str, float]] | None = None  # see estimate_camera_offsets
        self.suggested_imu_offsets: dict[str, dict[str, Any]] | None = None  # see estimate_imu_offsets
        # Solved hips height of each suit's wearer per tick: the camera side of the IMU offset estimate.
        self._heights: dict[str, deque[tuple[int, float]]] = {}
        # Body size per track: keypoints gathered until there are enough, then the track's own skeleton.
        self._sizing: dict[int, list[FloatArray]] = {}
        self._sized: set[int] = set()  # tracks sized for good (from body_size_frames)
        self.skeletons: dict[int, Skeleton] = {}
        self._restart: dict[int, FloatArray] = {}
        names = list(getattr(targets, "names", ()))
        self._names = tuple(names)
        self._sizable = can_size(self._names)  # the set names the limb joints body sizing measures
        self._hips = (
            [names.index("left_hip"), names.index("right_hip")] if {"left_hip", "right_hip"} <= set(names) else None
        )
        self._bone_ids = np.arange(N_BONES, dtype=np.float64)
        self._zero_offsets = np.zeros((N_BONES, 3))
        self._wall = wall_clock
        self._cpu = cpu_clock
        #: held while a tick solves; readers of the scheduler's state from other threads take it too
        self.lock = threading.RLock()
        self._count_lock = threading.Lock()  # counters and the heading estimator, shared by parallel person jobs
        #: solves the people of a tick in parallel when set (the daemon's solve threads); None: one after another
        self.pool: Executor | None = None
        #: per person job and stage: CPU time (ms), for the stage costs in /status and the benchmarks
        self.person_cpu = {s: LatencyStats() for s in PERSON_STAGES}
        self._pool_cpu_ns = 0  # CPU of the person jobs run on the pool this tick (not the tick thread's)
        self._tick_thread = threading.current_thread()  # the thread running the tick now
        self._last_status: dict[str, Any] = {}  # status() while a tick holds the lock
        #: called with (solve time, undistorted keypoints (n_cams, n_kp, 2), confidences (n_cams, n_kp), identity)
        #: of each person seen by two or more cameras, before the solve; returns the confidences to solve with (the
        #: bumped-camera watch, :mod:`mocapd.pipeline.camera_watch`). Called from the solve threads.
        self.observation_hook: Callable[[int, FloatArray, FloatArray, str], FloatArray] | None = None
        #: (solve time, identity) -> a pose solved before for that person at that instant and the skeleton it is on
        #: (None: the rig's), or None: ``resolve`` gives the live solve, kept where the objective rates it lower
        #: than the re-solve's (:meth:`PoseSolver.solve`'s ``alternative``; counted as ``reference_kept``)
        self.reference_pose: Callable[[int, str], tuple[FloatArray, Skeleton | None] | None] | None = None
        #: told (camera index, new camera) by :meth:`replace_camera`, under the lock, after the scheduler's own
        #: holders of the camera have it (the bumped-camera watch)
        self.camera_listeners: list[Callable[[int, Camera], None]] = []
        self._last_heading: dict[str, dict[str, Any]] = {}

    # ------------------------------------------------------------------------------------------- inputs
    def add_detections(self, camera: int, capture_ns: int, detections: Detections2D, arrival_ns: int) -> bool:
        """File one detected frame of ``camera`` captured at ``capture_ns`` (device clock) and received (detector
        done) at ``arrival_ns`` (host clock). Returns False when it was rejected (out of order)."""
        offsets = self.options.camera_offsets_ns
        t = capture_ns - (offsets[camera] if offsets else 0)
        if detections.undistorted is None and len(detections):
            # Undistorted once, here, for every tick that samples this frame (the flip search, body sizing and
            # heading triangulate in undistorted pixels).
            detections = detections.with_undistorted(self._undistort(camera, detections.keypoints))
        if not self.timelines[camera].push(t, detections):
            self.counters["detections_rejected"] += 1
            return False
        self.latency["detect"].add(arrival_ns - t)
        if self.auto_latency is not None:
            self.auto_latency.observe(camera, t, arrival_ns)
        return True

    # ------------------------------------------------------------------------------------------- cameras
    def replace_camera(self, index: int, camera: Camera) -> None:
        """Camera ``index`` is ``camera`` from the next tick on: a camera knocked during the run and re-estimated
        (:mod:`mocapd.pipeline.camera_watch`), or recalibrated. The new camera keeps its name, image size and
        intrinsics (the keypoints already filed were undistorted with them); only its pose may change.

        Every holder of the camera takes it in one step, under :attr:`lock` (which a tick holds while it solves),
        so a tick solves with the old rig or the new one, never a mix: the scheduler's projections (the flip
        search, body sizing, heading triangulation), the association's sorter, every person's solver (warm starts
        kept), the finger solve, the learned fusion, then the :attr:`camera_listeners`.

        Raises
        ------
        InputError
            No camera ``index``, or ``camera`` differs from it in more than its pose.
        """
        if not 0 <= index < len(self.cameras):
            raise InputError(f"no camera {index}: the rig has {len(self.cameras)}")
        old = self.cameras[index]
        same = (camera.name, camera.width, camera.height) == (old.name, old.width, old.height)
        if not (same and np.array_equal(camera.K, old.K) and np.array_equal(camera.dist, old.dist)):
            raise InputError(f"camera {old.name}: a camera replaced while running keeps its name, image size and "
                             "intrinsics (only its pose may change); restart with the new calibration")  # fmt: skip
        with self.lock:
            self.cameras[index] = camera
            self._projections = np.stack([c.projection_matrix for c in self.cameras])
            self.people.tracker.sorter.set_camera(index, camera)
            for solver in self.solvers.values():
                if solver.n_cams:  # a "learned" fusion solver holds no cameras
                    solver.set_camera(index, camera)
            if self.hands is not None:
                self.hands.projections = self._projections
            if self.fusion is not None:
                self.fusion.cameras[index] = camera
            for listener in self.camera_listeners:
                listener(index, camera)

    @property
    def solve_dt(self) -> float:
        """Seconds between a person's solves: a period times :attr:`solve_every` (the solver's motion terms, its
        smoothness and the IMU accelerations, difference the solves at this interval)."""
        return self.options.dt * self.solve_every

    @property
    def last_solve_ns(self) -> int:
        """The solve time of the latest tick (a camera replaced now is used from the tick after it)."""
        return self._tick_t

    # ------------------------------------------------------------------------------------------- the tick
    def tick(self, now_ns: int, *, predict: bool = True) -> PoseFrame:
        """Solve and return the frame at ``now_ns - latency``: :meth:`sample` then :meth:`solve`, in this thread.

        In predicted output the suit wearers are carried forward (:meth:`predict`) before it returns, unless
        ``predict`` is False: then the caller calls :meth:`predict` itself right before publishing, after letting
        the IMU inputs buffer what arrived while this tick solved.
        """
        out = self.solve(self.sample(now_ns))
        return self.predict(out) if predict else out

    def sample(self, now_ns: int) -> TickInputs:
        """The first half of a tick, on the thread that owns the inputs (the daemon's event loop): the delay behind
        wall time, then every camera's detections and every suit's IMU samples at the solve time. What it returns
        is the tick's own copy: the inputs may be written again while :meth:`solve` runs elsewhere."""
        if self.auto_latency is not None:
            # Before the first person solve nothing is on screen: the latency may drop to its first goal at once.
            self.latency_ns = self.auto_latency.update(now_ns, idle=self.counters["person_solves"] == 0)
        t = now_ns - self.latency_ns
        w0, c0 = self._wall(), self._cpu()
        # Solving every n-th tick: the ticks between carry the last solve on (none before the first solve).
        fill = 0 < self._since_solve < self.solve_every and self.counters["ticks_solved"] > 0
        self._since_solve = self._since_solve + 1 if fill else 1
        # A fill tick needs only how many cameras are missing: no people matched and blended for it (~1 ms).
        detections, missing, frames = self._sample_cameras(t, people=not fill)
        if fill and not self.options.prediction.predicted:
            # Likewise a fill tick in delayed output uses no IMU sample (it carries the last solve; predicted
            # output carries the wearers from them): every sensor's look-up is counted, nothing is blended (~0.5 ms
            # a tick for a 13-sensor suit).
            suits: dict[str, SuitSample] = {}
            for suit in self.suits.values():
                self._look_up_suit(suit, t)
        else:
            suits = {sid: self._sample_suit(suit, t, keep=not fill) for sid, suit in self.suits.items()}
        self._stage("sample", w0, c0)
        return TickInputs(now_ns, t, detections, missing, suits, frames, fill)

    def solve(self, inputs: TickInputs) -> PoseFrame:
        """The second half of a tick, on any one thread at a time (the daemon's tick worker): sort the sampled
        people, solve each (in parallel on :attr:`pool` when one is given), publishable frame out. Holds
        :attr:`lock` throughout, so readers of the scheduler's state on other threads (:meth:`status`) see it
        between ticks, never half-updated."""
        with self.lock:
            if inputs.fill:
                return self._fill_tick(inputs)
            return self._solve_tick(inputs)

    def _fill_tick(self, inputs: TickInputs) -> PoseFrame:
        """A tick between two solves: every person of the last solve carried on to this tick's solve time
        (:func:`~mocapd.core.carry.carry_pose`: root and bones at the velocity of their last two solves, joints from
        the carried θ, hands as solved), marked ``filled``."""
        t = inputs.t_solve_ns
        w0, c0 = self._wall(), self._cpu()
        people = []
        for t_last, pose, theta_prev, t_prev in self._solved.values():
            theta = carry_pose(pose.theta, t_last, t, theta_prev, t_prev)
            solver = self.solvers.get(pose.identity)
            if solver is not None:
                joints = self._joints(solver, theta)
            else:  # re-sized by its last solve: the solver is rebuilt at the next solve
                joints = Kinematics(pose.skeleton or self.skeleton).forward(theta).positions
            people.append(replace(pose, theta=theta, joints=joints, t_pose_ns=None, solved=None, filled=True))
        self._stage("solve", w0, c0)
        self._tick_t = t
        self.frame += 1
        self.counters["ticks"] += 1
        self.counters["ticks_filled"] += 1
        self._suit_samples = inputs.suits
        return PoseFrame(self.frame, t, inputs.now_ns, people, inputs.missing, self.options.prediction.output)

    def _remember_solves(self, t: int, poses: list[PersonPose]) -> None:
        """The people solved at ``t``, with the θ and instant of each one's solve before (what a fill carries)."""
        previous = self._solved
        self._solved = {}
        for pose in poses:
            before = previous.get(pose.identity)
            self._solved[pose.identity] = (
                (t, pose, None, 0) if before is None else (t, pose, before[1].theta, before[0])
            )

    def _solve_tick(self, inputs: TickInputs) -> PoseFrame:
        t, suits, detections = inputs.t_solve_ns, inputs.suits, inputs.detections
        self._tick_t = t
        w1, c1 = self._wall(), self._cpu()
        suit_bones = {
            sid: {suit.mounts[i].bone: s.orientations[i] for i in range(len(suit.mounts)) if s.mask[i]}
            for sid, (suit, s) in ((k, (self.suits[k], v)) for k, v in suits.items())
        }
        # The tracker counts enrolment evidence per detection frame, not per tick (issue 41): the frames sampled.
        frame = self.people.update(t, detections, {k: v for k, v in suit_bones.items() if v}, inputs.frames or None)
        w2, c2 = self._stage("sort", w1, c1)
        self._seen_suits.clear()
        self._tick_mattes = None
        people = [*frame.people, *self._imu_only_people(frame.people, suits)]
        jobs = [(p, detections, suits.get(p.suit) if p.suit else None, t) for p in people]
        self._tick_thread = threading.current_thread()
        self._pool_cpu_ns = 0
        if self.pool is not None and len(jobs) > 1 and self.fusion is None:
            # People in parallel: each job touches its own solver and track; what they share is locked
            # (counters, the heading estimator). The compiled kernels release the GIL.
            poses = list(self.pool.map(lambda job: self._solve(*job), jobs))
        else:
            poses = [self._solve(*job) for job in jobs]
        for pose in poses:
            self.plausibility.setdefault(pose.identity, PlausibilityMonitor()).step(t / 1e9, pose.theta)
        for sid, suit in self.suits.items():
            if sid not in self._seen_suits:
                self.heading.freeze(suit.sensors)  # the cameras lost the wearer: offsets stay as they are
        for sid in [k for k in self.suits if self.mounting.ready(k, t)]:
            self._refine_mountings(sid)
        self._forget_released({p.identity for p in people})
        if self.hands is not None:
            self.hands.forget(set(self.solvers))
        if self.fusion is not None:
            self.fusion.forget(set(self.solvers))
        self._stage("solve", w2, c2)
        self.cpu_ns["solve"] += self._pool_cpu_ns  # the person jobs the pool ran, on its own threads' clocks
        self._remember_solves(t, poses)
        self.frame += 1
        self.counters["ticks"] += 1
        self.counters["ticks_solved"] += 1
        self._suit_samples = suits
        return PoseFrame(self.frame, t, inputs.now_ns, poses, inputs.missing, self.options.prediction.output)

    def predict(self, frame: PoseFrame) -> PoseFrame:
        """In predicted output, ``frame`` (this scheduler's latest, from :meth:`tick`) with each suit wearer
        carried from the solve instant to the newest instant the suit's live IMUs have buffered now; the frame
        unchanged in delayed output, or when it is not the latest."""
        if not self.options.prediction.predicted or frame.frame != self.frame:
            return frame
        w0, c0 = self._wall(), self._cpu()
        samples = self._suit_samples
        people = [self._predict(p, samples[p.suit], frame.t_solve_ns) if p.suit in samples else p
                  for p in frame.people]  # fmt: skip
        self._stage("predict", w0, c0)
        return replace(frame, people=people)

    def record_publish(self, frame: PoseFrame, wall_start_ns: int, cpu_start_ns: int, published_ns: int) -> None:
        """Account the publishing stage (run by the caller), the end-to-end latency of ``frame`` (from the solve
        time, the capture instant it represents, to ``published_ns`` on the host clock) and, per suit wearer, the
        IMU-sample-to-publish latency (from the instant the pose is for: the newest IMU sample it used)."""
        self._stage("publish", wall_start_ns, cpu_start_ns)
        self.published += 1
        self.latency["end_to_end"].add(published_ns - frame.t_solve_ns)
        for p in frame.people:
            if p.suit is not None:
                self.latency["imu_to_publish"].add(published_ns - frame.pose_time_ns(p))

    def stage_clocks(self) -> tuple[int, int]:
        """(wall, CPU) now, for timing a stage run outside the scheduler."""
        return self._wall(), self._cpu()

    def _stage(self, name: str, w0: int, c0: int) -> tuple[int, int]:
        w, c = self._wall(), self._cpu()
        self.latency[name].add(w - w0)
        self.cpu_ns[name] += c - c0
        return w, c

    def _sample_cameras(self, t: int, people: bool = True) -> tuple[list[Detections2D], int, list[int]]:
        """Every camera's detections at ``t``, how many cameras have none usable, and per camera the frame they
        come from (:attr:`TimelineSample.frame_ns`). ``people=False``: the statuses only (the detections of a
        camera between two frames are then empty; :meth:`DetectionTimeline.sample`)."""
        out, frames = [], []
        missing = 0
        for c, tl in enumerate(self.timelines):
            s = tl.sample(t, with_people=people)
            self.keypoint_status[c][s.status.value] += 1
            if s.status not in USABLE:
                missing += 1
            out.append(s.detections)
            frames.append(s.frame_ns)
        return out, missing, frames

    def _sample_suit(self, suit: Suit, t: int, keep: bool = True) -> SuitSample:
        """Bone orientations at ``t`` (slerp) and accelerations at ``t - dt`` (kept from the previous solving tick
        when it was exactly ``dt`` earlier, :attr:`solve_dt`, else left out this frame), for the sensors whose
        buffers cover ``t``. ``keep``: this tick solves, its accelerations are the next solve's previous frame's.

        The look-ups follow :meth:`RingBuffer.sample`'s rules; the blending is done for all sensors at once.
        """
        a, b, alpha, mask = self._look_up_suit(suit, t)
        a[~mask, 0], b[~mask, 0] = 1.0, 1.0  # identity rows where nothing was measured (masked out below)
        q_i = quat_slerp(quat_normalize(a[:, 0:4]), quat_normalize(b[:, 0:4]), alpha)
        acc_s = a[:, 4:7] + alpha[:, None] * (b[:, 4:7] - a[:, 4:7])
        q_gi = quat_multiply(suit.calibration.q_ig[None], q_i)  # world <- sensor
        raw = quat_multiply(q_gi, _conj(self._q_ib[suit.id]))
        turn = yaw_quat(self.heading.offsets(suit.sensors))  # heading correction, about world up
        q_gi = quat_multiply(turn, q_gi)
        q = quat_multiply(turn, raw)
        acc = np.einsum("nij,nj->ni", matrix_from_quat(q_gi), acc_s) - np.array([0.0, GRAVITY, 0.0])
        prev = self._previous_acc.get(suit.id)
        if keep:
            self._previous_acc[suit.id] = (t, acc, mask)
        period = self.options.period_ns
        step = period * self.solve_every  # the solver's previous frame: the previous solve
        if prev is not None and abs(t - step - prev[0]) <= period // 4 and np.all(prev[2][mask]):
            return SuitSample(q, raw, q_i, prev[1], mask, True)
        return SuitSample(q, raw, q_i, acc, mask, False)  # no previous frame: the acceleration term sits this one out

    def _look_up_suit(self, suit: Suit, t: int) -> tuple[FloatArray, FloatArray, FloatArray, NDArray[np.bool_]]:
        """Every sensor of ``suit``'s two buffered samples around ``t`` (rows of ``a`` and ``b``, each
        (n_imu, width)), the blend weight (``alpha``, (n_imu,)) and whether it has them (``mask``); each look-up's
        outcome counted in :attr:`imu_status`."""
        assert self.ingest is not None
        n = len(suit.mounts)
        a = np.zeros((n, self._imu_width))
        b = np.zeros((n, self._imu_width))
        alpha = np.zeros(n)
        mask = np.zeros(n, dtype=bool)
        for i, sid in enumerate(suit.sensors):
            counts = self.imu_status.get(sid)
            if counts is None:  # not setdefault: its default would be built for every sensor on every tick
                counts = self.imu_status[sid] = dict.fromkeys((s.value for s in LookupStatus), 0)
            stream = self.ingest.streams.get(sid)
            if stream is None:
                counts[LookupStatus.EMPTY.value] += 1
                continue
            status = _bracket(stream.buffer, t + self.options.imu_offsets_ns.get(sid, 0), a[i], b[i], alpha, i)
            counts[status.value] += 1
            mask[i] = status is LookupStatus.OK
        return a, b, alpha, mask

    def _imu_only_people(self, seen: list[Person], suits: dict[str, SuitSample]) -> list[Person]:
        """Suits streaming without a person the cameras see: solved from their IMUs alone (the solver keeps their
        root on the ground, :mod:`mocapd.core.ground`). With no cameras at all, every streaming suit; with cameras,
        a suit already solved as a person (its wearer walked out of view, or the cameras lost them), so that its
        identity, warm start and contacts carry on; a suit the cameras never saw waits for its binding."""
        bound = {p.suit for p in seen if p.suit}
        nan = np.full((len(self.targets), 3), np.nan)
        return [
            Person(identity=f"suit:{sid}", track=-1, suit=sid, detections={}, keypoints=nan)
            for sid, sample in suits.items()
            if sid not in bound and sample.mask.any() and (not self.cameras or f"suit:{sid}" in self.solvers)
        ]

    def _solver_for(self, person: Person, with_suit: Suit | None, sample: SuitSample | None = None) -> PoseSolver:
        solver = self.solvers.get(person.identity)
        if solver is not None:
            return solver
        learned = self.fusion_mode == "learned"  # the skeleton fitted to the learned joints alone
        solver = PoseSolver(
            self.skeletons.get(person.track, self.skeleton),
            [] if learned else self.cameras,
            self.targets,
            with_suit.mounts if with_suit is not None and not learned else (),
            self.prior,
            self.cost,
            self.lm,
            backend="numpy" if self.backend == "numpy" else "compiled",
        )
        # Warm start: from this track's previous identity (a suit was just paired with it), else from the
        # triangulated keypoints.
        previous = self.solvers.pop(f"track:{person.track}", None)
        start = previous.theta if previous is not None else self._restart.pop(person.track, None)
        if start is None and person.track < 0 and with_suit is not None and sample is not None:
            # A suit no camera sees: its first pose from the sensors' orientations, not the rest pose (issue 46)
            start = initial_pose_from_imus(
                solver.skeleton, [m.bone for m in with_suit.mounts], sample.orientations, sample.mask
            )
        body = person.keypoints[: len(self._names)]  # hand keypoints, if any, come after the body's
        solver.reset(start if start is not None else initial_pose(solver.skeleton, body, self._names))
        self.solvers[person.identity] = solver
        return solver

    def _solve(
        self, person: Person, detections: list[Detections2D], suit_sample: SuitSample | None, t: int
    ) -> PersonPose:
        c0 = self._cpu()
        suit = self.suits.get(person.suit) if person.suit else None
        solver = self._solver_for(person, suit, suit_sample)
        n_cams, n_kp = len(self.cameras), len(self.targets)
        kp = np.zeros((n_cams, n_kp, 2))
        und = np.zeros((n_cams, n_kp, 2))
        conf = np.zeros((n_cams, n_kp))
        for cam, idx in person.detections.items():  # the body's columns (hand keypoints, if any, come after them)
            kp[cam] = detections[cam].keypoints[idx, :n_kp]
            und[cam] = self._undistorted(cam, detections[cam])[idx, :n_kp]
            conf[cam] = detections[cam].confidences[idx, :n_kp]
        np.clip(conf, 0.0, 1.0, out=conf)  # every view at once (the unseen views' zeros stay zeros)
        views = None if self.hands is None else {
            cam: (self._undistorted(cam, detections[cam])[idx], detections[cam].confidences[idx])
            for cam, idx in person.detections.items()}  # fmt: skip
        kp, und, conf = self._unflip(solver, kp, und, conf, len(person.detections), views, person.identity)
        if self.observation_hook is not None and len(person.detections) >= 2:
            conf = self.observation_hook(t, und, conf, person.identity)
        c1 = self._cpu()
        imu_kw: dict[str, Any] = {}
        n_imu = 0
        if suit is not None and suit_sample is not None:
            imu_kw = {
                "imu_orientations": suit_sample.orientations,
                "imu_accelerations": suit_sample.accelerations if suit_sample.has_acceleration else None,
                "imu_mask": suit_sample.mask,
            }
            n_imu = int(suit_sample.mask.sum())
        if suit is not None and self.frame % HEIGHT_EVERY == 0:
            self._record_height(suit.id, t, und, conf)
        if suit is not None and suit_sample is not None and len(person.detections) >= self.heading.options.min_views:
            self._seen_suits.add(suit.id)
            if (
                self.heading.options.enabled
                and t - self._heading_at.get(suit.id, t - HEADING_EVERY_NS) >= HEADING_EVERY_NS
            ):
                self._heading_at[suit.id] = t
                with self._count_lock:
                    self._observe_heading(suit, suit_sample, solver.skeleton, und, conf, t)
        if (
            suit is not None
            and suit_sample is not None
            and len(person.detections) >= 2
            and self.mounting.wants(suit.id)
            and t - self._mounting_at.get(suit.id, t - HEADING_EVERY_NS) >= HEADING_EVERY_NS
        ):
            self._mounting_at[suit.id] = t
            with self._count_lock:
                self._observe_mounting(suit, suit_sample, solver.skeleton, und, conf, t)
        obs = Observations(keypoints=kp, confidences=conf, dt=self.solve_dt, **imu_kw)
        if self.fusion is not None:
            obs = self._fused_observations(person, solver, suit, obs, kp, conf)
        result = solver.solve(obs, alternative=self._reference(person.identity, solver, t))
        c2 = self._cpu()
        with self._count_lock:
            self.counters["person_solves"] += 1
            self.counters["reference_kept"] += int(result.summary.kept_alternative)
            if not result.summary.converged:
                self.counters["not_converged"] += 1
        if person.track >= 0 and len(person.detections) >= 2:
            self._size_body(person, solver, und, conf)
        c3 = c4 = self._cpu()
        theta, hands = result.theta, None
        if self.hands is not None and views is not None:
            hands, theta = self.hands.solve(person.identity, solver.skeleton, theta, views)
            c4 = self._cpu()
        with self._count_lock:
            if self.hands is not None:
                self.hands.cpu.add(c4 - c3)
            for stage, ns in zip(PERSON_STAGES, (c1 - c0, c2 - c1, c3 - c2, c4 - c0), strict=True):
                self.person_cpu[stage].add(ns)
            if threading.current_thread() is not self._tick_thread:
                self._pool_cpu_ns += c4 - c0
        n_views = len(person.detections)
        used = conf[conf > 0]
        confidence = float(used.mean()) * min(1.0, n_views / 2.0) if used.size else 0.0
        joints = self._joints(solver, theta)
        return PersonPose(
            person.identity, person.track, person.suit, theta, joints, confidence, n_views, n_imu,
            result.summary.iterations, result.summary.converged,
            solver.skeleton if solver.skeleton is not self.skeleton else None, hands=hands,
        )  # fmt: skip

    def _reference(self, identity: str, solver: PoseSolver, t: int) -> FloatArray | None:
        """:attr:`reference_pose`'s pose for this solve, where it is on the skeleton the solver solves on."""
        ref = None if self.reference_pose is None else self.reference_pose(t, identity)
        if ref is None:
            return None
        theta, skeleton = ref
        sk = skeleton or self.skeleton
        same = abs(sk.root_height - solver.skeleton.root_height) < 1e-6 and np.allclose(
            sk.offsets, solver.skeleton.offsets, rtol=0.0, atol=1e-6
        )  # a recorded skeleton is stored in single precision (within 1e-7 m of the solver's)
        return theta if same else None

    def _unflip(
        self,
        solver: PoseSolver,
        kp: FloatArray,
        und: FloatArray,
        conf: FloatArray,
        views: int,
        hand_views: dict[int, tuple[FloatArray, FloatArray]] | None = None,
        identity: str | None = None,
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """The person's keypoints with each view's left/right labels as the views agree on them
        (:mod:`mocapd.core.lr_flips`); which of the mirror labellings is right comes from the previous solve.
        ``und``: the same keypoints undistorted. ``hand_views`` (camera -> every column's undistorted pixels and
        confidences, for the finger solve): a view whose wrists are swapped gets its two hands swapped too, in
        place. ``identity``: whose flip memo to search with (:class:`~mocapd.core.lr_flips.FlipMemo`)."""
        o = self.options.flips
        if not o.enabled or not self._lr_pairs or views < 2:
            return kp, und, conf
        reference = None
        if solver._has_solved:
            reference = solver.keypoint_positions(solver.theta)
        elif views < o.min_views_alone:
            return kp, und, conf
        memo = None
        if identity is not None:
            memo = self._flip_memos.get(identity)
            if memo is None or not memo.fits(len(self.cameras), len(self._lr_pairs)):
                memo = self._flip_memos[identity] = FlipMemo(len(self.cameras), len(self._lr_pairs))
        decision = choose_swaps(self._projections, und, conf, self._lr_pairs, reference, o, memo=memo)
        with self._count_lock:
            self.counters["lr_swaps"] += decision.count
            if memo is not None:
                self.counters["lr_pairs_searched"] += memo.searched
                self.counters["lr_pairs_reused"] += memo.reused
        if decision.swaps.any():
            kp, swapped_conf = apply_swaps(kp, conf, decision.swaps, self._lr_pairs)
            und, _ = apply_swaps(und, conf, decision.swaps, self._lr_pairs)
            conf = swapped_conf
            if hand_views is not None and self.hands is not None and self._wrist_pair is not None:
                for cam in np.flatnonzero(decision.swaps[:, self._wrist_pair]):
                    if int(cam) in hand_views:
                        hand_views[int(cam)] = self.hands.swapped(*hand_views[int(cam)])
        # A view that put both keypoints of a pair on one limb (issue 41's fast forearms) sits that pair out.
        collapsed = collapsed_pairs(self._projections, und, conf, self._lr_pairs, reference, o.collapse)
        if collapsed.any():
            with self._count_lock:
                self.counters["lr_collapsed"] += int(np.count_nonzero(collapsed))
            conf = drop_collapsed(conf, collapsed, self._lr_pairs)
        return kp, und, conf

    def _undistorted(self, camera: int, dets: Detections2D) -> FloatArray:
        """A camera's sampled keypoints undistorted (n_people, n_kp, 2): from the undistorted copies the timeline
        made as each frame arrived (interpolated like the pixels), else undistorted now."""
        if dets.undistorted is not None:
            return dets.undistorted
        return self._undistort(camera, dets.keypoints)

    def _undistort(self, camera: int, uv: FloatArray) -> FloatArray:
        """Pixels (..., 2) of ``camera`` undistorted; NaN stays NaN (a keypoint nobody saw)."""
        if np.isfinite(uv).all():  # the usual set (unseen keypoints are zeros with confidence 0): as it is
            return self.cameras[camera].undistort_points(uv)
        und = self.cameras[camera].undistort_points(np.nan_to_num(uv))
        return np.where(np.isfinite(uv), und, np.nan)

    def _fused_observations(
        self, person: Person, solver: PoseSolver, suit: Suit | None, obs: Observations, kp: FloatArray, conf: FloatArray
    ) -> Observations:
        """The person's learned stream for this tick (:class:`~mocapd.pipeline.fusion.FusionStage`) folded into
        their observations: added as E_J ("both", on the ticks it runs), or instead of everything ("learned")."""
        assert self.fusion is not None and self.mattes is not None
        source = self.mattes

        def mattes() -> list[NDArray[np.float32] | None]:
            if self._tick_mattes is None:
                self._tick_mattes = source.mattes(self._tick_t)
            return self._tick_mattes

        imu = None
        if suit is not None and obs.imu_orientations is not None:
            imu = (suit.mounts, replace(obs, keypoints=None, confidences=None))
        learned = self.fusion.step(person.identity, solver.skeleton, solver.theta, kp, conf, mattes, self.solve_dt, imu)
        if learned is not None:
            self.counters["learned_observations"] += 1
        if self.fusion_mode == "both":
            return obs if learned is None else replace(obs, joint_positions=learned.joints)
        joints = learned.joints if learned is not None else self.fusion.extrapolated(person.identity)
        return Observations(joint_positions=joints, dt=self.solve_dt)

    def _observe_heading(
        self, suit: Suit, sample: SuitSample, skeleton: Skeleton, und: FloatArray, conf: FloatArray, t: int
    ) -> None:
        """One heading observation of every measured sensor of ``suit`` from its wearer's keypoints (undistorted),
        triangulated from every camera that sees them (not the fused solve: it follows the very IMUs under test)."""
        points, ok = triangulate_projections(self._projections, und, conf)
        vectors = self._heading_vectors[suit.id].get(None if skeleton is self.skeleton else skeleton)
        idx = np.flatnonzero(sample.mask)
        yaw, evidence = observe_headings(sample.raw[idx], [vectors[i] for i in idx], points, ok)
        self.heading.observe(t, [suit.sensors[i] for i in idx], yaw, evidence)

    def _observe_mounting(
        self, suit: Suit, sample: SuitSample, skeleton: Skeleton, und: FloatArray, conf: FloatArray, t: int
    ) -> None:
        """One observation of ``suit``'s mountings from its wearer's keypoints, triangulated as for the heading, with
        the sensors' world orientations before the heading correction (``R_ig · R_i``), as the heading is estimated:
        the heading estimate started over from the new mountings (:meth:`_refine_mountings`) keeps the two apart."""
        points, ok = triangulate_projections(self._projections, und, conf)
        vectors = self._heading_vectors[suit.id].get(None if skeleton is self.skeleton else skeleton)
        idx = np.flatnonzero(sample.mask)
        q_sensor = quat_multiply(sample.raw[idx], self._q_ib[suit.id][idx])
        self.mounting.observe(suit.id, t, [suit.sensors[i] for i in idx], q_sensor, [vectors[i] for i in idx],
                              points, ok)  # fmt: skip

    def _refine_mountings(self, suit_id: str) -> None:
        """Fit ``suit_id``'s mountings from the cameras' first seconds and fuse the suit with them from the next
        tick (under :attr:`lock`, in the tick); every sensor's change is logged in one line. The calibration file is not
        rewritten: the next start refines again."""
        suit = self.suits[suit_id]
        fits = self.mounting.fit(suit_id, suit.calibration.q_ib)
        q_ib = {sid: fits[sid].q_ib if fits[sid].used else q for sid, q in suit.calibration.q_ib.items()}
        used = {sid: f for sid, f in fits.items() if f.used}
        # One line per suit, not one per sensor: the log limiter lets a few lines of one kind through a window, so
        # 13 lines at once would lose most of a suit's changes.
        bones = suit.calibration.bones
        turned = ", ".join(f"{sid} ({bones[sid]}) {f.change_deg:.1f} deg (misfit {f.misfit_deg:.1f}, {f.frames} frames)"
                           for sid, f in used.items())  # fmt: skip
        kept = ", ".join(f"{sid} ({bones[sid]}): {f.reason}" for sid, f in fits.items() if not f.used)
        log.warning("suit %s: %d of %d mountings refined from the cameras, turned %s; kept %s", suit_id, len(used),
                    len(fits), turned or "none", kept or "none")  # fmt: skip
        if used:
            self.suits[suit_id] = replace(suit, calibration=replace(suit.calibration, q_ib=q_ib))
            self._q_ib[suit_id] = np.array([q_ib[sid] for sid in suit.sensors])
            self.heading.restart(list(used))  # its window was measured with the old mountings

    def mounting_status(self) -> dict[str, dict[str, object]]:
        """``imu_mounting_from_cameras``: per suit ``gathering`` (frames so far) or ``done`` with each sensor's fit
        (``used``, ``change_deg``, ``misfit_deg``, ``frames``, ``rejected``, ``reason``); empty when off."""
        if self.lock.acquire(timeout=READ_WAIT_S):
            try:
                self._last_mounting = self.mounting.status()
            finally:
                self.lock.release()
        return self._last_mounting

    def _predict(self, pose: PersonPose, sample: SuitSample, t: int) -> PersonPose:
        """A suit wearer's solved pose carried to the suit's newest IMU instant (see module docstring)."""
        assert pose.suit is not None and self.ingest is not None
        suit = self.suits[pose.suit]
        solver = self.solvers.get(pose.identity)
        if solver is None:
            # This very solve re-sized the wearer's body (:meth:`_size_body` drops the solver; the next tick builds
            # it on the new skeleton): this frame publishes the solve itself, as delayed output would.
            self.counters["predictions_skipped"] += 1
            return pose
        hips = next((i for i, m in enumerate(suit.mounts) if m.bone == "Hips"), None)
        streams = [self.ingest.streams.get(sid) for sid in suit.sensors]
        state = SuitState(
            bones=np.array([m.bone_index for m in suit.mounts], dtype=np.intp),
            q_ib=self._q_ib[suit.id],
            q_wg=quat_multiply(yaw_quat(self.heading.offsets(suit.sensors)), suit.calibration.q_ig[None]),
            q_i=sample.sensor_quats, mask=sample.mask,
            buffers=[st.buffer if st is not None else None for st in streams],
            offsets_ns=np.array([self.options.imu_offsets_ns.get(sid, 0) for sid in suit.sensors], dtype=np.int64),
            hips=hips, hips_site=suit.mounts[hips].t_ib if hips is not None else np.zeros(3),
        )  # fmt: skip
        pred = self.predictor.predict(pose.identity, pose.theta, solver.skeleton.parents, t, state)
        if pred.t_ns == t:
            return replace(pose, t_pose_ns=t)  # nothing newer measured: the delayed pose, for its own instant
        return replace(pose, theta=pred.theta, joints=self._joints(solver, pred.theta), t_pose_ns=pred.t_ns,
                       solved=replace(pose, t_pose_ns=t))  # fmt: skip

    def _size_body(self, person: Person, solver: PoseSolver, und: FloatArray, conf: FloatArray) -> None:
        """Gather a track's keypoints, triangulated from every view that sees it (after the solve undid the views'
        left/right flips); give it its own skeleton from the first ``body_size_first_frames`` (a provisional size:
        the default 1.75 m skeleton misfits most people) and again, for good, from ``body_size_frames``. Its
        solver is rebuilt on the new skeleton at the next solve, warm-started from this one."""
        o = self.options
        n = o.body_size_frames
        if n <= 0 or person.track in self._sized or not self._sizable:
            return
        X, ok = triangulate_projections(self._projections, und, np.where(conf >= SIZE_MIN_CONFIDENCE, conf, 0.0))
        frames = self._sizing.setdefault(person.track, [])
        frames.append(np.where(ok[:, None], X, np.nan))
        first = min(o.body_size_first_frames, n) if o.body_size_first_frames > 0 else n
        final = len(frames) >= n
        if not (final or (len(frames) >= first and person.track not in self.skeletons)):
            return
        try:
            skeleton = estimate_skeleton(np.stack(frames), min_frames=(n if final else first) // 2, names=self._names)
        except InputError:
            self.counters["body_size_failed"] += 1
            if final:
                del frames[: n // 2]  # legs not seen well enough yet: keep trying with newer frames
            return
        self.skeletons[person.track] = skeleton
        self.counters["bodies_sized"] += 1
        if final:
            self._sized.add(person.track)
            del self._sizing[person.track]
        if self.solvers.pop(person.identity, None) is not None:
            # the next solve builds a solver on the new skeleton, from this pose (same θ layout)
            self._restart[person.track] = solver.theta.copy()

    def _record_height(self, suit: str, t: int, und: FloatArray, conf: FloatArray) -> None:
        """Hips height of a suit's wearer triangulated from the cameras alone: the camera side of the IMU offset
        estimate (the fused solve would not do — it follows the very IMU data whose timing is in question)."""
        if self._hips is None:
            return
        X, ok = triangulate_projections(self._projections, und[:, self._hips], conf[:, self._hips])
        if ok.all():
            keep = self._heights.setdefault(
                suit, deque(maxlen=round(HEIGHT_HISTORY_S * self.options.rate_hz / HEIGHT_EVERY))
            )
            keep.append((t, float(X[:, 1].mean())))

    def _joints(self, solver: PoseSolver, theta: FloatArray) -> FloatArray:
        """Global joint positions (21, 3): the solver's compiled forward kinematics when it has one."""
        static = solver._kernel_static
        if static is None:
            positions: FloatArray = solver.kin.forward(theta).positions
            return positions
        return np.asarray(
            _kernel.skeleton_points(theta, static.parents, static.offsets, self._bone_ids, self._zero_offsets)
        )

    def _forget_released(self, seen: set[str]) -> None:
        """Drop the solvers of identities the tracker no longer knows (released subjects)."""
        known = {f"track:{s.id}" for s in self.people.tracker.subjects}
        if self.people.binder is not None:
            known |= {f"suit:{s}" for s in self.people.binder.state.pairs}
        for identity in list(self.solvers):
            if identity not in known and identity not in seen:
                del self.solvers[identity]
        for identity in [k for k in self._flip_memos if k not in self.solvers]:
            del self._flip_memos[identity]
        for identity in [k for k in self.plausibility if k not in known and k not in seen]:
            del self.plausibility[identity]
        tracks = {s.id for s in self.people.tracker.subjects}
        for table in (self.skeletons, self._sizing, self._restart):
            for track in [k for k in table if k not in tracks]:
                del table[track]
        self._sized &= tracks
        self.predictor.forget(known | seen)

    def imu_alignment_inputs(self) -> list[ImuAlignmentInput]:
        """Copies of what :func:`estimate_imu_offsets` needs, per suit with a hips sensor and a solved wearer."""
        if not self.lock.acquire(timeout=READ_WAIT_S):
            return []  # a tick is solving: the next estimate (10 s later) has these records too
        try:
            return self._imu_alignment_inputs()
        finally:
            self.lock.release()

    def _imu_alignment_inputs(self) -> list[ImuAlignmentInput]:
        out = []
        for sid, suit in self.suits.items():
            heights = self._heights.get(sid)
            hips = [s for s, m in zip(suit.sensors, suit.mounts, strict=True) if m.bone == "Hips"]
            if not heights or not hips or self.ingest is None or hips[0] not in self.ingest.streams:
                continue
            buf = self.ingest.streams[hips[0]].buffer
            rows = buf.rows().copy()
            out.append(ImuAlignmentInput(
                suit=sid, sensor=hips[0], sensors=suit.sensors,
                cam_t_ns=np.array([h[0] for h in heights], dtype=np.int64), height_m=np.array([h[1] for h in heights]),
                imu_t_ns=buf.times().copy(), quat=rows[:, 0:4], acc=rows[:, 4:7], q_ig=suit.calibration.q_ig,
            ))  # fmt: skip
        return out

    def camera_frames(self) -> list[tuple[list[int], list[Detections2D]]]:
        """A copy of every camera's kept frames (for offset estimation off the event loop)."""
        return [tl.frames() for tl in self.timelines]

    # ------------------------------------------------------------------------------------------- status
    def status(self) -> dict[str, Any]:
        """JSON-able counters and latency percentiles, taken between two ticks. The event loop asks for it: it waits
        at most :data:`READ_WAIT_S` for a tick solving now, else it gets the previous document (the loop never
        waits on the tick thread for longer than that)."""
        if self.lock.acquire(timeout=READ_WAIT_S if self._last_status else -1):
            try:
                self._last_status = self._status()
            finally:
                self.lock.release()
        return self._last_status

    def _status(self) -> dict[str, Any]:
        return {
            "frame": self.frame,
            "published": self.published,
            "counters": dict(self.counters),
            "solve_every": self.solve_every,
            "body_heights_m": {str(k): round(v.height, 3) for k, v in self.skeletons.items()},
            "latency_ms": {k: v.summary() for k, v in self.latency.items()},
            "cpu_s": {k: round(v / 1e9, 3) for k, v in self.cpu_ns.items()},
            # What one person costs a tick, by stage (CPU): where the tick's budget goes.
            "person_cpu_ms": {k: v.summary() for k, v in self.person_cpu.items()},
            "cameras": [
                {"frames": tl.frames_received, "rejected": tl.rejected_out_of_order, "samples": dict(st)}
                for tl, st in zip(self.timelines, self.keypoint_status, strict=True)
            ],
            "imu_samples": {k: dict(v) for k, v in self.imu_status.items()},
            "people": self.people.status(),
            "solvers": sorted(self.solvers),
            "suggested_camera_offsets_ms": self.suggested_offsets,
            "output": self.options.prediction.output,
            "heading": self.heading_status(),
            "latency": self.latency_status(),
            "plausibility": {k: m.status() for k, m in sorted(self.plausibility.items())},
            "fusion": {"mode": self.fusion_mode, **(self.fusion.status() if self.fusion is not None else {})},
        }

    def latency_status(self) -> dict[str, Any]:
        """The delay behind wall time: fixed, or (auto) following the detector with what it is made of."""
        if self.auto_latency is not None:
            return self.auto_latency.status()
        return {"mode": "fixed", "latency_ms": round(self.latency_ns / 1e6, 1)}

    def heading_status(self) -> dict[str, dict[str, dict[str, Any]]]:
        """Per suit, per sensor: its bone, whether the cameras can observe its heading with this keypoint set,
        and the estimator's state (:meth:`HeadingEstimator.status`: applied offset, window estimate, samples;
        state "unobservable" for a sensor whose bone has no keypoint pair, "unobserved" before any observation)."""
        if self.lock.acquire(timeout=READ_WAIT_S):
            try:
                self._last_heading = self.heading.status()
            finally:
                self.lock.release()
        est = self._last_heading
        out: dict[str, dict[str, dict[str, Any]]] = {}
        for sid, suit in self.suits.items():
            vectors = self._heading_vectors[sid].default
            never = {"offset_deg": 0.0, "estimate_deg": None, "samples": 0, "inliers": 0, "rejected": 0}
            out[sid] = {
                sensor: {"bone": m.bone, "observable": v.observable,
                         **est.get(sensor, {**never, "state": "unobserved"}),
                         **({} if v.observable else {"state": "unobservable"})}
                for sensor, m, v in zip(suit.sensors, suit.mounts, vectors, strict=True)
            }  # fmt: skip
        return out


def _vectors_per_skeleton(
    skeleton: Skeleton, targets: TrackTargets, bones: tuple[str, ...]
) -> PerSkeleton[tuple[BoneVectors, ...]]:
    return PerSkeleton(bone_vectors(skeleton, targets, bones), lambda sk: bone_vectors(sk, targets, bones))


def _bracket(buf: RingBuffer, t: int, a: FloatArray, b: FloatArray, alpha: FloatArray, i: int) -> LookupStatus:
    """The two samples around ``t`` (into ``a`` and ``b``) and the blend weight (into ``alpha[i]``), with the
    outcomes of :meth:`RingBuffer.sample` (OK, EMPTY, BEFORE, AFTER, GAP)."""
    times = buf.times()
    if times.size == 0:
        return LookupStatus.EMPTY
    if t < times[0]:
        return LookupStatus.BEFORE
    if t > times[-1]:
        return LookupStatus.AFTER
    k = int(np.searchsorted(times, t, side="right")) - 1
    rows = buf.rows()
    if times[k] == t:
        a[:] = b[:] = rows[k]
        alpha[i] = 0.0
        return LookupStatus.OK
    t0, t1 = int(times[k]), int(times[k + 1])
    if t1 - t0 > buf.max_gap_ns:
        return LookupStatus.GAP
    a[:] = rows[k]
    b[:] = rows[k + 1]
    alpha[i] = (t - t0) / (t1 - t0)
    return LookupStatus.OK


def _conj(q: FloatArray) -> FloatArray:
    out: FloatArray = q * np.array([1.0, -1.0, -1.0, -1.0])
    return out


@dataclass(frozen=True)
class ImuAlignmentInput:
    """One suit's records for the IMU ↔ camera offset estimate (copied off the tick loop)."""

    suit: str
    sensor: str  # the hips sensor whose acceleration is used
    sensors: tuple[str, ...]  # every sensor of the suit (one clock path: the estimate applies to all)
    cam_t_ns: IntArray  # (n,) solve times
    height_m: FloatArray  # (n,) solved hips height of the wearer
    imu_t_ns: IntArray  # (m,) buffered sample times
    quat: FloatArray  # (m, 4) sensor orientation in the suit's global frame
    acc: FloatArray  # (m, 3) specific force, sensor frame
    q_ig: FloatArray  # (4,) world <- suit global frame


def estimate_imu_offsets(inputs: list[ImuAlignmentInput], current_ns: dict[str, int]) -> dict[str, dict[str, Any]]:
    """:func:`imu_offset_steps` at once."""
    return drain(imu_offset_steps(inputs, current_ns))


def imu_offset_steps(inputs: list[ImuAlignmentInput], current_ns: dict[str, int]) -> Steps[dict[str, dict[str, Any]]]:
    """Per suit: the offset (ms, ``[daemon.offsets.imus]`` convention, for every sensor of the suit) that aligns
    its hips sensor's vertical motion with the wearer's hips height as solved from the cameras, with the
    correlation peak as quality (see :func:`~mocapd.pipeline.time_alignment.estimate_imu_lag`). Suits without
    enough moving data are left out."""
    out: dict[str, dict[str, Any]] = {}
    for x in inputs:
        q_world = quat_multiply(np.asarray(x.q_ig)[None], quat_normalize(x.quat))
        vertical = np.einsum("nij,nj->ni", matrix_from_quat(q_world), x.acc)[:, 1] - GRAVITY
        yield
        est = yield from estimate_imu_lag_steps(x.cam_t_ns, x.height_m, x.imu_t_ns, vertical)
        if est is not None:
            # Buffered times are raw (offsets are applied at look-up), so the lag is the whole offset.
            out[x.suit] = {
                "offset_ms": round(est.lag_ns / 1e6, 1), "quality": round(est.quality, 3),
                "configured_ms": round(current_ns.get(x.sensor, 0) / 1e6, 1), "sensor": x.sensor,
                "sensors": list(x.sensors),
            }  # fmt: skip
    return out


def estimate_camera_offsets(
    names: list[str], frames: list[tuple[list[int], list[Detections2D]]], current_ns: tuple[int, ...]
) -> dict[str, dict[str, float]]:
    """:func:`camera_offset_steps` at once."""
    return drain(camera_offset_steps(names, frames, current_ns))


def camera_offset_steps(
    names: list[str], frames: list[tuple[list[int], list[Detections2D]]], current_ns: tuple[int, ...]
) -> Steps[dict[str, dict[str, float]]]:
    """Per camera (the first is the reference): the offset that would align its keypoint speeds with the first
    camera's, in ms, in the convention of ``[daemon.offsets]`` (added to what is configured), with the
    correlation peak as quality. Cameras without enough moving data are left out."""
    if len(frames) < 2:  # one camera, or none (a rig of IMUs alone): nothing to align
        return {}
    ref_t, ref_v = yield from keypoint_speed_steps(np.asarray(frames[0][0], dtype=np.int64), frames[0][1])
    out: dict[str, dict[str, float]] = {}
    offsets = current_ns[1:] or (0,) * (len(names) - 1)
    for name, (times, dets), offset in zip(names[1:], frames[1:], offsets, strict=True):
        t, v = yield from keypoint_speed_steps(np.asarray(times, dtype=np.int64), dets)
        est = yield from estimate_lag_steps(ref_t, ref_v, t, v)
        if est is not None:
            out[name] = {"offset_ms": round((offset + est.lag_ns) / 1e6, 1), "quality": round(est.quality, 3)}
    return out
