"""Foreground mattes for the learned fusion's PVH (issue 30; seed 001 §3.2's occupancy channel).

Seed 001 takes a soft occupancy from the thresholded HSV distance of each frame to a clean plate. A live rig has no
guaranteed clean plate (people walk in before the start), so :class:`BackgroundMatte` uses OpenCV's adaptive
Gaussian-mixture subtractor (MOG2) at the PVH's reduced scale: it learns the background as it goes and marks
shadows apart (they count as half foreground). The binary mask is blurred into a soft probability.

:class:`MatteSource` is what :class:`~mocapd.pipeline.fusion.FusionStage` reads each learned frame: per camera, the
matte nearest the solve time. :class:`FrameMattes` builds them from camera frames as they are read;
``mocapd.sim.silhouettes.SyntheticMattes`` renders the synthetic rig's.
"""

from __future__ import annotations

import threading
from typing import Protocol

import cv2
import numpy as np
from numpy.typing import NDArray

from mocapd.pipeline.frame_ring import FrameRing

F32 = NDArray[np.float32]


class MatteSource(Protocol):
    """Per camera, the foreground matte (h, w) in [0, 1] at the PVH's scale nearest ``t_ns``, or None."""

    def mattes(self, t_ns: int) -> list[F32 | None]: ...


class BackgroundMatte:
    """One camera's background subtraction at ``1/scale`` resolution.

    Parameters
    ----------
    scale : the PVH's image scale (8: a 1920×1080 frame becomes 240×135).
    history : frames the mixture model remembers (MOG2's ``history``).
    var_threshold : MOG2's squared Mahalanobis threshold for foreground.
    blur_px : σ (reduced pixels) of the blur that makes the binary mask a soft probability.
    learning_rate : -1: MOG2's automatic rate (1 / frames seen, then 1 / history).
    """

    def __init__(
        self,
        scale: int = 8,
        history: int = 300,
        var_threshold: float = 16.0,
        blur_px: float = 0.8,
        learning_rate: float = -1.0,
    ) -> None:
        self.scale = scale
        self.blur_px = blur_px
        self.learning_rate = learning_rate
        self._mog = cv2.createBackgroundSubtractorMOG2(history=history, varThreshold=var_threshold, detectShadows=True)
        self.frames = 0

    def apply(self, image: NDArray[np.uint8]) -> F32:
        """The soft matte of one BGR (or grey) frame, shape ``ceil(h / scale), ceil(w / scale)``."""
        h, w = image.shape[:2]
        small = cv2.resize(image, (-(-w // self.scale), -(-h // self.scale)), interpolation=cv2.INTER_AREA)
        mask = self._mog.apply(small, learningRate=self.learning_rate)
        self.frames += 1
        # 255 foreground, 127 shadow, 0 background
        p = np.where(mask == 255, 1.0, np.where(mask > 0, 0.5, 0.0)).astype(np.float32)
        if self.blur_px > 0:
            p = np.asarray(cv2.GaussianBlur(p, (0, 0), self.blur_px), dtype=np.float32)
        return p


class FrameMattes:
    """A :class:`MatteSource` over cameras whose frames are handed in as they are read (:meth:`push`).

    Each camera keeps its latest mattes with their capture times; :meth:`mattes` gives the one nearest the solve
    time (within ``max_age_ns``, else None: the camera's matte channel sits that frame out). Thread-safe: frames are
    pushed from capture or detector threads, mattes are read by the scheduler.
    """

    def __init__(self, n_cameras: int, scale: int = 8, keep: int = 16, max_age_ns: int = 100_000_000) -> None:
        self.subtractors = [BackgroundMatte(scale) for _ in range(n_cameras)]
        self.max_age_ns = max_age_ns
        self._keep = keep
        self._mattes: list[list[tuple[int, F32]]] = [[] for _ in range(n_cameras)]
        self._lock = threading.Lock()

    def push(self, camera: int, capture_ns: int, image: NDArray[np.uint8]) -> None:
        """Subtract the background of one frame of ``camera`` captured at ``capture_ns`` (host clock)."""
        m = self.subtractors[camera].apply(image)
        with self._lock:
            buf = self._mattes[camera]
            buf.append((capture_ns, m))
            del buf[: -self._keep]

    def mattes(self, t_ns: int) -> list[F32 | None]:
        out: list[F32 | None] = []
        with self._lock:
            for buf in self._mattes:
                best = min(buf, key=lambda e: abs(e[0] - t_ns), default=None)
                out.append(best[1] if best is not None and abs(best[0] - t_ns) <= self.max_age_ns else None)
        return out


class RingMattes(FrameMattes):
    """:class:`FrameMattes` fed from the cameras' frame rings: :meth:`poll` takes each ring's newest frame (if it
    is new) through the background subtraction. The daemon polls at the learned stream's rate, off the event loop.

    Parameters
    ----------
    rings : one frame ring per camera of the rig, in camera order (None: a camera without frames, e.g. a camera
        host that sends keypoints only; its matte channel sits every hull out).
    """

    def __init__(self, rings: list[FrameRing | None], scale: int = 8, keep: int = 16) -> None:
        super().__init__(len(rings), scale, keep)
        self.rings = rings
        self._seen = [-1] * len(rings)

    def poll(self) -> int:
        """Subtract the background of every ring's newest frame not seen yet; returns how many frames."""
        done = 0
        for c, ring in enumerate(self.rings):
            if ring is None:
                continue
            ref = ring.latest()
            if ref is None or ref.seq == self._seen[c]:
                continue
            image = ring.read(ref.seq)
            if image is None:
                continue
            self._seen[c] = ref.seq
            self.push(c, ref.host_ns, image)
            done += 1
        return done
