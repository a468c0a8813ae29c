"""BlazePose landmarks per person: YOLO's people → aligned 256 x 256 crops → 33 keypoints in source pixels.

The second stage of the keypoint front end (``[detector] landmarks``, issue 40): for each person YOLO found, the
crop :func:`mocapd.core.landmark_roi.roi_from_coco17` places (mid-hip centre, upright, MediaPipe's enlargement) is
resampled with one ``cv2.warpAffine``, the crops of all people (and of all the cameras of a call) go to the model
together (in batches of ``batch``), and :func:`mocapd.core.landmark_roi.decode_landmarks` maps the landmarks back
with their confidences. A person whose hips or shoulders YOLO did not see gets no crop: their row is all zeros
(confidence 0).

**Runtime: LiteRT, not onnxruntime.** The models are the .tflite files of ``@mediapipe/pose``
(:mod:`mocapd.io.landmark_build`). Both ways were measured on the same crops (one 256 x 256 input, 2 threads,
median of 6 runs after 2 warm-up, three interleaved rounds, ``nice -n 19``, load 11-13 on the 2-core
"Intel(R) Xeon(R) Processor" shared by eight engineers, 2026-11-29): ``ai-edge-litert`` 2.3.0 (XNNPACK) ran
*full* in 68-107 ms and *heavy* in 259-272 ms; onnxruntime 1.32.0 on the tf2onnx 1.17 / tensorflow-cpu 2.21
conversion (opset 17, landmarks within 0.003 crop px of LiteRT's) took 220-275 and 528-599 ms. The issue's own
numbers on a quieter 2-core machine agree (heavy 49-60 against 96-128 ms, full 16-19 against 28-42). So LiteRT
runs them: about twice as fast, the shipped file as it is (no conversion step, no tensorflow at set-up), at the
cost of one runtime dependency.

**Batches.** The crops of all people and cameras of a call go to the model together, ``batch`` at a time (the last
chunk padded, so one interpreter serves every call: each holds its own packed weights and arena, heavy ~120 MB at
batch 1, ~140 MB at 4, ~190 MB at 8, measured RSS). LiteRT runs a batch of 4 crops for what 4 single crops cost on
this CPU (61 against 64 ms per crop, full), so the default is 1; a runtime where batches pay (a GPU delegate) would
raise it.

MediaPipe refines the landmarks on the model's 64 x 64 heatmap (``RefineLandmarksFromHeatmapCalculator``); that
step is not done here.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from mocapd.core.landmark_roi import INPUT_SIZE, N_LANDMARKS, LandmarkRoi, decode_landmarks, roi_from_coco17
from mocapd.core.pose2d import PoseDetections
from mocapd.errors import ModelError
from mocapd.io.landmark_build import VARIANTS, landmark_model_is_current
from mocapd.io.model_cache import landmark_model_path

FloatArray = NDArray[np.float64]
Image = NDArray[np.uint8]


def load_interpreter(path: Path, threads: int) -> Any:
    """A LiteRT interpreter on ``path``, or ModelError naming what failed."""
    try:
        from ai_edge_litert.interpreter import Interpreter
    except ImportError as exc:
        raise ModelError(f"[detector] landmarks needs the PyPI package ai-edge-litert ({exc})") from None
    try:
        return Interpreter(model_path=str(path), num_threads=threads)
    except (ValueError, RuntimeError) as exc:
        raise ModelError(f"{path}: LiteRT cannot load it ({exc})") from None


@dataclass(frozen=True)
class PersonLandmarks:
    """Landmarks of the people of one image.

    Attributes
    ----------
    keypoints : array, shape (n, 33, 3)
        x, y (source pixels) and confidence in [0, 1]; zeros for a person without a crop.
    rois : list of (LandmarkRoi or None), length n
        Each person's crop (None: no hip or no shoulder seen).
    """

    keypoints: FloatArray
    rois: list[LandmarkRoi | None]


class LandmarkRunner:
    """One landmark model (``"full"`` or ``"heavy"``) on crops of people; not thread-safe (one per worker).

    Parameters
    ----------
    variant : str
        ``"full"`` or ``"heavy"``.
    threads : int
        LiteRT's CPU threads.
    path : Path, optional
        The .tflite file (default: the cache's, checked against its pinned sha256).
    batch : int
        Crops per model call (1..16; see the module docstring).
    """

    def __init__(self, variant: str = "full", *, threads: int = 2, path: Path | None = None, batch: int = 1) -> None:
        if not 1 <= batch <= 16:
            raise ModelError(f"landmark batch must be in 1..16, got {batch}")
        if variant not in VARIANTS:
            raise ModelError(f"unknown landmark model {variant!r}; known: {list(VARIANTS)}")
        if path is None:
            path = landmark_model_path(variant)
            if not landmark_model_is_current(path, variant):
                raise ModelError(
                    f"{path} not found or not the pinned model: run `mocapd model fetch --landmarks` "
                    "(setup/steps/31-landmarks.sh does it at set-up)"
                )
        self.variant = variant
        self.path = path
        self.threads = threads
        self.batch = batch
        self._interpreter: Any = None  # made at first use, on the calling (worker) thread
        self._lock = threading.Lock()
        self.crops_run = 0

    def _loaded(self) -> Any:
        if self._interpreter is None:
            it = load_interpreter(self.path, self.threads)
            if self.batch != 1:
                it.resize_tensor_input(it.get_input_details()[0]["index"], [self.batch, INPUT_SIZE, INPUT_SIZE, 3])
            it.allocate_tensors()
            self._interpreter = it
        return self._interpreter

    def infer(self, crops: NDArray[np.float32]) -> NDArray[np.float32]:
        """Raw landmark rows of ``crops``, shape (n, 256, 256, 3) RGB in [0, 1] → shape (n, 195)."""
        out = np.empty((len(crops), 195), dtype=np.float32)
        with self._lock:
            it = self._loaded()
            x_index, y_index = it.get_input_details()[0]["index"], it.get_output_details()[0]["index"]
            for start in range(0, len(crops), self.batch):
                part = crops[start : start + self.batch]
                chunk = np.zeros((self.batch, INPUT_SIZE, INPUT_SIZE, 3), np.float32)
                chunk[: len(part)] = part
                it.set_tensor(x_index, chunk)
                it.invoke()
                out[start : start + len(part)] = it.get_tensor(y_index).reshape(self.batch, -1)[: len(part)]
                self.crops_run += len(part)
        return out

    def run(self, images: Sequence[Image], people: Sequence[FloatArray]) -> list[PersonLandmarks]:
        """Landmarks of every person of every image, the crops of all images in one call sequence.

        Parameters
        ----------
        images : sequence of uint8 array, shape (H, W, 3), BGR
        people : sequence of array, shape (n_i, 17, 3)
            Each image's people as YOLO's COCO-17 keypoints (source pixels, confidence).
        """
        rois: list[list[LandmarkRoi | None]] = [[roi_from_coco17(kp) for kp in p] for p in people]
        crops = [crop(img, r) for img, rs in zip(images, rois, strict=True) for r in rs if r is not None]
        raw = self.infer(np.stack(crops)) if crops else np.zeros((0, 195), np.float32)
        placed = [r for rs in rois for r in rs if r is not None]
        decoded = decode_landmarks(raw, placed)
        out, k = [], 0
        for rs in rois:
            kp = np.zeros((len(rs), N_LANDMARKS, 3))
            for i, r in enumerate(rs):
                if r is not None:
                    kp[i] = decoded[k]
                    k += 1
            out.append(PersonLandmarks(kp, rs))
        return out


def with_landmarks(
    runner: LandmarkRunner | None, images: Sequence[Image], people: Sequence[PoseDetections]
) -> list[PoseDetections]:
    """Each image's people with their 33 BlazePose landmarks in place of YOLO's keypoints (boxes and scores kept),
    all images' crops together; ``people`` unchanged when ``runner`` is None."""
    if runner is None:
        return list(people)
    found = runner.run(images, [p.keypoints for p in people])
    return [PoseDetections(p.boxes, p.scores, lm.keypoints) for p, lm in zip(people, found, strict=True)]


def landmark_status(asked: str, runners: Sequence[LandmarkRunner | None]) -> dict[str, object]:
    """``/status`` ``detector.landmarks``: what ``[detector] landmarks`` asked for, what runs, and the crops the
    sessions' ``runners`` ran so far."""
    running = [r for r in runners if r is not None]
    out: dict[str, object] = {"asked": asked, "running": running[0].variant if running else "off"}
    if running:
        out["crops"] = sum(r.crops_run for r in running)
    return out


def crop(image: Image, roi: LandmarkRoi) -> NDArray[np.float32]:
    """The model's input for ``roi``: shape (256, 256, 3), RGB in [0, 1] (MediaPipe's ``ImageToTensorCalculator``
    with ``output_tensor_float_range`` 0..1; outside the image the border pixels repeat, its default)."""
    patch = cv2.warpAffine(
        image,
        roi.sampling_matrix(),
        (INPUT_SIZE, INPUT_SIZE),
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_REPLICATE,
    )
    rgb = cv2.cvtColor(patch, cv2.COLOR_BGR2RGB)
    return np.asarray(rgb, dtype=np.float32) * np.float32(1.0 / 255.0)
