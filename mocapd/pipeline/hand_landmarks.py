"""Hand landmarks per person: the body's keypoints → one aligned 224 x 224 crop per visible hand → 21 keypoints per
hand in source pixels, appended to the person's keypoints (``[detector] hands``, issue 44).

The third stage of the keypoint front end, after YOLO's people and (optionally) BlazePose's landmarks: for each
person, :func:`mocapd.core.hand_roi.hand_rois` places a crop per hand from the body's keypoints (BlazePose's wrist,
index and pinky where the body set has them, the forearm with COCO-17), each crop is resampled with one
``cv2.warpAffine``, the crops of all hands, people and cameras of a call go to MediaPipe's hand landmark model
(``@mediapipe/hands``, :mod:`mocapd.io.hand_model_build`) on LiteRT, and
:func:`mocapd.core.hand_roi.decode_hands` maps the 21 points back. The hand is the body's: the left hand's crop was
placed from the left arm, whatever the model's handedness output says.

**Confidences.** The model has no per-point visibility: every point of a hand gets the model's hand-presence score.
A hand under :data:`MIN_HAND_CONFIDENCE` is dropped (all 21 points at confidence 0), as MediaPipe drops a hand whose
presence is under 0.5. The model's handedness output (the probability that the crop shows a right hand as an
unmirrored camera sees it; MediaPipe documents it for mirrored selfie images, where it reads the other way) can
scale it (``side_check``): a crop whose hand the model takes for the other one would be trusted less. Measured on
Demo_SinglePerson it does not pay: on these ~60 px hands the handedness is unreliable, and the check drops half of
the hands found for 0.4 px of held-out median (docs/detection.md), so it is off by default.

**Runtime: LiteRT**, as for the body landmarks (:mod:`mocapd.pipeline.landmarks` measured it twice as fast as
onnxruntime on a tf2onnx conversion; the hand model is the same kind of small convolutional network).
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from mocapd.core.hand_roi import HAND_INPUT_SIZE, N_HAND, decode_hands, hand_roi_from_hand, hand_rois
from mocapd.core.keypoints import HAND_SIDES
from mocapd.core.landmark_roi import LandmarkRoi
from mocapd.core.pose2d import PoseDetections
from mocapd.errors import ModelError
from mocapd.io.hand_model_build import VARIANTS, hand_model_is_current
from mocapd.io.model_cache import hand_model_path
from mocapd.pipeline.landmarks import load_interpreter

FloatArray = NDArray[np.float64]
Image = NDArray[np.uint8]

MIN_HAND_CONFIDENCE = 0.5
"""A hand whose presence x side agreement is under this is dropped (confidence 0 on all its points)."""
RATE_WINDOW_S = 5.0
"""``/status`` rates are over the last this many seconds."""


class HandRates:
    """Per camera, what the hand stage saw over the last :data:`RATE_WINDOW_S` seconds (``/status``).

    Parameters
    ----------
    clock : callable returning float seconds
    """

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self.clock = clock
        self._events: dict[int, deque[tuple[float, int, int, int]]] = {}
        self._lock = threading.Lock()

    def record(self, camera: int, people: int, crops: int, found: int) -> None:
        """One image of ``camera``: ``people`` people, ``crops`` hand crops placed, ``found`` hands found."""
        now = self.clock()
        with self._lock:
            q = self._events.setdefault(camera, deque())
            q.append((now, people, crops, found))
            while q and q[0][0] < now - RATE_WINDOW_S:
                q.popleft()

    def totals(self) -> dict[int, tuple[int, int, int, int]]:
        """Per camera (-1: images whose camera the caller did not say), over the last :data:`RATE_WINDOW_S`
        seconds: images, people, hand crops placed, hands found."""
        now = self.clock()
        out: dict[int, tuple[int, int, int, int]] = {}
        with self._lock:
            for cam, q in self._events.items():
                recent = [e for e in q if e[0] >= now - RATE_WINDOW_S]
                out[cam] = (
                    len(recent),
                    sum(e[1] for e in recent),
                    sum(e[2] for e in recent),
                    sum(e[3] for e in recent),
                )
        return out


def rates_status(rates: Sequence[HandRates]) -> dict[str, dict[str, float]]:
    """Per camera, summed over ``rates`` (one per session: each sees some of a camera's images): images, hand crops
    and hands found per second, and hands found per person seen (0..2)."""
    sums: dict[int, list[int]] = {}
    for r in rates:
        for cam, row in r.totals().items():
            acc = sums.setdefault(cam, [0, 0, 0, 0])
            for k, v in enumerate(row):
                acc[k] += v
    return {
        str(cam): {
            "images_hz": round(images / RATE_WINDOW_S, 2),
            "crops_hz": round(crops / RATE_WINDOW_S, 2),
            "hands_hz": round(found / RATE_WINDOW_S, 2),
            "hands_per_person": round(found / people, 3) if people else 0.0,
        }
        for cam, (images, people, crops, found) in sorted(sums.items())
    }


class HandRunner:
    """The hand landmark model on crops placed from people's body keypoints; not thread-safe (one per worker).

    Parameters
    ----------
    body_names : tuple of str
        The body keypoint set's names (``coco17`` or ``blazepose33``), in the detector's output order.
    variant : str
        ``"full"`` or ``"lite"``.
    threads : int
        LiteRT's CPU threads.
    path : Path, optional
        The .tflite file (default: the cache's, checked against its pinned sha256).
    batch : int
        Crops per model call (1..16; the last chunk of a call padded).
    side_check : bool
        Scale each hand's confidence by the model's agreement with the body's side (see the module docstring);
        False (default): the presence score alone.
    refine : bool
        Run each found hand a second time on the crop its own points place
        (:func:`~mocapd.core.hand_roi.hand_roi_from_hand`, MediaPipe's tracking crop): twice the cost.
    """

    def __init__(
        self,
        body_names: tuple[str, ...],
        variant: str = "full",
        *,
        threads: int = 2,
        path: Path | None = None,
        batch: int = 1,
        side_check: bool = False,
        refine: bool = False,
    ) -> None:
        if not 1 <= batch <= 16:
            raise ModelError(f"hand landmark batch must be in 1..16, got {batch}")
        if variant not in VARIANTS:
            raise ModelError(f"unknown hand landmark model {variant!r}; known: {list(VARIANTS)}")
        if path is None:
            path = hand_model_path(variant)
            if not hand_model_is_current(path, variant):
                raise ModelError(
                    f"{path} not found or not the pinned model: run `mocapd model fetch --hands` "
                    "(setup/steps/32-hand-landmarks.sh does it at set-up)"
                )
        self.body_names = body_names
        self.variant = variant
        self.path = path
        self.threads = threads
        self.batch = batch
        self.side_check = side_check
        self.refine = refine
        self._interpreter: Any = None  # made at first use, on the calling (worker) thread
        self._lock = threading.Lock()
        self.crops_run = 0
        self.hands_found = 0
        self.rates = HandRates()

    def _loaded(self) -> Any:
        if self._interpreter is None:
            it = load_interpreter(self.path, self.threads)
            if self.batch != 1:
                shape = [self.batch, HAND_INPUT_SIZE, HAND_INPUT_SIZE, 3]
                it.resize_tensor_input(it.get_input_details()[0]["index"], shape)
            it.allocate_tensors()
            self._interpreter = it
        return self._interpreter

    def infer(self, crops: NDArray[np.float32]) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float32]]:
        """The model's outputs for ``crops``, shape (n, 224, 224, 3) RGB in [0, 1]: landmarks (n, 63) in crop pixels,
        hand presence (n,) and handedness (n,) (probability of a right hand, unmirrored image), both in [0, 1]."""
        n = len(crops)
        marks, presence, handed = np.empty((n, 63), np.float32), np.empty(n, np.float32), np.empty(n, np.float32)
        with self._lock:
            it = self._loaded()
            x_index = it.get_input_details()[0]["index"]
            # Outputs by shape and order: landmarks (63) first, then presence and handedness (1 each), then the
            # world landmarks (63) (MediaPipe's hand_landmark_cpu SplitTensorVectorCalculator ranges).
            outs = [d["index"] for d in it.get_output_details()]
            for start in range(0, n, self.batch):
                part = crops[start : start + self.batch]
                chunk = np.zeros((self.batch, HAND_INPUT_SIZE, HAND_INPUT_SIZE, 3), np.float32)
                chunk[: len(part)] = part
                it.set_tensor(x_index, chunk)
                it.invoke()
                stop = start + len(part)
                marks[start:stop] = it.get_tensor(outs[0]).reshape(self.batch, -1)[: len(part)]
                presence[start:stop] = it.get_tensor(outs[1]).reshape(-1)[: len(part)]
                handed[start:stop] = it.get_tensor(outs[2]).reshape(-1)[: len(part)]
                self.crops_run += len(part)
        return marks, presence, handed

    def run_rois(self, images: Sequence[Image], rois: Sequence[LandmarkRoi], sides: Sequence[int]) -> FloatArray:
        """One hand per crop: ``rois[i]`` of ``images[i]``, the hand of side ``sides[i]`` (0 left, 1 right).

        Returns
        -------
        array, shape (n, 21, 3)
            x, y (source pixels) and confidence (presence x agreement with the side; not thresholded).
        """
        if not rois:
            return np.zeros((0, N_HAND, 3))
        hands = self._once(images, rois, sides)
        if self.refine:
            again = [(i, hand_roi_from_hand(h)) for i, h in enumerate(hands) if h[0, 2] >= MIN_HAND_CONFIDENCE]
            todo = [(i, r) for i, r in again if r is not None]
            if todo:
                second = self._once([images[i] for i, _ in todo], [r for _, r in todo], [sides[i] for i, _ in todo])
                hands[[i for i, _ in todo]] = second
        return hands

    def _once(self, images: Sequence[Image], rois: Sequence[LandmarkRoi], sides: Sequence[int]) -> FloatArray:
        marks, presence, handed = self.infer(np.stack([crop_hand(im, r) for im, r in zip(images, rois, strict=True)]))
        agree = np.where(np.asarray(sides) == 1, handed, 1.0 - handed) if self.side_check else 1.0
        return decode_hands(marks, presence * agree, list(rois))

    def run(
        self, images: Sequence[Image], people: Sequence[FloatArray], cameras: Sequence[int] | None = None
    ) -> list[FloatArray]:
        """Both hands of every person of every image, the crops of all images in one call sequence.

        Parameters
        ----------
        images : sequence of uint8 array, shape (H, W, 3), BGR
        people : sequence of array, shape (n_i, K, 3)
            Each image's people as body keypoints of :attr:`body_names` (source pixels, confidence).
        cameras : sequence of int, optional
            Each image's camera, for :attr:`rates` (default: -1, not said).

        Returns
        -------
        list of array, shape (n_i, 42, 3)
            Per image, each person's left hand's 21 points then the right hand's (x, y source pixels, confidence);
            zeros for a hand without a crop or below :data:`MIN_HAND_CONFIDENCE`.
        """
        rois = [[hand_rois(kp, self.body_names) for kp in p] for p in people]
        placed = [(i, j, s, r) for i, p in enumerate(rois) for j, hs in enumerate(p) for s, r in enumerate(hs) if r]
        decoded = self.run_rois([images[i] for i, *_ in placed], [r for *_, r in placed], [s for *_, s, _ in placed])
        out = [np.zeros((len(p), len(HAND_SIDES) * N_HAND, 3)) for p in people]
        crops, found = [0] * len(people), [0] * len(people)
        for (i, j, s, _), hand in zip(placed, decoded, strict=True):
            crops[i] += 1
            if hand[0, 2] >= MIN_HAND_CONFIDENCE:
                out[i][j, s * N_HAND : (s + 1) * N_HAND] = hand
                found[i] += 1
        self.hands_found += sum(found)
        for i, p in enumerate(people):
            self.rates.record(-1 if cameras is None else cameras[i], len(p), crops[i], found[i])
        return out


def with_hand_landmarks(
    runner: HandRunner | None,
    images: Sequence[Image],
    people: Sequence[PoseDetections],
    cameras: Sequence[int] | None = None,
) -> list[PoseDetections]:
    """Each image's people with both hands' 42 keypoints after their body keypoints (boxes, scores and body
    keypoints kept as they are), all images' crops together; ``people`` unchanged when ``runner`` is None."""
    if runner is None:
        return list(people)
    found = runner.run(images, [p.keypoints for p in people], cameras)
    return [
        PoseDetections(p.boxes, p.scores, np.concatenate([p.keypoints, h], axis=1))
        for p, h in zip(people, found, strict=True)
    ]


def hand_status(decision: tuple[bool, str], asked: str, runners: Sequence[HandRunner | None]) -> dict[str, object]:
    """``/status`` ``detector.hands``: what ``[detector] hands`` asked for, whether the hand model runs and why, and
    what the sessions' ``runners`` did (crops and hands so far, rates per camera over the last seconds)."""
    running = [r for r in runners if r is not None]
    out: dict[str, object] = {"asked": asked, "running": "on" if decision[0] else "off", "why": decision[1]}
    if running:
        out["model"] = running[0].variant
        out["crops"] = sum(r.crops_run for r in running)
        out["hands_found"] = sum(r.hands_found for r in running)
        out["cameras"] = rates_status([r.rates for r in running])
    return out


def crop_hand(image: Image, roi: LandmarkRoi) -> NDArray[np.float32]:
    """The hand model's input for ``roi``: shape (224, 224, 3), RGB in [0, 1] (MediaPipe's ``ImageToTensor`` with
    ``output_tensor_float_range`` 0..1, border pixels repeated)."""
    patch = cv2.warpAffine(
        image,
        roi.sampling_matrix(HAND_INPUT_SIZE),
        (HAND_INPUT_SIZE, HAND_INPUT_SIZE),
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_REPLICATE,
    )
    rgb = cv2.cvtColor(patch, cv2.COLOR_BGR2RGB)
    return np.asarray(rgb, dtype=np.float32) * np.float32(1.0 / 255.0)
