"""The camera demo's rig: the Pose2Sim multi-person demo seen by four GigE Vision cameras, through the detector.

Per camera: an :class:`~mocapd.io.aravis_camera.AravisSource` opened by IP (the fake camera serving that camera's
video, :mod:`mocapd.sim.fake_cameras`), Bayer frames demosaiced into its ring, and a
:class:`~mocapd.pipeline.keypoint_source.DetectorKeypointSource` running the onnxruntime pose detector on the
newest frame whenever a detector worker is free (the four cameras share ``[detector] workers`` threads, so the
detection rate per camera is what the CPU gives; skipped frames are counted), its detections stamped with the
camera's frame timestamp mapped to the host clock. The cameras are the demo's Qualisys calibration, scaled to the
served image size.
"""

from __future__ import annotations

import ctypes
import queue
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from mocapd.core.camera import Camera
from mocapd.core.keypoints import coco17_targets
from mocapd.core.skeleton import Skeleton
from mocapd.core.sorting import Detections2D
from mocapd.errors import ConfigError
from mocapd.io.aravis_camera import AravisCameraConfig, AravisSource
from mocapd.io.calibration_files import core_cameras, read_qca
from mocapd.io.pose2sim_demo import CAMERAS, demo_calibration, demo_video
from mocapd.io.prior import resolve_prior
from mocapd.pipeline.clocksync import ClockSync
from mocapd.pipeline.detector import OnnxPoseDetector
from mocapd.pipeline.detector_config import DetectorConfig
from mocapd.pipeline.keypoint_source import DetectorKeypointSource
from mocapd.pipeline.packed_source import PackedDetectionGroup, PackedKeypointSource
from mocapd.pipeline.packing import packed_detector_from_config
from mocapd.service.config import Config
from mocapd.service.daemon import Rig
from mocapd.sim.fake_cameras import FakeCameraSpec


@dataclass(frozen=True)
class CameraDemoOptions:
    """What the camera demo serves and how (``mocapd demo`` flags).

    Attributes
    ----------
    demo : str
        Pose2Sim demo folder (``Demo_MultiPerson``: two people walking, four 60 fps portrait cameras).
    scale : float
        Served image size as a fraction of the videos' 1088 x 1920 (0.5: 544 x 960).
    pixel_format : str
        What the cameras send (``BayerRG8``: what a colour machine-vision camera sends; mocapd demosaics).
    max_frames : int
        Frames of each video served, looped (the demo videos have 100).
    replug_after_s : float
        A fake camera whose process ends is started again after this long.
    lost_after_s : float
        A camera silent this long is declared lost and reopened with back-off.
    packed : bool
        Detect the newest frames of all cameras together, their people's regions packed onto shared canvases
        (``[detector.packing]``, :mod:`mocapd.pipeline.packed_source`); False (default): one whole-frame
        inference per camera frame, the cameras taking turns on ``[detector] workers``. Packing detects more
        camera-frames per second, but each camera's detections wait for the whole pass: on this CPU they arrive
        three times later, so fewer are in time for the fixed latency (docs/daemon.md, Numbers).
    latency_s : float
        The daemon's fixed delay between solve time and wall time. A CPU detector shared by four cameras
        delivers each camera's detections late and far apart, and the scheduler interpolates only between
        detections it already has: the latency must cover the detection delay plus the interval between two
        detections of a camera. The keypoint hold and gap limits follow it (``latency/2``, ``2 × latency``).
    """

    demo: str = "Demo_MultiPerson"
    scale: float = 0.5
    pixel_format: str = "BayerRG8"
    max_frames: int = 100
    replug_after_s: float = 3.0
    lost_after_s: float = 2.0
    latency_s: float = 1.0
    packed: bool = False

    def __post_init__(self) -> None:
        if not 0.05 <= self.scale <= 1.0:
            raise ConfigError(f"camera demo scale = {self.scale}; allowed: 0.05 .. 1.0")
        if self.max_frames < 1 or self.replug_after_s < 0 or self.lost_after_s <= 0:
            raise ConfigError("camera demo: max_frames >= 1, replug_after_s >= 0 and lost_after_s > 0 are required")
        if not 0.0 < self.latency_s <= 2.0:
            raise ConfigError(f"camera demo latency = {self.latency_s} s; allowed: (0, 2]")

    def apply(self, config: Config) -> Config:
        """``config`` with this demo's scheduler timing."""
        lat = self.latency_s
        daemon = config.daemon.model_copy(
            update={"latency_s": lat, "keypoint_max_age_s": lat / 2, "keypoint_max_gap_s": 2 * lat}
        )
        return config.model_copy(update={"daemon": daemon})


def video_fps(path: Path) -> float:
    """Frame rate of a video file (30 if the container does not say)."""
    cap = cv2.VideoCapture(str(path))
    try:
        return float(cap.get(cv2.CAP_PROP_FPS)) or 30.0
    finally:
        cap.release()


def demo_cameras(opts: CameraDemoOptions, addresses: list[str]) -> tuple[list[Camera], list[FakeCameraSpec]]:
    """The calibrated cameras (scaled to the served size) and the fake camera serving each one's video."""
    cameras = core_cameras(read_qca(demo_calibration(opts.demo)), opts.scale)
    if len(addresses) < len(cameras):
        raise ConfigError(f"{len(cameras)} cameras need as many addresses, got {addresses}")
    specs = []
    for cam, video_name, address in zip(cameras, CAMERAS, addresses, strict=False):
        video = demo_video(opts.demo, video_name)
        specs.append(FakeCameraSpec(cam.name, video, address, (cam.width, cam.height), video_fps(video),
                                    opts.pixel_format, opts.max_frames))  # fmt: skip
    return cameras, specs


def name_os_thread(name: str) -> None:
    """Give the calling thread an OS-level name (``/proc/.../comm``; Python's thread names stay in Python).

    Threads the named thread starts inherit the name (Linux), onnxruntime's intra-op pool included, so per-thread
    CPU accounting can attribute them. A no-op where ``prctl`` is missing.
    """
    libc = ctypes.CDLL(None, use_errno=True)
    prctl = getattr(libc, "prctl", None)
    if prctl is not None:
        prctl(15, name.encode()[:15], 0, 0, 0)  # 15 = PR_SET_NAME


class PooledDetector:
    """The 2D detector behind :class:`DetectorKeypointSource`: RGB ring image in, COCO-17 people out.

    One onnxruntime session per worker thread (``[detector] workers``), handed out through a queue.
    """

    def __init__(self, cfg: DetectorConfig) -> None:
        self._pool: queue.SimpleQueue[OnnxPoseDetector] = queue.SimpleQueue()
        self.executor = ThreadPoolExecutor(
            max_workers=cfg.workers, thread_name_prefix="mocapd-detect", initializer=name_os_thread,
            initargs=("mocapd-detect",),
        )  # fmt: skip
        for _ in range(cfg.workers):
            # Made in a worker thread: onnxruntime's own threads inherit its name, so CPU accounting by thread
            # name (mocapd bench latency --rig cameras) sees the detector's whole cost.
            self._pool.put(self.executor.submit(OnnxPoseDetector.from_config, cfg).result())

    def __call__(self, rgb: NDArray[np.uint8]) -> Detections2D:
        det = self._pool.get()
        try:
            people = det.detect(
                np.asarray(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), np.uint8)
            )  # the detector takes BGR, the ring holds RGB
        finally:
            self._pool.put(det)
        kp = people.keypoints
        return Detections2D(kp[..., :2], kp[..., 2])

    def close(self) -> None:
        self.executor.shutdown(wait=True)


def make_detector(cfg: DetectorConfig, opts: CameraDemoOptions, cameras: list[Camera]) -> AnyDetector:
    """The demo's detector (blocking: loads the model): one packed detector for all cameras on one named worker
    thread, or a pool of whole-frame detectors."""
    if not opts.packed:
        return PooledDetector(cfg)
    executor = ThreadPoolExecutor(1, thread_name_prefix="mocapd-detect", initializer=name_os_thread,
                                  initargs=("mocapd-detect",))  # fmt: skip
    sizes = [(c.width, c.height) for c in cameras]
    return PackedDetectionGroup(executor.submit(packed_detector_from_config, cfg, sizes).result(), executor)


def build_rig(
    config: Config,
    opts: CameraDemoOptions,
    cameras: list[Camera],
    specs: list[FakeCameraSpec],
    detector: AnyDetector,
) -> tuple[Rig, list[AravisSource]]:
    """Capture sources, keypoint sources and the people model of the camera rig (blocking: loads the prior)."""
    d = config.daemon
    captures: list[AravisSource] = []
    sources: list[DetectorKeypointSource] = []
    for i, (cam, spec) in enumerate(zip(cameras, specs, strict=True)):
        capture = AravisSource(
            AravisCameraConfig(
                cam.name, address=spec.address, pixel_format=opts.pixel_format, region=(0, 0, cam.width, cam.height),
                frame_rate=spec.video_fps, packet_size=8192, ring_slots=8, lost_after_s=opts.lost_after_s,
            ),
            backoff_s=(d.restart_min_s, d.restart_max_s),
        )  # fmt: skip
        captures.append(capture)
        clock = ClockSync(tick_hz=1e9, wrap_bits=64)
        if isinstance(detector, PackedDetectionGroup):
            sources.append(PackedKeypointSource(i, capture, detector, device_clock=clock))
        else:
            sources.append(DetectorKeypointSource(i, capture, detector, executor=detector.executor, device_clock=clock))
    skeleton = Skeleton.from_height(1.75)
    rig = Rig(cameras, list(sources), skeleton, coco17_targets(skeleton), resolve_prior(config.solver.prior))
    return rig, captures


AnyDetector = PooledDetector | PackedDetectionGroup
