"""Packed detection for free-running cameras: one detector pass over the newest frame of every camera.

:class:`~mocapd.pipeline.packing.PackedDetector` puts the regions around the people each camera saw last time
onto shared detector canvases (seed 000 §3.3.1), so a pass costs a canvas or two instead of one whole-frame
inference per camera. It wants one image per camera per pass; the daemon's cameras are not synchronised, so
:class:`PackedDetectionGroup` takes, when the worker is free, the newest frame of every camera that has a new one
(each camera's own capture time stamps its detections), and gives a camera without a new frame (down, or slower)
its previous image, whose detections are not delivered again.

Each camera keeps its own :class:`PackedKeypointSource` (so the daemon supervises, counts and reports cameras
one by one); a source waiting for detections joins the group's pass in flight, or starts one. A pass's results
wait in the group until their camera's source collects them (a newer pass's result replaces an uncollected one).
"""

from __future__ import annotations

import asyncio
from concurrent.futures import Executor
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from mocapd.core.pose2d import PoseDetections
from mocapd.core.sorting import Detections2D
from mocapd.pipeline.frame_ring import FrameRef
from mocapd.pipeline.keypoint_source import DetectorKeypointSource
from mocapd.pipeline.packing import PackedDetector

Image = NDArray[np.uint8]


def to_detections2d(people: PoseDetections, columns: NDArray[np.intp] | None = None) -> Detections2D:
    """Detector output (boxes, scores, keypoints (n, K, 3)) → the sorter's 2D people (only ``columns`` of the K
    keypoints when given: those with a track target, in the targets' order)."""
    kp = people.keypoints if columns is None else people.keypoints[:, columns]
    return Detections2D(kp[..., :2], kp[..., 2])


class PackedDetectionGroup:
    """The cameras detected together by one :class:`PackedDetector` on one worker.

    Parameters
    ----------
    packer : PackedDetector
        Its ``image_sizes`` are the cameras' (in camera index order).
    executor : Executor
        One worker thread (the packer keeps per-camera ROI state between passes).
    columns : array of int, optional
        Keypoint columns to deliver (see :func:`to_detections2d`).
    """

    def __init__(self, packer: PackedDetector, executor: Executor, columns: NDArray[np.intp] | None = None) -> None:
        self.packer = packer
        self.executor = executor
        self.columns = columns
        self.sources: dict[int, PackedKeypointSource] = {}
        self.passes = 0
        self.replaced = 0  # results a newer pass overwrote before their camera collected them
        self._images: list[Image | None] = [None] * packer.n_cameras
        self._results: dict[int, tuple[FrameRef, Detections2D]] = {}
        self._pass: asyncio.Future[None] | None = None

    def add(self, source: PackedKeypointSource) -> None:
        self.sources[source.camera] = source

    async def join(self, camera: int) -> tuple[FrameRef, Detections2D] | None:
        """This camera's newest detections: collected from a finished pass, or from the pass in flight / a new
        one (None if that pass had no new frame of it)."""
        if camera not in self._results:
            if self._pass is None or self._pass.done():
                self._pass = asyncio.get_running_loop().run_in_executor(self.executor, self._run_pass)
            await asyncio.shield(self._pass)  # a source cancelled meanwhile must not cancel the others' pass
        return self._results.pop(camera, None)

    def _run_pass(self) -> None:
        new: dict[int, FrameRef] = {}
        for cam, source in self.sources.items():
            got = source.take_newest()
            if got is not None:
                new[cam] = got[0]
                self._images[cam] = np.asarray(cv2.cvtColor(got[1], cv2.COLOR_RGB2BGR), np.uint8)
        if not new:
            return
        images = []
        for cam, (w, h) in enumerate(self.packer.image_sizes):
            image = self._images[cam]
            images.append(image if image is not None else np.full((h, w, 3), 114, np.uint8))
        (found,) = self.packer.detect([images])
        self.passes += 1
        for cam, ref in new.items():
            if cam in self._results:
                self.replaced += 1
            self._results[cam] = (ref, to_detections2d(found[cam], self.columns))

    def close(self) -> None:
        """Abort the pass in flight and stop the worker (at once: nobody waits for its results)."""
        self.packer.detector.terminate()
        self.packer.canvas_detector.terminate()
        self.executor.shutdown(wait=True, cancel_futures=True)

    def status(self) -> dict[str, Any]:
        st = self.packer.stats
        return {"passes": self.passes, "canvases": st.canvases, "tiles": st.tiles, "replaced": self.replaced,
                "canvases_per_pass": round(st.canvases / self.passes, 2) if self.passes else None}  # fmt: skip


class PackedKeypointSource(DetectorKeypointSource):
    """One camera of a :class:`PackedDetectionGroup`: captures like :class:`DetectorKeypointSource`, detects
    through the group's shared passes."""

    def __init__(self, camera: int, frames: Any, group: PackedDetectionGroup, **kw: Any) -> None:
        super().__init__(camera, frames, _never, executor=group.executor, **kw)
        self.group = group
        group.add(self)

    async def _detection(self, loop: asyncio.AbstractEventLoop) -> tuple[FrameRef, Detections2D] | None:
        return await self.group.join(self.camera)

    def status(self) -> dict[str, Any]:
        out = super().status()
        out["kind"] = "packed detector"
        out["packing"] = self.group.status()
        return out


def _never(_image: Image) -> Detections2D:
    raise AssertionError("a packed source detects through its group")  # pragma: no cover
