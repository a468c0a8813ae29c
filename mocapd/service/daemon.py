"""The daemon: IMU inputs, keypoint sources, the fixed-latency scheduler and the status server under one
``asyncio.TaskGroup``, each long-running task supervised (failure logged, counted, restarted with back-off).

Life cycle: the solver kernel is loaded (off the event loop), the HTTP server listens, the pose sinks start, the
inputs start and every device is opened — every camera and every IMU port must open within
``daemon.open_timeout_s``, or the run stops there with :class:`StartupError` naming the device and why (a device
that fails *later* is reopened with back-off while the others keep running) — then the scheduler starts and
``READY=1`` goes to systemd. SIGINT/SIGTERM set the stop event: ``STOPPING=1``, serial devices close their ports,
tasks are cancelled (capture threads stop and close their cameras), pose sinks are flushed and closed, and
:meth:`Daemon.run` returns (within ``shutdown_timeout_s``). With ``WatchdogSec`` set, ``WATCHDOG=1`` is sent from
the tick loop, so a stuck solver stops the pings and systemd restarts the service.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import os
import socket
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, TypeVar, runtime_checkable

import cv2
import numpy as np

from mocapd.core._undistort_kernel import warm_up as warm_up_undistortion
from mocapd.core.assignment import warm_up as warm_up_assignment
from mocapd.core.camera import Camera
from mocapd.core.heading import yaw_quat
from mocapd.core.heading_reset import ResetHistory, enu_turn, reset_yaws
from mocapd.core.keypoints import TrackTargets
from mocapd.core.lr_flips import warm_up as warm_up_flip_search
from mocapd.core.people import PeopleTracker
from mocapd.core.plausibility import first_events
from mocapd.core.prior import PcaPrior
from mocapd.core.rate_limit import TokenBucket
from mocapd.core.rotations import quat_conjugate, quat_multiply, quat_normalize
from mocapd.core.skeleton import Skeleton
from mocapd.core.solver import Observations, PoseSolver
from mocapd.core.sorting import Detections2D, DetectionSorter
from mocapd.core.suit_binding import SuitBinder
from mocapd.core.taps import TapOptions
from mocapd.core.tracking import SubjectTracker
from mocapd.core.yaw_drift import StillDrift
from mocapd.errors import ConfigError, DeviceError, InputError, RateLimitError
from mocapd.io import lifecycle
from mocapd.io.device_state import OpenState
from mocapd.io.gc_watch import GcWatch
from mocapd.io.machine_cpu import MachineCpuReader
from mocapd.io.os_threads import worker_thread_setup
from mocapd.io.sd_notify import SdNotifier
from mocapd.pipeline.camera_watch import CameraChange, LiveCameraWatch, turn_deg
from mocapd.pipeline.detector_pool import landmark_fronts
from mocapd.pipeline.fusion import FusionModels, FusionStage
from mocapd.pipeline.governor import Governor, ladder
from mocapd.pipeline.hands import HandStage
from mocapd.pipeline.keypoint_source import KeypointSource
from mocapd.pipeline.landmark_auto import LandmarkFront, has_auto, shed_landmarks, status_field
from mocapd.pipeline.mattes import MatteSource, RingMattes
from mocapd.pipeline.optical_flow import warm_up as warm_up_optical_flow
from mocapd.pipeline.scheduler import (
    READ_WAIT_S,
    FixedLatencyScheduler,
    PoseFrame,
    Suit,
    TickPlan,
    camera_offset_steps,
    imu_offset_steps,
)
from mocapd.pipeline.time_alignment import Steps, estimate_imu_lag, estimate_lag
from mocapd.service.calibration_save import save_cameras
from mocapd.service.config import Config
from mocapd.service.config.imu import ImuConfig
from mocapd.service.http_status import StatusServer
from mocapd.service.imu_inputs import ImuInputs
from mocapd.service.live_calibration import LiveCalibrations, install_suit
from mocapd.service.metrics import latency_snapshot, render_metrics
from mocapd.service.supervisor import Supervisor

log = logging.getLogger(__name__)
T = TypeVar("T")


class PoseSink(Protocol):
    """Where published frames go: files, WebSocket / UDP streams, session recorders.

    ``start`` runs once on the event loop before the first tick (bind sockets, open files); ``publish`` is called
    from the tick loop and must not block (hand the frame to a bounded queue, or write to a buffer); ``aclose``
    flushes and releases, once, at shutdown.
    """

    async def start(self) -> None: ...

    def publish(self, frame: PoseFrame) -> None: ...

    async def aclose(self) -> None: ...


@runtime_checkable
class ReportingSink(Protocol):
    """A pose sink with counters for /status (under ``sinks.<name>``), e.g. the UDP streams."""

    name: str

    def status(self) -> dict[str, Any]: ...


@dataclass
class Rig:
    """What the daemon captures with: cameras with their keypoint sources, the people's model, the suits."""

    cameras: list[Camera]
    sources: list[KeypointSource]
    skeleton: Skeleton
    targets: TrackTargets
    prior: PcaPrior | None = None
    suits: list[Suit] = field(default_factory=list)
    keypoint_names: tuple[str, ...] = ()
    """The detections' columns when they go beyond the targets' (both hands' keypoints after the body's, ``[detector]
    hands``); empty: the targets' names."""

    @property
    def columns(self) -> tuple[str, ...]:
        """The names of the detections' keypoint columns (the targets' first)."""
        return self.keypoint_names or self.targets.names


def build_fusion(config: Config, rig: Rig, mattes: MatteSource | None) -> FusionStage | None:
    """The learned fusion's stage for ``[fusion]`` (None in mode "solver").

    Raises
    ------
    ConfigError
        A learned mode without camera frames for the mattes, or an output rate other than the 60 Hz the networks'
        windows were trained at.
    ModelError
        The networks cannot be loaded.
    """
    f = config.fusion
    if f.mode == "solver":
        return None
    if mattes is None:
        raise ConfigError(
            f"fusion.mode = {f.mode!r} needs camera frames for the foreground mattes (video, aravis, uvc or images "
            "cameras, or the synthetic rig); this rig has none"
        )
    if config.daemon.output_rate_hz != 60.0:
        raise ConfigError(
            f"fusion.mode = {f.mode!r} needs daemon.output_rate_hz = 60 (the networks' windows are 60 Hz frames); "
            f"got {config.daemon.output_rate_hz:g}"
        )
    models = FusionModels(None if f.model == "default" else Path(f.model), threads=f.threads)
    return FusionStage(models, rig.cameras, rig.targets, rig.prior, config.solver.cost)


async def run_in_steps(steps: Steps[T]) -> T:
    """Run ``steps`` (work that yields after each bounded piece) on the event loop, one step per loop iteration,
    and return its result: a timer that falls due (the next tick) runs after the current step, never after the
    whole work."""
    while True:
        try:
            next(steps)
        except StopIteration as done:
            result: T = done.value
            return result
        await asyncio.sleep(0)


def in_daemon_thread(fn: Callable[..., T], *args: Any) -> asyncio.Future[T]:
    """``fn(*args)`` in a daemon thread: work a stop may abandon (the solver kernel's compile, the rig's model
    loads).

    Not the loop's default executor: its threads are joined when the process exits, so a second of estimation
    (or a minute of compiling) still running at Ctrl-C would delay the stop by that long. A daemon thread is
    abandoned instead, and its result with it: cancel the future to say nobody waits.
    """
    loop = asyncio.get_running_loop()
    future: asyncio.Future[T] = loop.create_future()

    def deliver(result: T | None, exc: BaseException | None) -> None:
        if future.done():  # cancelled: the waiting task was stopped
            return
        if exc is not None:
            future.set_exception(exc)
        else:
            future.set_result(result)  # type: ignore[arg-type]

    def work() -> None:
        result: T | None = None
        error: BaseException | None = None
        try:
            result = fn(*args)
        except Exception as exc:  # handed to the awaiting task, which reports it (the supervisor counts it)
            error = exc
        if not loop.is_closed():
            with contextlib.suppress(RuntimeError):  # the loop closed between the check and the call: nobody waits
                loop.call_soon_threadsafe(deliver, result, error)

    threading.Thread(target=work, name="mocapd-estimate", daemon=True).start()
    return future


TAP_BONES = ("Spine3", "Spine2", "Spine1", "Spine", "Hips")
"""Where the tap gesture is watched, the first present: upper chest, chest, waist, hips (the SlimeVR server's order)."""
CALM_BONES = ("Hips", "Spine", "Spine1", "Spine2", "Spine3", "LeftUpperLeg", "RightUpperLeg", "LeftLowerLeg",
              "RightLowerLeg", "LeftFoot", "RightFoot")  # fmt: skip
"""Sensors that must stay calm for taps to count (a heel strike jolts the chest too)."""


class StartupError(DeviceError):
    """A device did not open when the daemon started (the message names each one and why)."""


class Daemon:
    """The running service. ``await run()``; ``request_stop()`` (or a signal) ends it.

    Parameters
    ----------
    config : Config
    rig : Rig
    imu : ImuConfig, optional
        The IMU inputs (default ``config.imu``; a synthetic rig adds its simulated devices' ports).
    sinks : list of PoseSink
    clock : callable
    notifier : SdNotifier
    status_line : callable, optional
        Called with a one-line summary every second.
    mattes : MatteSource, optional
        The cameras' foreground mattes for the learned fusion (``[fusion] mode`` other than "solver" needs them);
        a :class:`~mocapd.pipeline.mattes.RingMattes` is polled by the daemon.
    """

    def __init__(
        self,
        config: Config,
        rig: Rig,
        *,
        imu: ImuConfig | None = None,
        sinks: list[PoseSink] | None = None,
        clock: Callable[[], int] = time.monotonic_ns,
        notifier: SdNotifier | None = None,
        status_line: Callable[[str], None] | None = None,
        mattes: MatteSource | None = None,
    ) -> None:
        self.config = config
        self.rig = rig
        self.sinks = list(sinks or [])
        #: observers of every detected camera frame as it arrives (camera, capture_ns, detections, arrival_ns),
        #: e.g. the session recorder; called on the event loop, so they must not block
        self.detection_taps: list[Callable[[int, int, Detections2D, int], None]] = []
        self.clock = clock
        self.notifier = notifier if notifier is not None else SdNotifier()
        self.status_line = status_line
        d = config.daemon
        self.imu = ImuInputs(imu if imu is not None else config.imu)
        self.imu.use_calibrations([s.calibration for s in rig.suits])  # SlimeVR trackers' own headings
        self.imu.keep_sensors(sid for s in rig.suits for sid in s.sensors)  # never evicted by unknown sensor ids
        #: heading resets (without cameras nothing else corrects a drifting heading) and each sensor's drift
        self.resets = ResetHistory(since_ns=clock())
        self.reset_log: list[dict[str, Any]] = []
        self.still_drift = StillDrift()
        self._reset_timers: dict[str | None, asyncio.TimerHandle] = {}  # per suit: a reset asked, still waiting
        #: every source's heading resets together (a flood from any door would spin the suit's heading around)
        self.reset_limit = TokenBucket(d.heading_resets_per_s, d.heading_reset_burst, clock())
        self._implausible_said: set[tuple[str, str]] = set()  # (person, check) already warned about
        self._watch_gestures(config, rig.suits)
        #: more sections of /status (name -> provider), e.g. the camera demo's fake cameras
        self.status_extras: dict[str, Callable[[], Any]] = {}
        #: more fields of the status line, e.g. the synthetic rig's keypoint error
        self.status_line_extras: list[Callable[[], str]] = []
        tracker = PeopleTracker(
            SubjectTracker(
                # every column's name: the flip-aware matching pairs left and right (the hands' too, when they come)
                DetectionSorter(rig.cameras, config.tracking.sorting.options(), keypoint_names=rig.columns),
                config.tracking.enrolment.options(),
            ),
            SuitBinder(rig.skeleton, config.tracking.binding.options(), names=rig.targets.names) if rig.suits else None,
        )
        self.mattes = mattes
        fusion = build_fusion(config, rig, mattes)
        self.scheduler = FixedLatencyScheduler(
            rig.cameras,
            rig.skeleton,
            rig.targets,
            tracker,
            prior=rig.prior,
            ingest=self.imu.ingest,
            suits=rig.suits,
            options=d.scheduler_options([c.name for c in rig.cameras]),
            cost=config.fusion.options().cost(config.solver.cost),
            lm=config.solver.lm.options(),
            backend=config.solver.backend,
            fusion=fusion,
            fusion_mode=config.fusion.mode,
            mattes=mattes,
            # Fingers when the detector delivers both hands' keypoints (``[detector] hands``); else nothing of it runs.
            hands=HandStage.from_names(rig.columns, np.stack([c.projection_matrix for c in rig.cameras]))
            if rig.cameras
            else None,
        )
        watch = config.calibration.watch
        #: the bumped-camera watch (None: ``[calibration.watch] enabled = false`` or fewer than three cameras)
        self.camera_watch = (LiveCameraWatch(rig.cameras, watch.options())
                             if watch.enabled and len(rig.cameras) >= 3 else None)  # fmt: skip
        if self.camera_watch is not None:
            self.scheduler.observation_hook = self.camera_watch.observe
            self.scheduler.camera_listeners.append(self.camera_watch.camera_replaced)
        #: the cameras replaced while running, newest last (the last 10: ``/status`` ``camera_changes``)
        self.camera_changes: list[CameraChange] = []
        #: told of each camera replaced (the session recorder, the viewer's camera panels); on the event loop
        self.camera_taps: list[Callable[[CameraChange], None]] = []
        self._refusals_said: set[str] = set()  # cameras whose refused re-estimate was said since they were named
        # The tick solves on its own thread (the loop only samples and publishes), its people on the solve pool.
        self._tick_executor = ThreadPoolExecutor(1, "mocapd-tick", initializer=worker_thread_setup,
                                                 initargs=("mocapd-tick",))  # fmt: skip
        threads = self.solve_threads = d.solve_thread_count(os.cpu_count())
        self._solve_pool = (ThreadPoolExecutor(threads, "mocapd-solve", initializer=worker_thread_setup,
                                               initargs=("mocapd-solve",)) if threads > 1 else None)  # fmt: skip
        self.scheduler.pool = self._solve_pool
        #: sheds work when the tick does not fit its period (None: ``[daemon] governor = false``)
        sources = self.rig.sources
        steps = ladder(has_auto(self._landmark_fronts()), any(hasattr(s, "tracking_rate_scale") for s in sources),
                       any(hasattr(getattr(s, "group", None), "duty") for s in sources))  # fmt: skip
        pin = None if d.governor_pin_step < 0 else d.governor_pin_step
        try:
            self.governor = (Governor(self.scheduler.options.period_ns, start_ns=clock(), steps=steps, pin=pin)
                             if d.governor else None)  # fmt: skip
        except ValueError as exc:  # a pinned step this rig's ladder does not have
            raise ConfigError(f"daemon.governor_pin_step: {exc}") from None
        if self.governor is not None and self.governor.pinned:
            self._apply_governor()
        self._machine_cpu = MachineCpuReader()  # the machine's busy CPU for the governor (None where unreadable)
        self.supervisor = Supervisor(d.restart_min_s, d.restart_max_s)
        #: what ``POST <path>`` does on the status server (and the WebSocket's requests of the same name)
        self.actions: dict[str, Callable[[dict[str, str], str], Any]] = {
            "/heading/reset": lambda q, who: self.reset_heading(q.get("suit") or None, who, remote=True),
            "/imu/calibrate": lambda q, who: self.calibrate_imu(q.get("suit") or None, q.get("pose") or None, who,
                                                                cancel=q.get("cancel") in ("1", "true")),
            "/calibration/save": lambda q, who: self.save_calibration(who),
        }  # fmt: skip
        #: the guided IMU calibrations asked of this daemon (docs/imu.md "Calibrating a suit live")
        self.live_calibration = LiveCalibrations(
            Path(self.imu.config.calibration_dir), rig.skeleton,
            lambda suit: install_suit(self.scheduler, self.rig.suits, suit),
        )  # fmt: skip
        self.http = self.status_server()
        self.plan: TickPlan | None = None
        self.latest: PoseFrame | None = None
        self.started_ns = clock()
        self.ready = asyncio.Event()
        self._stop = asyncio.Event()
        self._rate_window: deque[int] = deque()  # tick times of the last second, for the achieved rate
        #: with fingers on: each published frame of the last second, its time and who had which hand solved
        self._hand_window: deque[tuple[int, dict[str, tuple[bool, bool]]]] = deque()
        self.stopping = False
        self._startup_error: StartupError | None = None
        #: run() installs SIGINT/SIGTERM/SIGHUP handlers (False: the caller owns signals, see lifecycle.stop_event)
        self.handle_signals = True
        #: the garbage collections while it runs (counts and pauses per generation; ``gc`` in /status)
        self.gc_watch = GcWatch()

    # ------------------------------------------------------------------------------------------ control
    def status_server(self, sock: socket.socket | None = None) -> StatusServer:
        """The status server of this daemon: on ``[daemon] http_host:http_port``, or on ``sock``, a listening socket
        a parent bound for it (the camera demo's daemon runs in a private network namespace). Either way with the
        same actions and the same ``[web]`` Host and Origin rules: one place builds it, so a server on an inherited
        socket cannot miss a protection the other gets."""
        d, web = self.config.daemon, self.config.web
        return StatusServer(self.status, render_metrics, d.http_host, d.http_port, sock=sock, actions=self.actions,
                            allowed_hosts=web.allowed_hosts, allowed_origins=web.allowed_origins)  # fmt: skip

    def request_stop(self) -> None:
        """Begin a clean shutdown (signal handlers call this)."""
        self._stop.set()

    # ------------------------------------------------------------------------------------------ heading reset
    def reset_heading(
        self, suit: str | None = None, source: str = "request", *, remote: bool = False
    ) -> dict[str, Any]:
        """Heading reset (:mod:`mocapd.core.heading_reset`): the wearer stands straight facing forward (the way they
        faced at calibration); every sensor of ``suit`` (default: every suit) is turned about the vertical so its
        bone faces forward, from its newest sample on, the buffered samples included. Returns what was done per
        suit and sensor (the correction in degrees; sensors without a sample in the last second are left alone).

        ``source`` says who asked, in the log and in /status (``heading_resets``); a reset asked over the network
        (``remote``: HTTP, the WebSocket) is logged as a warning, so it shows without ``--verbose``. Every source
        shares one rate limit (``[daemon] heading_reset_burst``, ``heading_resets_per_s``).

        Raises
        ------
        InputError
            ``suit`` is not a suit of this rig, or the rig has none.
        RateLimitError
            More resets than the rate limit allows (nothing is turned).
        """
        suits = [s for s in self.rig.suits if suit in (None, s.id)]
        if not suits:
            have = ", ".join(s.id for s in self.rig.suits) or "none: calibrate one with `mocapd calibrate imu`"
            raise InputError(f"no suit {suit!r} to reset (suits: {have})" if suit else f"no suit to reset ({have})")
        now = self.clock()
        wait = self.reset_limit.take(now)
        if wait > 0:
            limits = self.config.daemon
            raise RateLimitError(
                f"heading reset refused: more than {limits.heading_reset_burst} at once or "
                f"{limits.heading_resets_per_s:g} a second ([daemon] heading_reset_burst, heading_resets_per_s); the "
                f"next in {wait:.1f} s",
                wait,
            )
        done: dict[str, Any] = {}
        for s in suits:
            with self.scheduler.lock:  # the tick thread updates the estimates
                offsets = self.scheduler.heading.offsets(s.sensors)
            live, q_gb, missing = [], [], []
            for i, sid in enumerate(s.sensors):
                stream = self.imu.ingest.streams.get(sid)
                latest = stream.buffer.latest() if stream is not None else None
                if latest is None or now - latest[0] > 1_000_000_000 or not np.all(np.isfinite(latest[1][0:4])):
                    missing.append(sid)
                    continue
                q_gi = quat_multiply(s.calibration.q_ig, quat_normalize(latest[1][0:4]))
                q_gb.append(
                    quat_multiply(yaw_quat(offsets[i]), quat_multiply(q_gi, quat_conjugate(s.calibration.q_ib[sid])))
                )
                live.append(sid)
            yaws = reset_yaws(np.array(q_gb)) if q_gb else np.zeros(0)
            self.imu.turn_headings(
                {sid: enu_turn(s.calibration.q_ig, float(y)) for sid, y in zip(live, yaws, strict=True)}
            )
            corrections = {sid: round(float(np.degrees(y)), 2) for sid, y in zip(live, yaws, strict=True)}
            self.resets.record(now, corrections)
            done[s.id] = {"corrections_deg": corrections, "no_recent_sample": missing}
        entry = {"t_ns": now, "source": source, "suits": done}
        self.reset_log = [*self.reset_log[-9:], entry]
        for sid, d in done.items():
            worst = max((abs(v) for v in d["corrections_deg"].values()), default=0.0)
            log.log(logging.WARNING if remote else logging.INFO,
                     "heading reset (%s): suit %s, %d sensor(s) turned, at most %.1f deg%s", source, sid,
                     len(d["corrections_deg"]), worst, f"; no recent sample: {d['no_recent_sample']}"
                     if d["no_recent_sample"] else "")  # fmt: skip
        return entry

    def calibrate_imu(self, suit: str | None, pose: str | None, source: str, *, cancel: bool = False) -> dict[str, Any]:
        """Start the guided calibration of ``suit`` (:mod:`mocapd.service.live_calibration`), or stop it; returns its
        state (the first thing the wearer is asked to do). Raises InputError (naming the cause) when it cannot."""
        return self.live_calibration.start(self.rig.suits, suit, pose, source, self.clock(), cancel=cancel)

    def request_reset(self, suit: str | None, source: str, delay_s: float) -> None:
        """A heading reset of ``suit`` in ``delay_s`` (a gesture: the hand goes back down first); a later request for
        the same suit replaces one still waiting."""
        waiting = self._reset_timers.pop(suit, None)
        if waiting is not None:
            waiting.cancel()
        loop = asyncio.get_running_loop()

        def fire() -> None:
            self._reset_timers.pop(suit, None)
            try:
                self.reset_heading(suit, source)
            except InputError:  # the suit's sensors are gone: nothing to reset
                pass
            except RateLimitError as exc:  # a tracker's gestures share the limit: said, and nothing turned
                log.warning("%s: %s", source, exc)

        self._reset_timers[suit] = loop.call_later(delay_s, fire)

    def _watch_gestures(self, config: Config, suits: list[Suit]) -> None:
        """Heading resets asked on SlimeVR trackers: the firmware's reset button and double tap (any tracker of a
        suit), and the SlimeVR server's tap gesture (taps on the chest or hips tracker, counted here)."""
        sv = config.imu.slimevr
        owner = {sid: s.id for s in suits for sid in s.sensors}
        if self.imu.slimevr is not None:

            def gesture(what: str, sensors: list[str]) -> None:
                for suit in sorted({owner[sid] for sid in sensors if sid in owner}):
                    self.request_reset(suit, what, sv.reset_delay_s)

            self.imu.slimevr.on_gesture = gesture
        if not sv.enabled or sv.reset_taps <= 0:
            return
        for s in suits:
            bones = {s.calibration.bones[sid]: sid for sid in s.sensors if "/" in sid}  # SlimeVR sensors
            watched = next((bones[b] for b in TAP_BONES if b in bones), None)
            if watched is None:
                continue
            body = [sid for b, sid in bones.items() if b in CALM_BONES]

            def taps(sensor: str, suit: str = s.id) -> None:
                self.request_reset(suit, f"{sv.reset_taps} taps on {sensor}", sv.reset_delay_s)

            self.imu.watch_taps(watched, body, TapOptions(taps=sv.reset_taps), taps)

    async def run(self) -> int:
        """Serve until stopped; returns the process exit status."""
        loop = asyncio.get_running_loop()
        # How long a thread that wants the interpreter lock waits for the one holding it: the tick thread gives it
        # up in every compiled kernel and would wait this long to get it back while the capture, tracking and
        # detector threads run Python (CPython's default 5 ms is a third of a 60 Hz period).
        sys.setswitchinterval(self.config.daemon.switch_interval_ms / 1000.0)
        # OpenCV's worker pool, process-wide: none by default (the capture threads are the parallelism); its idle
        # workers spin (sched_yield) after each parallel call, CPU a budget or a game on the laptop pays for.
        cv2.setNumThreads(self.config.daemon.opencv_threads)
        self.gc_watch.install()
        signals = lifecycle.STOP_SIGNALS if self.handle_signals else ()
        for sig in signals:
            # add_signal_handler raises RuntimeError off the main thread: then signals are the caller's job.
            with contextlib.suppress(RuntimeError):
                loop.add_signal_handler(sig, self.request_stop)
        lifecycle.enter_phase("loading the solver kernel")
        # A daemon thread, raced against the stop: a first compile takes up to a minute, and a stop meanwhile
        # abandons it (nothing else is started yet) rather than waiting for it.
        warm_up = in_daemon_thread(self._warm_up)
        stop: asyncio.Future[Any] = asyncio.ensure_future(self._stop.wait())
        await asyncio.wait({warm_up, stop}, return_when=asyncio.FIRST_COMPLETED)
        stop.cancel()
        started: list[PoseSink] = []
        try:
            if not warm_up.done():
                warm_up.cancel()
                return 0
            warm_up.result()
            await self.http.start()
            await self.imu.bind()
            for sink in self.sinks:
                await sink.start()  # a stream that cannot listen, a session that exists: the run stops here, cleanly
                started.append(sink)
            self.notifier.notify("STATUS=starting inputs")
            async with asyncio.timeout(None) as deadline:
                await self._serve(deadline)
        except TimeoutError:
            # A task ignored its cancellation for shutdown_timeout_s: leave it behind rather than hang the stop.
            pending = [t.get_name() for t in asyncio.all_tasks() if t is not asyncio.current_task()]
            log.error("shutdown: tasks still running after %.1f s, abandoned: %s",
                      self.config.daemon.shutdown_timeout_s, ", ".join(sorted(pending)))  # fmt: skip
        finally:
            self.gc_watch.uninstall()
            self._tick_executor.shutdown(wait=False, cancel_futures=True)
            if self._solve_pool is not None:
                self._solve_pool.shutdown(wait=False, cancel_futures=True)
            for sink in started:
                await sink.aclose()
            self.imu.close()
            await self.http.close()
            for sig in signals:
                with contextlib.suppress(RuntimeError):
                    loop.remove_signal_handler(sig)
            self.notifier.close()
        if self._startup_error is not None:
            raise self._startup_error
        return 0

    async def _serve(self, deadline: asyncio.Timeout) -> None:
        async with asyncio.TaskGroup() as tg:
            tasks = [tg.create_task(self.supervisor.supervise("imu", self.imu.run), name="imu")]
            for src in self.rig.sources:
                name = f"keypoints:{src.name}"
                tasks.append(tg.create_task(self.supervisor.supervise(name, self._source(src)), name=name))
            lifecycle.enter_phase("opening devices")
            self._startup_error = await self._open_devices()
            if self._startup_error is None:
                if isinstance(self.mattes, RingMattes) and self.scheduler.fusion is not None:
                    tasks.append(tg.create_task(self.supervisor.supervise("mattes", self._matte_loop), name="mattes"))
                tasks.append(tg.create_task(self.supervisor.supervise("scheduler", self._tick_loop), name="scheduler"))
                tasks.append(tg.create_task(self.supervisor.supervise("status", self._status_loop), name="status"))
                self.gc_watch.freeze()  # the start-up heap out of every later collection (see _warm_up)
                lifecycle.enter_phase("running")
                self.notifier.notify("READY=1", f"STATUS=serving {self.http.url}/status")
                self.ready.set()
                await self._stop.wait()
            lifecycle.enter_phase("stopping")
            self.stopping = True
            deadline.reschedule(asyncio.get_running_loop().time() + self.config.daemon.shutdown_timeout_s)
            self.notifier.notify("STOPPING=1", "STATUS=stopping")
            self.imu.stop()
            for device in self.imu.devices:
                device.stop()  # closes the serial ports now
            for t in tasks:
                t.cancel()

    def devices(self) -> list[tuple[str, OpenState]]:
        """Every device of the rig with its opening state: cameras (``camera <name>``), IMU ports (``IMU <path>``),
        the SlimeVR server's and the IMU bridge's sockets."""
        out = [(f"camera {src.name}", src.open_state()) for src in self.rig.sources]
        out += [(f"IMU {d.config.path}", d.open_state()) for d in self.imu.devices]
        if self.imu.slimevr is not None:
            out.append((f"SlimeVR server {self.imu.slimevr.host}", self.imu.slimevr.open_state()))
        if self.imu.bridge is not None:
            out.append((f"IMU bridge {self.imu.bridge.host}:{self.imu.bridge.port}", self.imu.bridge.open_state()))
        return out

    async def _open_devices(self) -> StartupError | None:
        """Wait until every device has opened; the first openings that fail (or time out) stop the start-up."""
        timeout = self.config.daemon.open_timeout_s
        deadline = self.clock() + round(timeout * 1e9)
        while not self._stop.is_set():
            states = self.devices()
            failed = [f"{name}: {state.error}" for name, state in states if state.state == "failed"]
            if failed:
                return StartupError("; ".join(failed))
            pending = [name for name, state in states if state.state != "open"]
            if not pending:
                return None
            if self.clock() > deadline:
                return StartupError(f"{', '.join(pending)} did not open within {timeout:g} s (daemon.open_timeout_s)")
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._stop.wait(), 0.05)
        return None

    def _warm_up(self) -> None:
        """Load (or compile, the first time on a machine) the solver and sorting kernels before serving: a first
        compile takes seconds, which inside a live tick would be seconds of missed output."""
        mounts = self.rig.suits[0].mounts if self.rig.suits else ()
        s = PoseSolver(self.rig.skeleton, self.rig.cameras, self.rig.targets, mounts, self.rig.prior,
                       self.config.solver.cost, self.config.solver.lm.options(),
                       backend="numpy" if self.config.solver.backend == "numpy" else "compiled")  # fmt: skip
        n_cams, n_kp = len(self.rig.cameras), len(self.rig.targets)
        s.solve(
            Observations(
                keypoints=np.zeros((n_cams, n_kp, 2)),
                confidences=np.zeros((n_cams, n_kp)),
                # the learned fusion's E_J has its own compiled kernel: load (or compile) it too
                joint_positions=s.kin.forward(s.theta).positions if self.scheduler.fusion is not None else None,
                dt=self.scheduler.options.dt,
            ),
            update_state=False,
        )
        if n_cams >= 2:
            DetectionSorter(self.rig.cameras, self.config.tracking.sorting.options(),
                            keypoint_names=self.rig.targets.names).warm_up(n_kp)  # fmt: skip
            warm_up_flip_search(self.rig.cameras, n_kp)
        warm_up_assignment()  # SciPy's, imported on first use: here, not in the first tick that matches people
        warm_up_undistortion()  # every keypoint set arriving is undistorted by it, on the event loop
        warm_up_optical_flow()  # the keypoint tracker's, on the capture threads
        # The offset estimates of the status loop, once: their first run, 10 s after READY, imported SciPy's signal
        # package (~200 modules) while the tick ran, and the imports' allocations set off full garbage collections
        # of the whole start-up heap: a second of 26-49 Hz output in every run. The IMU estimate's band-pass is
        # NumPy's now (mocapd.core.band_pass: no SciPy signal package to import, here or later, ~1 s of CPU off
        # every start); the first runs here still do whatever the estimates import first, and the start-up heap is
        # frozen at READY (gc.freeze: out of every later collection).
        t = np.arange(0, 4_000_000_000, 10_000_000, dtype=np.int64)
        wave = np.sin(t / 1e9 * 2 * np.pi)
        estimate_imu_lag(t, wave, t, wave)
        estimate_lag(t, wave, t, wave)  # the cameras' estimate: its first run's imports too
        gc.collect()

    def _source(self, src: KeypointSource) -> Callable[[], Any]:
        def sink(camera: int, capture_ns: int, dets: Detections2D, arrival_ns: int) -> None:
            self.scheduler.add_detections(camera, capture_ns, dets, arrival_ns)
            for tap in self.detection_taps:
                tap(camera, capture_ns, dets, arrival_ns)

        return lambda: src.run(sink)

    async def _tick_loop(self) -> None:
        period = self.scheduler.options.period_ns
        previous = self.plan
        plan = self.plan = TickPlan(period, self.clock() + period, round(self.config.daemon.max_catch_up_s * 1e9))
        if previous is not None:  # a restarted loop keeps the counts
            plan.missed, plan.late = previous.missed, previous.late
        watchdog_every = self.notifier.watchdog_s / 2 if self.notifier.watchdog_s else None
        last_ping = 0
        loop = asyncio.get_running_loop()
        while True:
            await asyncio.sleep(max(0.0, (plan.next_ns - self.clock()) / 1e9))
            # Solve for the scheduled tick time, not the (jittery) wake-up time: output frames stay evenly spaced.
            # The loop samples the inputs (its own buffers, written on it); the solve runs on the tick thread while
            # the loop goes on capturing, reading IMUs and serving clients. One tick at a time: a late one makes
            # the plan skip what it cannot catch up (max_catch_up_s), work never piles up.
            inputs = self.scheduler.sample(plan.next_ns)
            if self.config.daemon.tick_thread:
                frame = await loop.run_in_executor(self._tick_executor, self.scheduler.solve, inputs)
            else:
                frame = self.scheduler.solve(inputs)
            if self.scheduler.options.prediction.predicted:
                # Two loop iterations: the first polls the serial ports and queues their readers after this task,
                # the second runs them, so the IMU samples that arrived while solving are buffered; then the
                # suit wearers are carried to the newest of them.
                await asyncio.sleep(0)
                await asyncio.sleep(0)
                frame = self.scheduler.predict(frame)
            w0, c0 = self.scheduler.stage_clocks()
            for sink in self.sinks:
                sink.publish(frame)
            self.latest = frame
            published = self.clock()
            self.scheduler.record_publish(frame, w0, c0, published)
            # The last second's windows trimmed from their old end (no list rebuilt per tick: the times only grow).
            second_ago = published - 1_000_000_000
            while self._rate_window and self._rate_window[0] <= second_ago:
                self._rate_window.popleft()
            self._rate_window.append(published)
            if self.scheduler.hands is not None:
                seen = {p.identity: (bool(p.hands.present[0]), bool(p.hands.present[1]))
                        for p in frame.people if p.hands is not None}  # fmt: skip
                while self._hand_window and self._hand_window[0][0] <= second_ago:
                    self._hand_window.popleft()
                self._hand_window.append((published, seen))
            if watchdog_every is not None and published - last_ping > watchdog_every * 1e9:
                self.notifier.notify("WATCHDOG=1")
                last_ping = published
            skipped = plan.advance(self.clock())
            if self.camera_watch is not None:
                self._apply_camera_proposals()  # between two ticks: the next one solves with the new camera
            if self.governor is not None:
                self.governor.observe(published - frame.tick_ns, skipped)
                # The process's CPU clock and, at a window's edge, the machine's: the governor's cause test (did a
                # step take work away? did other programs load the machine meanwhile?) needs them.
                machine = self._machine_cpu.read() if self.governor.due(published) else None
                if self.governor.step(published, time.process_time_ns(), machine):
                    self._apply_governor()

    def replace_camera(
        self, index: int, camera: Camera, source: str, details: dict[str, Any] | None = None
    ) -> CameraChange:
        """Camera ``index`` is ``camera`` from the next tick on (its pose changed: its name, size and intrinsics
        stay): the scheduler swaps it in everything that holds it (:meth:`FixedLatencyScheduler.replace_camera`),
        then the rig, the log, ``/status`` and the :attr:`camera_taps` (the session records it). On the event loop,
        between ticks. Raises InputError when ``camera`` changes more than the pose."""
        old = self.rig.cameras[index]
        self.scheduler.replace_camera(index, camera)
        self.rig.cameras[index] = camera
        change = CameraChange(self.scheduler.last_solve_ns, index, camera, source, turn_deg(old, camera),
                              dict(details or {}))  # fmt: skip
        self.camera_changes = [*self.camera_changes[-9:], change]
        d = change.details
        errors = (f"; its people reproject {d['median_px_before']} -> {d['median_px_after']} px"
                  if "median_px_after" in d else "")  # fmt: skip
        log.warning("camera %s recalibrated (%s): turned %.2f deg%s; in the solve again, from the tick after %.3f s",
                    camera.name, source, change.rotation_deg, errors, change.t_ns / 1e9)  # fmt: skip
        for tap in self.camera_taps:
            tap(change)
        return change

    def save_calibration(self, source: str = "request") -> dict[str, Any]:
        """The cameras this daemon runs with now (the camera watch's changes applied) written to ``[calibration]
        save_to``, else the calibration file (:func:`mocapd.service.calibration_save.save_cameras`: atomically, the
        old file backed up beside it), so the next start has them. Logged as a warning (it changes a file the next
        start reads); returns what was written.

        Raises
        ------
        InputError
            No file to write (a synthetic rig without ``save_to``), a name that is not ``.toml``, an unreadable old
            file.
        OutputError
            The file or its backup cannot be written.
        """
        cal = self.config.calibration
        target = cal.save_to or cal.file
        if not target:
            raise InputError("nowhere to save the cameras: [calibration] file is not set (a synthetic rig); set "
                             "[calibration] save_to")  # fmt: skip
        changed = sorted({c.camera.name for c in self.camera_changes})
        saved = save_cameras(self.rig.cameras, Path(target), source=f"mocapd daemon ({source})",
                             world_up=None if cal.world_up == "auto" else cal.world_up)  # fmt: skip
        log.warning("calibration saved to %s on %s: %d camera(s)%s%s", saved.file, source, len(saved.cameras),
                    f", changed while running: {', '.join(changed)}" if changed else ", none changed while running",
                    f"; the old file kept as {saved.backup}" if saved.backup else "")  # fmt: skip
        return {"file": str(saved.file), "backup": None if saved.backup is None else str(saved.backup),
                "cameras": list(saved.cameras), "kept": list(saved.kept), "changed": changed}  # fmt: skip

    def _apply_camera_proposals(self) -> None:
        """The camera watch's re-estimates that passed their checks, applied (``[calibration.watch] apply``)."""
        assert self.camera_watch is not None
        pending = self.camera_watch.pending()
        if pending:
            self._say_camera_events()  # the re-estimate said before its application
        for index, p in pending:
            # doubt_ns: the first solve that left the camera out; the re-estimate holds from then (`resolve` uses it)
            self.replace_camera(index, p.camera, "camera watch", {
                "matches": p.matches, "inliers": p.inliers, "median_px_before": p.median_px_before,
                "median_px_after": p.median_px_after, "doubt_ns": self.camera_watch.doubted_since(index)})  # fmt: skip

    def _landmark_fronts(self) -> list[LandmarkFront]:
        """The landmark stages of the cameras' detectors, each once."""
        out: list[LandmarkFront] = []
        for src in self.rig.sources:
            group = getattr(src, "group", None)
            for f in landmark_fronts(group if group is not None else getattr(src, "detector", None)):
                if all(f is not g for g in out):
                    out.append(f)
        return out

    def _apply_governor(self) -> None:
        """The governor's level to the keypoint sources (tracking rate), the detectors (duty), the landmark model and
        the scheduler (people solved every n-th tick), said in the log: what is shed now and why."""
        assert self.governor is not None
        level = self.governor.level
        # A paced detector leaves a camera's people to the tracking for a pace: never past their age limit (the
        # pace's pass and delivery on top, a quarter of it).
        ages = [t.options.max_age_s for s in self.rig.sources if (t := getattr(s, "tracker", None)) is not None]
        pace_s = min([level.pace_s, *(0.75 * a for a in ages)])
        for src in self.rig.sources:
            if hasattr(src, "tracking_rate_scale"):
                src.tracking_rate_scale = level.tracking_rate
            group = getattr(src, "group", None)  # a packed detection group (shared by its cameras)
            if group is not None and hasattr(group, "duty"):
                group.duty = level.detector_duty
                group.pace_ns = round(pace_s * 1e9)  # the deepest steps: paced, on half-scale tiles
                group.packer.tile_ratio = level.tile_ratio
        self.scheduler.solve_every = level.solve_every  # the deepest steps: people solved on every 2nd or 3rd tick
        # landmarks = "auto": the landmark model off from step 1 on
        shed_landmarks(self._landmark_fronts(), None if level.landmarks else f"step {self.governor.step_index}, "
                       f"{self.governor.last_reason}")  # fmt: skip
        log.warning("governor: %s (%s)", level.name, self.governor.last_reason)

    async def _matte_loop(self) -> None:
        """Background subtraction of the cameras' newest frames at the learned stream's rate, off the event loop."""
        assert isinstance(self.mattes, RingMattes) and self.scheduler.fusion is not None
        period = self.scheduler.fusion.models.stride / self.scheduler.options.rate_hz
        while True:
            await in_daemon_thread(self.mattes.poll)
            await asyncio.sleep(period)

    async def _status_loop(self) -> None:
        names = [c.name for c in self.rig.cameras]
        ticks = 0
        estimating: asyncio.Task[None] | None = None
        try:
            while True:
                await asyncio.sleep(1.0)
                ticks += 1
                self._observe_drift()
                self.live_calibration.poll(self.imu.ingest, self.clock())
                # Offset suggestions from the last seconds of keypoints, between ticks, beside this loop: on a
                # machine with no time between ticks a step runs per tick, and the status lines go on meanwhile.
                if ticks % 10 == 0 and (estimating is None or estimating.done()):
                    if estimating is not None and not estimating.cancelled() and estimating.exception() is not None:
                        log.warning("offset estimate failed: %s", estimating.exception())
                    estimating = asyncio.create_task(self.estimate_offsets(names), name="offset estimate")
                self._status_second()
        finally:
            if estimating is not None:
                estimating.cancel()

    def _status_second(self) -> None:
        """The status loop's work of each second: implausible poses said, the camera watch's news, the status
        line."""
        warnings: list[str] = []
        if self.scheduler.lock.acquire(timeout=READ_WAIT_S):  # the tick thread adds people's monitors
            try:
                warnings = first_events(self.scheduler.plausibility, self._implausible_said)
            finally:
                self.scheduler.lock.release()
        for warning in warnings:
            log.warning("%s", warning)
        self._say_camera_events()
        line = self.status_line_text()
        self.notifier.notify(f"STATUS={line}")
        if self.status_line is not None:
            self.status_line(line)

    async def estimate_offsets(self, names: list[str]) -> None:
        """The cameras' and suits' offset suggestions (``/status``), computed on the event loop in steps of about a
        millisecond (:func:`run_in_steps`).

        Not in a thread (issue 45: the hiccup of every ``demo --synthetic`` near t = 10 s): the estimate's thousands
        of small NumPy calls then competed with the tick for the interpreter lock, and each time the tick let go
        of it (a compiled kernel, a socket) it waited a switch interval (5 ms) to get it back; ticks took 57-68 ms
        for the seconds the estimate ran. Between ticks, a due tick waits for one step at most."""
        offsets = self.scheduler.options.camera_offsets_ns
        camera_steps = camera_offset_steps(names, self.scheduler.camera_frames(), offsets)
        self.scheduler.suggested_offsets = await run_in_steps(camera_steps)
        imu_inputs = self.scheduler.imu_alignment_inputs()
        imu_steps = imu_offset_steps(imu_inputs, dict(self.scheduler.options.imu_offsets_ns))
        self.scheduler.suggested_imu_offsets = await run_in_steps(imu_steps)

    def _say_camera_events(self) -> None:
        """The bumped-camera watch's news to the log (the console), once each."""
        if self.camera_watch is None:
            return
        for _, name, what, d in self.camera_watch.new_events():
            if what == "re-estimated" and d["refused"] and name in self._refusals_said:
                continue  # refused again (the matches are gathered again, about once a second): said once a bump
            if what == "re-estimated" and d["refused"]:
                self._refusals_said.add(name)
            elif what == "bumped":
                self._refusals_said.discard(name)
            if what == "bumped":
                log.warning("camera %s moved: its people reproject %s px off (%s px before); left out of the solve "
                            "until it is recalibrated or back", name, d["residual_px"], d["baseline_px"])  # fmt: skip
            elif what == "re-estimated":
                applying = self.camera_watch.watch.options.apply
                why = ("not applied: " + d["refused"] if d["refused"] else "applied" if applying
                       else "not applied: [calibration.watch] apply = false")  # fmt: skip
                again = "; said once, retried while it stays bumped" if d["refused"] else ""
                log.warning("camera %s re-estimated from the people, the others held: turned %.2f deg, %s -> %s px "
                            "(/status camera_watch.%s.proposal; %s%s)", name, d["rotation_deg"],
                            d["median_px_before"], d["median_px_after"], name, why, again)  # fmt: skip
            elif what == "released":
                log.warning("camera %s back in the solve: %d re-estimates in a row refused (the last: %s); it may not "
                            "be the camera that moved: the others are re-examined without it for %g s (/status "
                            "camera_watch.%s.re_examining)", name, d["refused"], d["reason"], d["re_examine_s"],
                            name)  # fmt: skip
            else:
                log.warning("camera %s agrees with the others again (%s px)", name, d["residual_px"])

    def _observe_drift(self) -> None:
        """Each suit sensor's newest samples to the still-drift estimate (:mod:`mocapd.core.yaw_drift`)."""
        span = round(self.still_drift.options.max_span_s * 1e9)
        for suit in self.rig.suits:
            for sid in suit.sensors:
                stream = self.imu.ingest.streams.get(sid)
                if stream is None or not len(stream.buffer):
                    continue
                times = stream.buffer.times()
                k = int(np.searchsorted(times, times[-1] - span))
                rows = stream.buffer.rows()[k:]
                self.still_drift.observe(sid, times[k:], rows[:, 0:4], rows[:, 4:7])

    def heading_status(self) -> dict[str, Any]:
        """``imu_heading``: per suit and sensor the camera correction's state (docs/imu.md) and ``yaw_drift``: the
        drift measured while still and the one the heading resets revealed."""
        out = self.scheduler.heading_status()
        now = self.clock()
        for sensors in out.values():
            for sid, entry in sensors.items():
                entry["yaw_drift"] = {**self.still_drift.status(sid), **self.resets.status(sid, now)}
        return out

    # ------------------------------------------------------------------------------------------ health
    def status_line_text(self) -> str:
        """The console's one line a second. On the event loop, so it reads counters and one percentile: the whole
        /status (every stage's percentiles, every camera's tracker statistics) cost ~100 ms of loop time a second
        on the 2-core camera demo, six ticks' worth, every second (issue 39's profile)."""
        e2e = self.scheduler.latency["end_to_end"].percentiles_ms((50,))["p50"]
        people = ", ".join(p.identity for p in self.latest.people) if self.latest else ""
        line = (
            f"t={(self.clock() - self.started_ns) / 1e9:6.1f} s  output {len(self._rate_window):3d} Hz  "
            f"missed {self.plan.missed if self.plan else 0} late {self.plan.late if self.plan else 0}  "
            f"e2e p50 {e2e} ms  people [{people}]"
        )
        if self.governor is not None and self.governor.step_index:
            line += f"  shed: {self.governor.level.name}"
        marks = status_field(self._landmark_fronts())
        if marks is not None:
            line += f"  {marks}"
        if self.camera_watch is not None and (doubt := self.camera_watch.in_doubt()):
            line += f"  camera moved? {', '.join(doubt)}"
        if self.imu.devices:
            streaming = sum(1 for d in self.imu.devices if d.streaming.is_set())
            line += f"  IMUs {streaming}/{len(self.imu.devices)}"
        opened = [getattr(getattr(s, "frames", None), "opened", None) for s in self.rig.sources]
        if any(isinstance(o, threading.Event) for o in opened):  # frame sources of mocapd.io: a capture device
            up = sum(1 for o in opened if isinstance(o, threading.Event) and o.is_set())
            detected = sum(int(getattr(s, "detected", 0)) for s in self.rig.sources)
            line += f"  cameras up {up}/{len(opened)}  detected {detected}"
        return "  ".join([line, *(extra() for extra in self.status_line_extras)])

    def status(self) -> dict[str, Any]:
        """The /status document."""
        s = self.scheduler.status()
        frame = self.latest
        return {
            "uptime_s": round((self.clock() - self.started_ns) / 1e9, 3),
            "ready": self.ready.is_set(),
            "stopping": self.stopping,
            "output": {
                "configured_hz": self.scheduler.options.rate_hz,
                "achieved_hz": len(self._rate_window),
                "frames": s["published"],
                "missed_ticks": self.plan.missed if self.plan else 0,
                "late_ticks": self.plan.late if self.plan else 0,
                "latency_s": self.scheduler.latency_ns / 1e9,
                "latency": self.scheduler.latency_status(),
                "mode": s["output"],
            },
            "latency_ms": s["latency_ms"],
            "latency_histograms": latency_snapshot(self.scheduler.latency),
            "cpu_s": s["cpu_s"],
            "gc": self.gc_watch.status(),  # collections and their pauses per generation since start
            "person_cpu_ms": s["person_cpu_ms"],
            "hands": self.hand_status(),
            "governor": None if self.governor is None else self.governor.status(),
            "solve_threads": self.solve_threads,
            "counters": s["counters"],
            "cameras": [
                {**src.status(), **cam} for src, cam in zip(self.rig.sources, s["cameras"], strict=False)
            ],
            "imu": self.imu.status(),
            "imu_lookups": s["imu_samples"],
            "imu_heading": self.heading_status(),
            # per suit: the mountings refined from the cameras' first seconds (off by default; docs/imu.md)
            "imu_mounting_from_cameras": self.scheduler.mounting_status(),
            # per suit: the posture its calibration found and each sensor's residuals (docs/imu.md)
            "imu_calibration": {s.id: s.calibration.summary() for s in self.rig.suits},
            "imu_calibration_routine": self.live_calibration.status(self.clock()),
            "heading_resets": [{**r, "s_ago": round((self.clock() - r["t_ns"]) / 1e9, 1)} for r in self.reset_log],
            "heading_resets_refused": self.reset_limit.refused,  # over the rate limit
            "http_refused": self.http.refused.as_dict(),  # foreign Host or Origin, POSTs without X-Mocapd-Request
            "plausibility": s["plausibility"],
            "camera_watch": None if self.camera_watch is None else self.camera_watch.status(),
            "camera_changes": [
                {"camera": c.camera.name, "source": c.source, "t_solve_ns": c.t_ns, "rotation_deg": c.rotation_deg,
                 **c.details, "R": np.round(c.camera.R, 9).tolist(), "t": np.round(c.camera.t, 6).tolist()}
                for c in self.camera_changes
            ],
            "tasks": {k: v.as_dict() for k, v in self.supervisor.tasks.items()},
            "sinks": {sink.name: sink.status() for sink in self.sinks if isinstance(sink, ReportingSink)},
            "subjects": s["people"],
            "time_alignment": {
                "configured_camera_offsets_ms": {
                    c.name: o / 1e6
                    for c, o in zip(self.rig.cameras, self.scheduler.options.camera_offsets_ns, strict=False)
                },
                "suggested_camera_offsets_ms": s["suggested_camera_offsets_ms"],
                "configured_imu_offsets_ms": {k: v / 1e6 for k, v in self.scheduler.options.imu_offsets_ns.items()},
                "suggested_imu_offsets_ms": self.scheduler.suggested_imu_offsets,
            },
            **{name: provider() for name, provider in self.status_extras.items()},
            "frame": None if frame is None else {
                "frame": frame.frame,
                "t_solve_ns": frame.t_solve_ns,
                "missing_cameras": frame.missing_cameras,
                "people": [
                    {"identity": p.identity, "suit": p.suit, "root_m": [round(float(v), 4) for v in p.theta[:3]],
                     "confidence": round(p.confidence, 3), "views": p.views, "imus": p.imus,
                     "iterations": p.iterations, "t_pose_ns": frame.pose_time_ns(p)}
                    for p in frame.people
                ],
            },
        }  # fmt: skip

    def hand_status(self) -> dict[str, Any] | None:
        """The finger solve in ``/status`` (None: hands off, the detections carry no hand keypoints): per person the
        hands solved per second over the last second (the output rate when a hand is solved every tick), the
        stage's counters and its CPU per person and tick (both hands). The hand landmark model's rates per camera
        are in ``detector.hands``."""
        stage = self.scheduler.hands
        if stage is None:
            return None
        rates: dict[str, dict[str, int]] = {}
        for _, seen in self._hand_window:
            for identity, (left, right) in seen.items():
                r = rates.setdefault(identity, {"left_hz": 0, "right_hz": 0})
                r["left_hz"] += left
                r["right_hz"] += right
        return {"people": rates, "counters": dict(stage.counters), "cpu_ms": stage.cpu.summary()}

    def metrics(self) -> str:
        """The /metrics document (Prometheus text format 0.0.4) of the daemon's state now."""
        return render_metrics(self.status()).decode()
