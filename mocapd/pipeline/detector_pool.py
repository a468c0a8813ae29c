"""The detector the daemon's cameras share: whole-frame workers, or one packed pass over every camera.

:class:`PooledDetector` is the :data:`~mocapd.pipeline.keypoint_source.Detector` behind
:class:`~mocapd.pipeline.keypoint_source.DetectorKeypointSource`: one onnxruntime session per worker thread
(``[detector] workers``), handed out through a queue, the cameras taking turns. With ``[detector.packing]
enabled`` (true or "auto"), :func:`make_detector` builds a
:class:`~mocapd.pipeline.packed_source.PackedDetectionGroup` instead: the newest frame of every camera detected
together on shared canvases by one worker (with "auto", or alone where whole frames deliver more).

Worker threads carry an OS-level name (``mocapd-detect``) that onnxruntime's own threads inherit, so per-thread
CPU accounting (``mocapd bench latency``) sees the detector's whole cost.
"""

from __future__ import annotations

import ctypes
import queue
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np
from numpy.typing import NDArray

from mocapd.core.keypoints import keypoint_format
from mocapd.core.sorting import Detections2D
from mocapd.pipeline.detection_mode import ModeChooser
from mocapd.pipeline.detector import OnnxPoseDetector
from mocapd.pipeline.detector_config import DetectorConfig
from mocapd.pipeline.packed_source import PackedDetectionGroup
from mocapd.pipeline.packing import packed_detector_from_config

THREAD_NAME = "mocapd-detect"


def name_os_thread(name: str) -> None:
    """Give the calling thread an OS-level name (``/proc/.../comm``; Python's thread names stay in Python).

    Threads the named thread starts inherit the name (Linux), onnxruntime's intra-op pool included. A no-op where
    ``prctl`` is missing.
    """
    libc = ctypes.CDLL(None, use_errno=True)
    prctl = getattr(libc, "prctl", None)
    if prctl is not None:
        prctl(15, name.encode()[:15], 0, 0, 0)  # 15 = PR_SET_NAME


def detector_executor(workers: int = 1) -> ThreadPoolExecutor:
    """Worker threads named ``mocapd-detect``, in Python and at the OS level (:func:`name_os_thread`): the threads
    onnxruntime and OpenVINO start from them carry the name too, so per-thread CPU accounting sees the detector."""
    return ThreadPoolExecutor(workers, thread_name_prefix=THREAD_NAME, initializer=name_os_thread,
                              initargs=(THREAD_NAME,))  # fmt: skip


def target_columns(cfg: DetectorConfig, target_names: Sequence[str]) -> NDArray[np.intp]:
    """Column of each track target's keypoint in the model's output (the detector may output keypoints that have
    no target on the skeleton)."""
    fmt = keypoint_format(cfg.model.keypoint_format)
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
    """

    def __init__(
        self,
        cfg: DetectorConfig,
        columns: NDArray[np.intp] | None = None,
        image_sizes: Sequence[tuple[int, int]] = (),
    ) -> None:
        self._pool: queue.SimpleQueue[OnnxPoseDetector] = queue.SimpleQueue()
        self._columns = columns
        self._detectors: list[OnnxPoseDetector] = []
        self.executor = detector_executor(cfg.workers)
        for _ in range(cfg.workers):
            # Made in a worker thread: onnxruntime's threads inherit its name (see the module docstring).
            self._detectors.append(self.executor.submit(OnnxPoseDetector.from_config, cfg, image_sizes).result())
            self._pool.put(self._detectors[-1])

    def __call__(self, rgb: NDArray[np.uint8]) -> Detections2D:
        det = self._pool.get()
        try:
            # The detector takes BGR (OpenCV's order); the ring holds RGB.
            people = det.detect(np.asarray(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), np.uint8))
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


def make_detector(
    cfg: DetectorConfig, image_sizes: Sequence[tuple[int, int]], columns: NDArray[np.intp] | None = None
) -> AnyDetector:
    """The cameras' detector (blocking: loads the model): one packed group for all cameras on one named worker
    thread when ``cfg.packing.enabled`` (with ``"auto"``, the group chooses packed or whole-frame passes by what
    they deliver, :class:`~mocapd.pipeline.detection_mode.ModeChooser`), else a pool of whole-frame workers.

    Parameters
    ----------
    image_sizes : sequence of (width, height)
        Every camera's image size, in camera index order.
    """
    if not cfg.packing.enabled:
        return PooledDetector(cfg, columns, image_sizes)
    executor = detector_executor()
    packer = executor.submit(packed_detector_from_config, cfg, list(image_sizes)).result()
    # Whole frames first: their passes seed every camera's ROIs, so the first packed epoch is measured on the
    # people's regions rather than on the whole frames an empty start would pack (and warm-up, which slows
    # whichever runs first, then weighs against whole frames, re-checked 15 s later anyway).
    chooser = ModeChooser(first="whole") if cfg.packing.enabled == "auto" else None
    return PackedDetectionGroup(packer, executor, columns, chooser=chooser)


def detector_status(detector: AnyDetector) -> dict[str, object]:
    """``/status`` section ``detector``: which execution provider and precision run (packed: also the canvas
    model's), so that a user who left ``providers = ["auto"]`` sees whether the GPU or the CPU took it."""
    if isinstance(detector, PooledDetector):
        return {"mode": "whole", "workers": len(detector._detectors), **detector._detectors[0].describe()}
    packer = detector.packer
    # With packing "auto" the group's chooser picks packed or whole passes; name the one it runs now.
    mode = detector.chooser.mode if detector.chooser is not None else "packed"
    out: dict[str, object] = {"mode": mode, **packer.detector.describe()}
    if packer.canvas_detector is not packer.detector:
        out["canvas"] = packer.canvas_detector.describe()
    return out
