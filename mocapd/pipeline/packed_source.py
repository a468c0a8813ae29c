"""Packed detection for free-running cameras: one detector pass over the newest frame of every camera.

:class:`~mocapd.pipeline.packing.PackedDetector` puts the regions around the people each camera saw last time
onto shared detector canvases (seed 000 §3.3.1), so a pass costs a canvas or two instead of one whole-frame
inference per camera. It wants one image per camera per pass; the daemon's cameras are not synchronised, so
:class:`PackedDetectionGroup` takes, when the worker is free, the newest frame of every camera that has a new one
(each camera's own capture time stamps its detections), and gives a camera without a new frame (down, or slower)
its previous image, whose detections are not delivered again. The worker starts the next pass itself as soon as
one ends and a camera has an unseen frame, and may run whole-frame passes instead where they deliver more
(:mod:`mocapd.pipeline.detection_mode`).

Each camera keeps its own :class:`PackedKeypointSource` (so the daemon supervises, counts and reports cameras
one by one); a source's captured frames wake the group's worker, and its detections wait in the group until the
source collects them (a newer pass's result replaces an uncollected one).
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections.abc import Callable
from concurrent.futures import Executor, Future
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from mocapd.core.pose2d import PoseDetections
from mocapd.core.sorting import Detections2D
from mocapd.pipeline.detection_mode import ModeChooser
from mocapd.pipeline.frame_ring import FrameRef
from mocapd.pipeline.keypoint_source import DetectorKeypointSource
from mocapd.pipeline.packing import PackedDetector

Image = NDArray[np.uint8]
log = logging.getLogger(__name__)


def to_detections2d(people: PoseDetections, columns: NDArray[np.intp] | None = None) -> Detections2D:
    """Detector output (boxes, scores, keypoints (n, K, 3)) → the sorter's 2D people (only ``columns`` of the K
    keypoints when given: those with a track target, in the targets' order)."""
    kp = people.keypoints if columns is None else people.keypoints[:, columns]
    return Detections2D(kp[..., :2], kp[..., 2])


class PackedDetectionGroup:
    """The cameras detected by one :class:`PackedDetector` on one worker thread that never idles.

    The worker loops on its own thread: as soon as a pass ends it starts the next one if any camera has a frame
    it has not detected yet (waiting on the event loop to start a pass would leave the detector idle while the
    loop solves a tick), and otherwise sleeps until a camera captures one. Results go to the event loop with
    ``call_soon_threadsafe``; each camera keeps its newest uncollected result (a newer one replaces it, counted).

    With a :class:`~mocapd.pipeline.detection_mode.ModeChooser` (``[detector.packing] enabled = "auto"``) each
    pass is either packed (the newest frames of the cameras that share a canvas, see :meth:`_packed_pass`) or
    whole-frame (the newest frame of the camera whose detection is oldest, letterboxed alone), whichever delivered more
    frames with people per second of detector time on this rig; without one, every pass is packed.

    Parameters
    ----------
    packer : PackedDetector
        Its ``image_sizes`` are the cameras' (in camera index order).
    executor : Executor
        One worker thread (the packer keeps per-camera ROI state between passes); the group's loop occupies it.
    columns : array of int, optional
        Keypoint columns to deliver (see :func:`to_detections2d`).
    chooser : ModeChooser, optional
        Chooses the mode of each pass (None: always packed).
    clock : callable returning int ns
        Measures each pass's detector time (for the chooser and /status).
    """

    def __init__(
        self,
        packer: PackedDetector,
        executor: Executor,
        columns: NDArray[np.intp] | None = None,
        *,
        chooser: ModeChooser | None = None,
        clock: Callable[[], int] = time.perf_counter_ns,
    ) -> None:
        self.packer = packer
        self.executor = executor
        self.columns = columns
        self.chooser = chooser
        self.clock = clock
        self.sources: dict[int, PackedKeypointSource] = {}
        self.passes = 0
        self.whole_passes = 0
        self.failed_passes = 0
        self.replaced = 0  # results a newer pass overwrote before their camera collected them
        self.busy_ns = 0
        self._images: list[Image | None] = [None] * packer.n_cameras
        self._detected_at: list[int] = [0] * packer.n_cameras  # pass number of each camera's last detection
        self._results: dict[int, tuple[FrameRef, Detections2D]] = {}
        self._ready: dict[int, asyncio.Event] = {}
        self._wake = threading.Event()
        self._stop = False
        self._loop: asyncio.AbstractEventLoop | None = None
        self._worker: Future[None] | None = None

    def add(self, source: PackedKeypointSource) -> None:
        self.sources[source.camera] = source

    def poke(self) -> None:
        """A camera captured a frame (on the event loop): wake the worker, starting it the first time."""
        if self._worker is None and not self._stop:
            self._loop = asyncio.get_running_loop()
            self._worker = self.executor.submit(self._work)
        self._wake.set()

    async def join(self, camera: int) -> tuple[FrameRef, Detections2D] | None:
        """This camera's next detections (waits for the worker to deliver them)."""
        ready = self._ready.setdefault(camera, asyncio.Event())
        await ready.wait()
        ready.clear()
        return self._results.pop(camera, None)

    def _deliver(self, found: dict[int, tuple[FrameRef, Detections2D]]) -> None:
        """On the event loop: hand a pass's results to their cameras."""
        for cam, result in found.items():
            if cam in self._results:
                self.replaced += 1
            self._results[cam] = result
            self._ready.setdefault(cam, asyncio.Event()).set()

    def _work(self) -> None:
        """The worker thread's loop: a pass whenever a camera has an unseen frame, until :meth:`close`."""
        while not self._stop:
            self._wake.wait()
            self._wake.clear()
            if self._stop:
                break
            try:
                found = self._run_pass()
            except Exception:
                if self._stop:  # terminate() aborts the inference in flight: that is how a pass ends at close
                    break
                self.failed_passes += 1
                log.exception("detection pass failed")
                continue
            if found is None:
                continue
            self._wake.set()  # frames captured during the pass are unseen: run again without waiting for a poke
            loop = self._loop
            if found and loop is not None and not loop.is_closed():
                loop.call_soon_threadsafe(self._deliver, found)

    def _run_pass(self) -> dict[int, tuple[FrameRef, Detections2D]] | None:
        """One pass in the chosen mode; None when no camera had an unseen frame."""
        mode = self.chooser.mode if self.chooser is not None else "packed"
        t0 = self.clock()
        found = self._whole_pass() if mode == "whole" else self._packed_pass()
        if found is None:
            return None
        busy = self.clock() - t0
        self.busy_ns += busy
        self.passes += 1
        for cam in found:
            self._detected_at[cam] = self.passes
        if self.chooser is not None:
            usable = sum(1 for _, d in found.values() if len(d) > 0)
            self.chooser.record(mode, usable, len(found), busy)
        return found

    def _packed_pass(self) -> dict[int, tuple[FrameRef, Detections2D]] | None:
        """One canvas's worth of cameras: those with an unseen frame, detected longest ago first, as many as
        share the canvases the first one needs. A pass over every camera would deliver each camera's detections
        only after all canvases ran, and make every camera wait that long again for its next frame; passes of one
        canvas each deliver as they go (the same inferences, a shorter detection delay).

        With a batched detector (a GPU: ``[detector] batch``) a pass takes every camera with an unseen frame
        instead: its canvases run in one inference that costs little more than one canvas (1.25-1.8 ms each in a
        batch of 4 against 5.5 ms alone on the H100), and one-canvas passes there ran 1.1 canvases a pass at ~20 ms,
        mostly the pass's own Python work, so live detection reached 0.32 of the detector alone (docs/daemon.md,
        "Issue 15: on a GPU"). Not measured live on a GPU since (no device lent)."""
        order = sorted(
            (c for c, src in self.sources.items() if src.has_new_frame()), key=lambda c: self._detected_at[c]
        )
        if not order:
            return None
        chosen = order if self.packer.canvas_detector.batched else self._one_canvas(order)
        new: dict[int, FrameRef] = {}
        for cam in chosen:
            got = self.sources[cam].take_newest()
            if got is not None:
                new[cam] = got[0]
                self._images[cam] = np.asarray(cv2.cvtColor(got[1], cv2.COLOR_RGB2BGR), np.uint8)
        if not new:
            return None
        images = []
        for cam, (w, h) in enumerate(self.packer.image_sizes):
            image = self._images[cam]
            images.append(image if image is not None and cam in new else np.empty((h, w, 3), np.uint8))
        (found,) = self.packer.detect([images], cameras=sorted(new))
        return {cam: (ref, to_detections2d(found[cam], self.columns)) for cam, ref in new.items()}

    def _one_canvas(self, order: list[int]) -> list[int]:
        """The cameras of one canvas: ``order``'s first and those that share the canvases it needs."""
        # The cameras detected together last time first (then any other that still fits): the groups stay
        # stable, so every camera is detected at a steady interval (the latency covers the slowest, its p95).
        first = self._detected_at[order[0]]
        order = sorted(order, key=lambda c: (self._detected_at[c] != first, self._detected_at[c]))
        chosen = [order[0]]
        need = self.packer.canvases_for(chosen)
        for cam in order[1:]:
            if self.packer.canvases_for([*chosen, cam]) <= need:
                chosen.append(cam)
        return chosen

    def _whole_pass(self) -> dict[int, tuple[FrameRef, Detections2D]] | None:
        # The camera detected longest ago first: every camera gets its turn, none waits two rounds.
        for cam in sorted(self.sources, key=lambda c: self._detected_at[c]):
            got = self.sources[cam].take_newest()
            if got is None:
                continue
            image = np.asarray(cv2.cvtColor(got[1], cv2.COLOR_RGB2BGR), np.uint8)
            self._images[cam] = image
            people = self.packer.detector.detect(image)
            # Counted once done, like ``passes``: a pass aborted by close() is neither (packed = passes - whole).
            self.whole_passes += 1
            self.packer.seed_rois(cam, people)  # packed passes start from where the people are now
            return {cam: (got[0], to_detections2d(people, self.columns))}
        return None

    def close(self) -> None:
        """Abort the pass in flight and stop the worker (at once: nobody waits for its results)."""
        self._stop = True
        self._wake.set()
        self.packer.detector.terminate()
        self.packer.canvas_detector.terminate()
        self.executor.shutdown(wait=True, cancel_futures=True)

    def _inference_ns(self) -> int:
        whole, canvas = self.packer.detector, self.packer.canvas_detector
        return whole.inference_ns + (canvas.inference_ns if canvas is not whole else 0)

    def status(self) -> dict[str, Any]:
        st = self.packer.stats
        packed = self.passes - self.whole_passes
        out: dict[str, Any] = {
            "passes": self.passes, "packed_passes": packed, "whole_frame_passes": self.whole_passes,
            "failed_passes": self.failed_passes, "canvases": st.canvases, "tiles": st.tiles, "replaced": self.replaced,
            "canvases_per_pass": round(st.canvases / packed, 2) if packed else None,
            "detector_busy_s": round(self.busy_ns / 1e9, 2),
            # Of which inside onnxruntime: the rest of a pass (frame conversion, canvases, decoding) is mocapd's.
            "inference_s": round(self._inference_ns() / 1e9, 2),
        }  # fmt: skip
        out["mode"] = self.chooser.status() if self.chooser is not None else {"mode": "packed", "chosen": "packed"}
        return out


class PackedKeypointSource(DetectorKeypointSource):
    """One camera of a :class:`PackedDetectionGroup`: captures like :class:`DetectorKeypointSource`, detects
    through the group's shared passes."""

    def __init__(self, camera: int, frames: Any, group: PackedDetectionGroup, **kw: Any) -> None:
        super().__init__(camera, frames, _never, executor=group.executor, **kw)
        self.group = group
        group.add(self)

    def frame_arrived(self, ref: FrameRef) -> None:
        self.group.poke()

    async def _detection(self, loop: asyncio.AbstractEventLoop) -> tuple[FrameRef, Detections2D] | None:
        return await self.group.join(self.camera)

    def status(self) -> dict[str, Any]:
        out = super().status()
        out["kind"] = "packed detector"
        out["packing"] = self.group.status()
        return out


def _never(_image: Image) -> Detections2D:
    raise AssertionError("a packed source detects through its group")  # pragma: no cover
