"""The rig a config describes, built: calibrated cameras, their frame and keypoint sources, the detector they share,
the people's model, the IMU suits — and for a synthetic rig, the simulated world with its simulated devices.

Two steps, so that ``mocapd check-config`` says everything that can be said without touching a device:
:func:`~mocapd.service.rig_plan.plan_rig` (its own module, which imports no detector) checks the rig against its
calibration and files, then :func:`build_rig` makes the sources (nothing is opened yet: the daemon opens every
device before it reports READY, and names the one that fails).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

from mocapd.core.camera import Camera
from mocapd.core.keypoints import hand_keypoint_names, keypoint_format
from mocapd.core.prior import PcaPrior
from mocapd.errors import ConfigError
from mocapd.io.aravis_camera import AravisCameraConfig, AravisSource
from mocapd.io.frame_source import ThreadedSource
from mocapd.io.os_threads import worker_thread_setup
from mocapd.io.pixels import capture_ring, pixel_format
from mocapd.io.prior import resolve_prior
from mocapd.io.uvc_source import UvcCameraConfig, UvcSource
from mocapd.io.video_source import ImageFolderSource, VideoFileSource
from mocapd.pipeline.clocksync import ClockSync
from mocapd.pipeline.detector_config import DetectorConfig
from mocapd.pipeline.detector_pool import AnyDetector, make_detector, target_columns
from mocapd.pipeline.keypoint_source import DetectorKeypointSource, KeypointSource
from mocapd.pipeline.keypoint_tracker import KeypointTracker
from mocapd.pipeline.latency import AutoLatencyOptions
from mocapd.pipeline.packed_source import PackedDetectionGroup, PackedKeypointSource
from mocapd.pipeline.remote_cameras import RemoteRig, ZenohKeypointSource
from mocapd.pipeline.scheduler import Suit
from mocapd.service.config import Config
from mocapd.service.config.cameras import (
    AravisCamera,
    CameraConfig,
    ImagesCamera,
    UvcCamera,
    VideoCamera,
    ZenohCamera,
)
from mocapd.service.config.imu import ImuConfig
from mocapd.service.daemon import Rig
from mocapd.service.rig_plan import RigPlan, rig_skeleton
from mocapd.service.suits import load_suits
from mocapd.sim.suits import SimulatedSuits
from mocapd.sim.world import SyntheticKeypointSource, SyntheticWorld

TRACK_THREAD = "mocapd-track"  # the tracking pool's threads, by this OS name in per-thread CPU accounting
DEFAULT_HEIGHT_M = 1.75  # the skeleton people start with, until body sizing gives each their own


@dataclass
class BuiltRig:
    """A built rig and what it owns beside the daemon (closed by :meth:`close` once the daemon has stopped)."""

    rig: Rig
    imu: ImuConfig
    """``[imu]`` with the simulated suits' ports added (a synthetic rig)."""
    captures: list[ThreadedSource] = field(default_factory=list)
    detector: AnyDetector | None = None
    world: SyntheticWorld | None = None
    epoch_ns: int = 0
    """Host time of the synthetic world's t = 0."""
    simulated: SimulatedSuits | None = None
    remote: RemoteRig | None = None
    """The Zenoh session of the rig's ``zenoh`` cameras (camera hosts), when it has any."""
    tracking_pool: ThreadPoolExecutor | None = None
    """The keypoint trackers' worker threads (``[detector.tracking] thread = "pool"``)."""

    def close(self) -> None:
        """Stop the detector's workers (after the detection in flight), the tracking pool, the simulated devices
        and the Zenoh session."""
        if self.tracking_pool is not None:
            self.tracking_pool.shutdown(wait=True, cancel_futures=True)
            self.tracking_pool = None
        if self.remote is not None:
            self.remote.close()
            self.remote = None
        if self.detector is not None:
            self.detector.close()
            self.detector = None
        if self.simulated is not None:
            self.simulated.close()
            self.simulated = None


def detection_columns(cfg: DetectorConfig, targets: tuple[str, ...], remote: bool) -> tuple[str, ...]:
    """The keypoint columns the rig's detections carry: the track targets', then both hands' 21 keypoints when the
    hand landmark model runs (``[detector] hands``: the scheduler's finger solve takes them). A rig with camera
    hosts keeps the targets' alone: the hosts' keypoint stream carries the body's columns only."""
    if remote or not cfg.hands_decision()[0]:
        return targets
    return targets + hand_keypoint_names("left") + hand_keypoint_names("right")


def build_rig(config: Config, plan: RigPlan, clock: Callable[[], int] = time.monotonic_ns) -> BuiltRig:
    """Make the rig's sources (blocking: loads the detector model and the prior; starts simulated devices)."""
    prior = resolve_prior(config.solver.prior)
    if plan.synthetic:
        return _build_synthetic(config, plan, prior, clock)
    skeleton = rig_skeleton(config)
    fmt = keypoint_format(config.detector.options().output_format)  # blazepose33 when landmarks run
    targets = fmt.track_targets(skeleton)
    backoff = (config.daemon.restart_min_s, config.daemon.restart_max_s)
    pairs = list(zip(config.cameras, plan.cameras, strict=True))
    local = {i: frame_source(c, cam, backoff) for i, (c, cam) in enumerate(pairs) if not isinstance(c, ZenohCamera)}
    captures = list(local.values())
    for capture in captures:  # the event loop's tick first, then the capture threads' tracking, then the detector
        capture.worker_nice = config.daemon.capture_nice
    remote_hosts = sorted({c.host for c in config.cameras if isinstance(c, ZenohCamera)})
    by_host = {h: [c.name for c in config.cameras if isinstance(c, ZenohCamera) and c.host == h] for h in remote_hosts}
    remote = RemoteRig(config.zenoh, remote_hosts, cameras=by_host, clock=clock) if remote_hosts else None
    detector_config = config.detector.options()
    detector: AnyDetector | None = None
    names = detection_columns(detector_config, targets.names, bool(remote_hosts))
    if local:  # a rig of camera hosts only runs no detector here: the hosts run it
        sizes = [(c.width, c.height) for c in plan.cameras]
        columns = target_columns(detector_config, names)
        detector = make_detector(detector_config, sizes, columns, config.daemon.detector_nice)
    sources: list[KeypointSource] = []
    tracking = detector_config.tracking
    track = tracking.enabled and detector is not None
    pool = None
    if track and tracking.thread == "pool":
        pool = ThreadPoolExecutor(tracking.workers, thread_name_prefix=TRACK_THREAD, initializer=worker_thread_setup,
                                  initargs=(TRACK_THREAD, config.daemon.capture_nice))  # fmt: skip
    # A remote frame older than the latency on arrival is counted late; under "auto" the latency moves, so only
    # what is older than its ceiling is surely late here (the timeline drops the rest as it does local frames).
    latency_s = config.daemon.latency_s
    latency_ns = AutoLatencyOptions().max_ns if latency_s == "auto" else round(latency_s * 1e9)
    try:
        for i, (cam, calibrated) in enumerate(pairs):
            if isinstance(cam, ZenohCamera):
                assert remote is not None
                sources.append(ZenohKeypointSource(i, cam.name, cam.host, remote, (calibrated.width, calibrated.height),
                                                   len(targets), latency_ns, clock=clock))  # fmt: skip
                continue
            capture = local[i]
            # A camera's own frame clock (exposure time) beats the host's arrival time; a replayed file has none
            # worth mapping: its frames are published at their due time.
            clk = ClockSync(tick_hz=1e9, wrap_bits=64) if isinstance(cam, AravisCamera | UvcCamera) else None
            # Keypoints between detections: one tracker per camera, on its capture thread or on the pool.
            size = (calibrated.width, calibrated.height)
            tracker = KeypointTracker(len(names), tracking, names, size) if track else None
            if isinstance(detector, PackedDetectionGroup):
                sources.append(PackedKeypointSource(i, capture, detector, device_clock=clk, clock=clock,
                                                    tracker=tracker, tracking_pool=pool))  # fmt: skip
            elif detector is not None:
                sources.append(DetectorKeypointSource(i, capture, detector, executor=detector.executor,
                                                      device_clock=clk, clock=clock, tracker=tracker,
                                                      tracking_pool=pool))  # fmt: skip
        suits = load_suits(config.imu, skeleton)
    except BaseException:
        if detector is not None:
            detector.close()
        if pool is not None:
            pool.shutdown(wait=False)
        raise
    rig = Rig(plan.cameras, sources, skeleton, targets, prior, suits, names if names != targets.names else ())
    return BuiltRig(rig, config.imu, captures, detector, remote=remote, tracking_pool=pool)


def frame_source(cam: CameraConfig, calibrated: Camera, backoff_s: tuple[float, float]) -> ThreadedSource:
    """The capture source of one configured camera, its ring sized to the camera's calibration."""
    w, h = calibrated.width, calibrated.height
    if isinstance(cam, AravisCamera):
        fmt = pixel_format(cam.pixel_format)
        cfg = AravisCameraConfig(
            cam.name, address=cam.address or None, serial=cam.serial or None, device_id=cam.device_id or None,
            interface=cam.interface,
            pixel_format=cam.pixel_format, region=None if cam.region is None else tuple(cam.region),  # type: ignore[arg-type]
            binning=None if cam.binning is None else tuple(cam.binning),  # type: ignore[arg-type]
            frame_rate=cam.frame_rate, exposure_us=cam.exposure_us, gain_db=cam.gain_db,
            trigger=cam.trigger or None, packet_size=cam.packet_size, n_buffers=cam.n_buffers,
            ring_slots=cam.ring_slots, lost_after_s=cam.lost_after_s, socket_frames=cam.socket_frames,
            packet_timeout_ms=cam.packet_timeout_ms, frame_retention_ms=cam.frame_retention_ms,
            packet_delay_ns=cam.packet_delay_ns, ptp=cam.ptp, features=tuple(cam.features.items()),
        )  # fmt: skip
        ring = capture_ring(cam.name, cam.ring_slots, h, w, fmt)
        return AravisSource(cfg, ring, backoff_s=backoff_s)
    if isinstance(cam, UvcCamera):
        uvc = UvcCameraConfig(cam.name, cam.device, w, h, fps=cam.fps, fourcc=cam.fourcc, ring_slots=cam.ring_slots)
        return UvcSource(uvc, backoff_s=backoff_s)
    if isinstance(cam, VideoCamera):
        return VideoFileSource(cam.name, Path(cam.path), loop=cam.loop, ring_slots=cam.ring_slots, backoff_s=backoff_s)
    if isinstance(cam, ImagesCamera):
        return ImageFolderSource(cam.name, Path(cam.path), fps=cam.fps, loop=cam.loop, ring_slots=cam.ring_slots,
                                 backoff_s=backoff_s)  # fmt: skip
    raise ConfigError(f"camera {cam.name!r}: a {cam.source} camera has no frame source")


def _build_synthetic(config: Config, plan: RigPlan, prior: PcaPrior | None, clock: Callable[[], int]) -> BuiltRig:
    syn = config.synthetic
    world = SyntheticWorld(len(plan.cameras), syn.people, syn.suits, seed=syn.seed, motion=syn.motion,
                           camera_names=[c.name for c in plan.cameras])  # fmt: skip
    epoch = clock()
    simulated = SimulatedSuits.start(world, syn.imu_rate_hz, epoch)
    sources: list[KeypointSource] = [
        SyntheticKeypointSource(world, c, epoch_ns=epoch, rate_hz=syn.camera_rate_hz, delay_s=syn.detection_delay_s,
                                noise_px=syn.noise_px, seed=syn.seed, clock=clock)
        for c in range(len(world.cameras))
    ]  # fmt: skip
    suits = [Suit.from_calibration(s.id, world.calibration(s), world.skeleton) for s in world.suits]
    if config.imu.sources():  # IMU inputs of its own beside the simulated suits (e.g. SlimeVR trackers): their suits
        suits += load_suits(config.imu, world.skeleton)
    # The rig's calibration is its own list: the world's is the truth (SyntheticWorld.bump turns a camera there alone)
    rig = Rig(list(world.cameras), sources, world.skeleton, world.targets, prior, suits)
    # The simulated devices reconnect and stall-detect faster than real ones need: they restart in milliseconds.
    imu = config.imu.model_copy(update={
        "ports": (*config.imu.ports, *simulated.ports), "rate_hz": syn.imu_rate_hz,
        "reconnect_min_s": 0.2, "reconnect_max_s": 1.0, "stall_timeout_s": 1.0,
    })  # fmt: skip
    return BuiltRig(rig, imu, world=world, epoch_ns=epoch, simulated=simulated)
