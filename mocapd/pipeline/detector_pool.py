"""The detector the daemon's cameras share: whole-frame workers, or packed passes over the cameras.

:class:`PooledDetector` is the :data:`~mocapd.pipeline.keypoint_source.Detector` behind
:class:`~mocapd.pipeline.keypoint_source.DetectorKeypointSource`: one onnxruntime session per worker thread
(``[detector] workers``), handed out through a queue, the cameras taking turns. With ``[detector.packing]
enabled`` (true or "auto"), :func:`make_detector` builds a
:class:`~mocapd.pipeline.packed_source.PackedDetectionGroup` instead: the newest frames of the cameras detected
together on shared canvases (with "auto", or alone where a whole frame costs less), one pass per session in flight.

Sessions and threads (``[detector] workers``, ``intra_op_threads``; :meth:`DetectorConfig.sessions`): "auto" runs
one session per two cores of this process (``os.sched_getaffinity``, so ``taskset`` counts), each with its share of
the cores as intra-op threads.

Worker threads carry an OS-level name (``mocapd-detect``) that onnxruntime's own threads inherit, so per-thread
CPU accounting (``mocapd bench latency``) sees the detector's whole cost; they inherit the workers' nice value the
same way (``[daemon] detector_nice``, :mod:`mocapd.io.os_threads`).

With ``[detector] landmarks`` on, each session also holds a BlazePose landmark model
(:class:`~mocapd.pipeline.landmarks.LandmarkRunner`, the session's intra-op threads; its interpreters are made on
the worker thread at first use): the people YOLO found get their 33 landmarks as keypoints
(:meth:`DetectorConfig.output_format` is then ``blazepose33``). With "auto" each session holds an
:class:`~mocapd.pipeline.landmark_auto.AutoLandmarks` that picks the model (or none) per pass from the measured
costs.
"""

from __future__ import annotations

import os
import queue
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np
from numpy.typing import NDArray

from mocapd.core.keypoints import keypoint_format
from mocapd.core.sorting import Detections2D
from mocapd.io import cpu_budget
from mocapd.io.os_threads import worker_thread_setup
from mocapd.pipeline.detection_mode import ModeChooser
from mocapd.pipeline.detector import OnnxPoseDetector
from mocapd.pipeline.detector_config import DetectorConfig
from mocapd.pipeline.hand_auto import AutoHands, HandFront, hand_stage
from mocapd.pipeline.hand_auto import front_status as hands_status
from mocapd.pipeline.hand_landmarks import HandRunner
from mocapd.pipeline.landmark_auto import LandmarkFront, front_status, landmark_front, mark
from mocapd.pipeline.packed_source import PackedDetectionGroup, Session
from mocapd.pipeline.packing import PackedDetector, detectors_from_config

THREAD_NAME = "mocapd-detect"


def detector_executor(workers: int = 1, nice: int = 0) -> ThreadPoolExecutor:
    """Worker threads named ``mocapd-detect``, in Python and at the OS level (:func:`worker_thread_setup`), ``nice``
    nicer than the caller: the threads onnxruntime and OpenVINO start from them carry the name and the nice value
    too, so per-thread CPU accounting sees the detector and the event loop's tick comes first."""
    return ThreadPoolExecutor(workers, thread_name_prefix=THREAD_NAME, initializer=worker_thread_setup,
                              initargs=(THREAD_NAME, nice))  # fmt: skip


def process_cores() -> int:
    """The cores this process may use, at least 1: its CPU affinity (``taskset`` counts), and no more than its
    cgroup's CPU quota allows (``--cpu-budget``, systemd ``CPUQuota=``): a detector session with two intra-op
    threads under a one-core quota spends the quota in half of each period, and the whole process, tick included,
    then waits out the other half."""
    try:
        cores = max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        cores = max(1, os.cpu_count() or 1)
    quota = cpu_budget.quota_cores()
    return cores if quota is None else max(1, min(cores, int(quota)))


def landmark_runner(cfg: DetectorConfig) -> LandmarkFront:
    """A session's landmark stage for ``[detector] landmarks`` (``cfg`` with concrete sessions): None, a model, or
    "auto"'s chooser; ModelError when a model was not fetched."""
    return landmark_front(cfg.landmarks, max(1, cfg.intra_op_threads))


def hand_runner(cfg: DetectorConfig, body: LandmarkFront = None) -> HandFront:
    """A session's hand stage when ``[detector] hands`` runs the model (``cfg`` with concrete sessions): the model
    ("on"), or "auto"'s per-pass choice over the session's ``body`` landmark stage (:mod:`mocapd.pipeline.hand_auto`);
    else None. ModelError when the model was not fetched."""
    if not cfg.hands_decision()[0]:
        return None
    runner = HandRunner(keypoint_format(cfg.body_format).keypoints, threads=max(1, cfg.intra_op_threads))
    return AutoHands(runner, body) if cfg.hands == "auto" else runner


def target_columns(cfg: DetectorConfig, target_names: Sequence[str]) -> NDArray[np.intp]:
    """Column of each track target's keypoint in the detector's output (the detector may output keypoints that have
    no target on the skeleton)."""
    fmt = keypoint_format(cfg.output_format)
    return np.array([fmt.index(n) for n in target_names], dtype=np.intp)


class PooledDetector:
    """RGB ring image in, people out: ``workers`` whole-frame onnxruntime sessions shared by the cameras.

    Parameters
    ----------
    cfg : DetectorConfig
    columns : array of int, optional
        Keypoint columns to keep, in the track targets' order (default: all).
    image_sizes : sequence of (width, height)
        The cameras' image sizes: their whole-frame inputs are made when the workers load
        (:meth:`OnnxPoseDetector.fit_to`).
    nice : int
        How much nicer than the caller the workers (and onnxruntime's threads) run, 0..19.
    """

    def __init__(
        self,
        cfg: DetectorConfig,
        columns: NDArray[np.intp] | None = None,
        image_sizes: Sequence[tuple[int, int]] = (),
        nice: int = 0,
    ) -> None:
        self._pool: queue.SimpleQueue[OnnxPoseDetector] = queue.SimpleQueue()
        self._columns = columns
        self._detectors: list[OnnxPoseDetector] = []
        cfg = cfg.with_sessions(process_cores(), len(image_sizes))
        assert isinstance(cfg.workers, int)
        self.intra_op_threads = cfg.intra_op_threads
        self.landmarks_asked = cfg.landmarks
        self.hands_asked, self.hands_decision = cfg.hands, cfg.hands_decision()
        self.executor = detector_executor(cfg.workers, nice)
        self._runners: dict[int, LandmarkFront] = {}
        self._hands: dict[int, HandFront] = {}
        for _ in range(cfg.workers):
            # Made in a worker thread: onnxruntime's threads inherit its name (see the module docstring).
            self._detectors.append(self.executor.submit(OnnxPoseDetector.from_config, cfg, image_sizes).result())
            body = self._runners[id(self._detectors[-1])] = landmark_runner(cfg)
            self._hands[id(self._detectors[-1])] = hand_runner(cfg, body)
            self._pool.put(self._detectors[-1])

    def __call__(self, rgb: NDArray[np.uint8]) -> Detections2D:
        det = self._pool.get()
        try:
            # The detector takes BGR (OpenCV's order); the ring holds RGB.
            image = np.asarray(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), np.uint8)
            t0 = time.perf_counter_ns()
            found = det.detect(image)
            t1 = time.perf_counter_ns()
            (people,) = mark(self._runners[id(det)], [image], [found], t1 - t0)
            body_ns = time.perf_counter_ns() - t1
            (people,) = hand_stage(self._hands[id(det)], [image], [people], None, t1 - t0, body_ns)
        finally:
            self._pool.put(det)
        kp = people.keypoints if self._columns is None else people.keypoints[:, self._columns]
        return Detections2D(kp[..., :2], kp[..., 2])

    def close(self) -> None:
        """Abort the inferences in flight and stop the workers (at once: nobody waits for their results)."""
        for det in self._detectors:
            det.terminate()
        self.executor.shutdown(wait=True, cancel_futures=True)


AnyDetector = PooledDetector | PackedDetectionGroup


def landmark_fronts(detector: object) -> list[LandmarkFront]:
    """The landmark stages of a detector's sessions (none for anything else): the governor's hook reaches them."""
    if isinstance(detector, PooledDetector):
        return list(detector._runners.values())
    if isinstance(detector, PackedDetectionGroup):
        return [s.landmarks for s in detector.sessions]
    return []


def make_detector(
    cfg: DetectorConfig,
    image_sizes: Sequence[tuple[int, int]],
    columns: NDArray[np.intp] | None = None,
    nice: int = 0,
) -> AnyDetector:
    """The cameras' detector (blocking: loads the model): one packed group for all cameras on one named worker
    thread when ``cfg.packing.enabled`` (with ``"auto"``, the group chooses packed or whole-frame passes by what
    they deliver, :class:`~mocapd.pipeline.detection_mode.ModeChooser`), else a pool of whole-frame workers.

    Parameters
    ----------
    image_sizes : sequence of (width, height)
        Every camera's image size, in camera index order.
    nice : int
        How much nicer than the caller the detector's threads run (``[daemon] detector_nice``), 0..19.
    """
    if not cfg.packing.enabled:
        return PooledDetector(cfg, columns, image_sizes, nice)
    cfg = cfg.with_sessions(process_cores(), len(image_sizes))
    assert isinstance(cfg.workers, int)
    executor = detector_executor(cfg.workers, nice)
    sizes = list(image_sizes)
    # Made on the named worker threads: onnxruntime's threads inherit their name (see the module docstring).
    pairs = [executor.submit(detectors_from_config, cfg, sizes).result() for _ in range(cfg.workers)]
    packer = PackedDetector(pairs[0][0], sizes, cfg.packing, canvas_detector=pairs[0][1])
    # Whole frames first: until the people are found every camera's ROI is its whole frame, which a whole pass runs
    # at the camera's aspect for the cost of a one-camera canvas; the per-pass cost then picks (ties keep the mode).
    chooser = ModeChooser(first="whole") if cfg.packing.enabled == "auto" else None
    fronts = [landmark_runner(cfg) for _ in pairs]
    sessions = [Session(w, c, f, hand_runner(cfg, f)) for (w, c), f in zip(pairs, fronts, strict=True)]
    return PackedDetectionGroup(
        packer, executor, columns, chooser=chooser, sessions=sessions, landmarks_asked=cfg.landmarks,
        hands=(cfg.hands, cfg.hands_decision()),
    )  # fmt: skip


def detector_status(detector: AnyDetector) -> dict[str, object]:
    """``/status`` section ``detector``: which execution provider and precision run (packed: also the canvas
    model's), so that a user who left ``providers = ["auto"]`` sees whether the GPU or the CPU took it."""
    if isinstance(detector, PooledDetector):
        marks = front_status(detector.landmarks_asked, list(detector._runners.values()))
        hands = hands_status(detector.hands_decision, detector.hands_asked, list(detector._hands.values()))
        return {"mode": "whole", "workers": len(detector._detectors), "intra_op_threads": detector.intra_op_threads,
                **detector._detectors[0].describe(), "landmarks": marks, "hands": hands}  # fmt: skip
    packer = detector.packer
    # With packing "auto" the group's chooser picks packed or whole passes; name the one it runs now.
    mode = detector.chooser.mode if detector.chooser is not None else "packed"
    out: dict[str, object] = {
        "mode": mode,
        "workers": len(detector.sessions),
        "intra_op_threads": packer.detector.intra_op_threads,
        **packer.detector.describe(),
    }
    if packer.canvas_detector is not packer.detector:
        out["canvas"] = packer.canvas_detector.describe()
    names = [detector.sources[c].name if c in detector.sources else str(c) for c in range(packer.n_cameras)]
    out["landmarks"] = front_status(detector.landmarks_asked, [s.landmarks for s in detector.sessions], names)
    out["hands"] = hands_status(detector.hands_decision, detector.hands_asked, [s.hands for s in detector.sessions])
    return out
