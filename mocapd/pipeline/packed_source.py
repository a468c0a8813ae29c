"""Packed detection for free-running cameras: detector passes over the newest frames of the cameras, on one or more
inference sessions at once.

:class:`~mocapd.pipeline.packing.PackedDetector` puts the regions around the people each camera saw last time
onto shared detector canvases (seed 000 §3.3.1), so a pass costs a canvas or two instead of one whole-frame
inference per camera. It wants one image per camera per pass; the daemon's cameras are not synchronised, so
:class:`PackedDetectionGroup` takes, when a worker is free, the newest frame of the cameras that have a new one
(each camera's own capture time stamps its detections), and gives a camera without a new frame (down, or slower)
its previous image, whose detections are not delivered again. A worker starts its next pass as soon as one ends
and a camera has an unseen frame; each pass is packed or one whole frame, whichever costs less per camera frame
(:mod:`mocapd.pipeline.detection_mode`).

Several sessions (``[detector] workers``): one worker thread per inference session, each with a share of the
cores' threads, each pass taking cameras no other pass in flight holds. One onnxruntime session of a network this
small is latency-bound and parallelises poorly inside (16 threads on a 16-core machine detected no more than 2 on
the 2-core laptop, issue 31), so throughput on more cores comes from passes in flight at once.

Each camera keeps its own :class:`PackedKeypointSource` (so the daemon supervises, counts and reports cameras
one by one); a source's captured frames wake the group's workers, and its detections wait in the group until the
source collects them (a newer pass's result replaces an uncollected one).
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Executor, Future
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from mocapd.core.pose2d import PoseDetections
from mocapd.core.sorting import Detections2D
from mocapd.io.loop_mailbox import LoopMailbox, loop_mailbox
from mocapd.pipeline.detection_mode import ModeChooser, PassCost
from mocapd.pipeline.detector import OnnxPoseDetector
from mocapd.pipeline.frame_ring import FrameRef
from mocapd.pipeline.hand_auto import HandFront, hand_stage
from mocapd.pipeline.keypoint_source import DetectorKeypointSource
from mocapd.pipeline.landmark_auto import LandmarkFront, mark
from mocapd.pipeline.packing import PackedDetector

Image = NDArray[np.uint8]
log = logging.getLogger(__name__)
#: the longest rest after a pass at a duty below 1 (see :meth:`PackedDetectionGroup._rest`)
MAX_REST_NS = 300_000_000
#: no rest at a duty below 1 while a camera went this long without a detection (see :meth:`PackedDetectionGroup._rest`)
STARVED_NS = 1_000_000_000


def to_detections2d(people: PoseDetections, columns: NDArray[np.intp] | None = None) -> Detections2D:
    """Detector output (boxes, scores, keypoints (n, K, 3)) → the sorter's 2D people (only ``columns`` of the K
    keypoints when given: those with a track target, in the targets' order)."""
    kp = people.keypoints if columns is None else people.keypoints[:, columns]
    return Detections2D(kp[..., :2], kp[..., 2])


@dataclass(frozen=True)
class Session:
    """One inference session of the group (one worker thread): its whole-frame detector and its canvas detector
    (the same object when the canvases are the model's own size), and its landmark model when ``[detector]
    landmarks`` runs one (the people's keypoints are then its 33 landmarks; with "auto", the chooser)."""

    whole: OnnxPoseDetector
    canvas: OnnxPoseDetector
    landmarks: LandmarkFront = None
    hands: HandFront = None
    """Its hand stage when ``[detector] hands`` runs the model (both hands' 42 keypoints after the body's): the model,
    or "auto"'s per-pass choice (:mod:`mocapd.pipeline.hand_auto`)."""


@dataclass(frozen=True)
class _Plan:
    mode: str
    cameras: tuple[int, ...]
    pixels: int


class PackedDetectionGroup:
    """The cameras detected by one :class:`PackedDetector` on worker threads that never idle.

    Each worker loops on its own thread with its own session: as soon as a pass ends it starts the next one if a
    camera no other pass holds has a frame it has not detected yet (waiting on the event loop to start a pass would
    leave the detector idle while the loop solves a tick), and otherwise sleeps until a camera captures one.
    Results go to the event loop through its :class:`~mocapd.io.loop_mailbox.LoopMailbox`; each camera keeps its
    newest uncollected result (a newer one replaces it, counted).

    With a :class:`~mocapd.pipeline.detection_mode.ModeChooser` (``[detector.packing] enabled = "auto"``) each
    pass is either packed (the newest frames of the cameras that share a canvas, see :meth:`_packed_pass`) or
    whole-frame (the newest frame of the camera whose detection is oldest, letterboxed alone), whichever is
    predicted to cost less detector time per camera frame; without one, every pass is packed.

    Parameters
    ----------
    packer : PackedDetector
        Its ``image_sizes`` are the cameras' (in camera index order).
    executor : Executor
        One worker thread per session (the group's loops occupy them).
    columns : array of int, optional
        Keypoint columns to deliver (see :func:`to_detections2d`).
    chooser : ModeChooser, optional
        Chooses the mode of each pass (None: always packed).
    clock : callable returning int ns
        Measures each pass's detector time (for the chooser and /status).
    sessions : sequence of Session, optional
        The inference sessions, one per worker (default: the packer's own detectors, one worker).
    landmarks_asked : str
        ``[detector] landmarks`` as configured (``/status``; the sessions' landmark models are what runs).
    hands : (str, (bool, str))
        ``[detector] hands`` as configured and :meth:`DetectorConfig.hands_decision` (``/status``).
    """

    def __init__(
        self,
        packer: PackedDetector,
        executor: Executor,
        columns: NDArray[np.intp] | None = None,
        *,
        chooser: ModeChooser | None = None,
        clock: Callable[[], int] = time.perf_counter_ns,
        sessions: Sequence[Session] = (),
        landmarks_asked: str = "off",
        hands: tuple[str, tuple[bool, str]] = ("off", (False, "detector.hands is off")),
    ) -> None:
        self.packer = packer
        self.landmarks_asked = landmarks_asked
        self.hands_asked, self.hands_decision = hands
        self.executor = executor
        self.columns = columns
        self.chooser = chooser
        self.clock = clock
        self.sessions = list(sessions) or [Session(packer.detector, packer.canvas_detector)]
        self.sources: dict[int, PackedKeypointSource] = {}
        self.passes = 0
        self.whole_passes = 0
        self.failed_passes = 0
        self.replaced = 0  # results a newer pass overwrote before their camera collected them
        self.busy_ns = 0
        self.in_flight_max = 0  # most passes that ran at once
        self._images: list[Image | None] = [None] * packer.n_cameras
        self._detected_at: list[int] = [0] * packer.n_cameras  # pass number of each camera's last detection
        self._results: dict[int, tuple[FrameRef, Detections2D]] = {}
        self._ready: dict[int, asyncio.Event] = {}
        self._cond = threading.Condition()
        self._held: set[int] = set()  # cameras of the passes in flight
        self._in_flight = 0
        self._stop = False
        self._mailbox: LoopMailbox | None = None  # the event loop's: results cross to it there
        self._workers: list[Future[None]] = []
        #: the share of wall time each worker may spend in passes (the governor's; 1: passes back to back). A
        #: worker rests ``pass × (1/duty − 1)`` after each pass: on a machine (or a CPU budget) too small for
        #: everything, the detector gives way before the output tick does.
        self.duty = 1.0
        self.max_rest_ns = MAX_REST_NS
        #: no rest while a camera's last detection is older than this (or it has none yet)
        self.starved_ns = STARVED_NS
        #: > 0: the passes paced instead of by :attr:`duty` (the governor's deepest steps): after a pass a worker
        #: rests until the camera detected longest ago is this far past its detection (:meth:`_paced_rest`)
        self.pace_ns = 0
        self.rested_ns = 0
        self.rests_skipped = 0
        self._detected_ns: dict[int, int] = {}  # per camera: when a pass last delivered its detections

    def add(self, source: PackedKeypointSource) -> None:
        self.sources[source.camera] = source

    def poke(self) -> None:
        """A camera captured a frame (on the event loop): wake the workers, starting them the first time."""
        if not self._workers and not self._stop:
            self._mailbox = loop_mailbox(asyncio.get_running_loop())
            self._workers = [self.executor.submit(self._work, i) for i in range(len(self.sessions))]
        with self._cond:
            self._cond.notify_all()

    async def join(self, camera: int) -> tuple[FrameRef, Detections2D] | None:
        """This camera's next detections (waits for a worker to deliver them)."""
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

    def _work(self, worker: int) -> None:
        """Worker ``worker``'s loop on its session: a pass whenever a camera no other pass holds has an unseen
        frame, until :meth:`close`."""
        while True:
            with self._cond:
                plan = None
                while not self._stop and (plan := self._claim(worker)) is None:
                    self._cond.wait()
                if self._stop or plan is None:
                    return
            failed = False
            t0 = self.clock()
            try:
                found = self._run_pass(plan, worker)
            except Exception:
                if self._stop:  # terminate() aborts the inference in flight: that is how a pass ends at close
                    return
                failed = True
                log.exception("detection pass failed")
                found = None
            finally:
                with self._cond:
                    self.failed_passes += failed
                    self._held.difference_update(plan.cameras)
                    self._in_flight -= 1
                    self._cond.notify_all()  # its cameras are free again, and more frames came meanwhile
            mailbox = self._mailbox
            done = self.clock()
            if found:
                for cam in found:
                    self._detected_ns[cam] = done
            if found and mailbox is not None:
                mailbox.post(self._deliver, found)  # dropped once the loop is closed
            self._rest(done - t0)

    def _rest(self, took_ns: int) -> None:
        """After a pass that took ``took_ns``: rest so that passes take at most :attr:`duty` of the time, but never
        longer than :attr:`max_rest_ns` (default :data:`MAX_REST_NS`); paced (:attr:`pace_ns`), see
        :meth:`_paced_rest`."""
        if self.pace_ns > 0:
            self._paced_rest()
            return
        duty = self.duty
        if duty >= 1.0 or took_ns <= 0:
            return
        now = self.clock()
        if any(now - self._detected_ns.get(cam, -(1 << 62)) > self.starved_ns for cam in self.sources):
            # A camera the detector has not reached for a second: its tracked people are ageing out
            # (``[detector.tracking] max_age_s``), and resting would let them go. The duty gives way.
            self.rests_skipped += 1
            return
        # Capped: a pass a starved detector takes a second for would rest 2 s at 35 % duty, and a camera's
        # detections that far apart age its tracked people out (``[detector.tracking] max_age_s``) -- they left
        # the solve and came back as new identities on the loaded 2-core camera demo.
        self._sleep(min(round(took_ns * (1.0 / max(duty, 0.05) - 1.0)), self.max_rest_ns))

    def _paced_rest(self) -> None:
        """Rest until the camera detected longest ago is :attr:`pace_ns` past its last detection (not at all while
        a camera has none yet, or is already that far past it: the starvation guard built in).

        Why not a lower duty: under a CPU budget of 0.4 of a core here (0.8 of one on the issue's slower CPU) a
        pass's wall time is mostly the quota's throttling, so the duty's rest, a multiple of that wall time, took
        no CPU away: at 20 % duty the detector still used 0.09 s/s and, with the guard at 1.6 s, detected each
        camera 0.9 times a second. Paced, a camera is detected once a pace whatever a pass's wall time, and on
        half-scale tiles (:attr:`PackedDetector.tile_ratio`) one pass takes the four cameras' people: 0.045 s/s at
        one detection a camera a second (docs/daemon.md, "The paced detector")."""
        now = self.clock()
        oldest = min((self._detected_ns.get(cam, -(1 << 62)) for cam in self.sources), default=now)
        rest_ns = oldest + self.pace_ns - now
        if rest_ns <= 0:
            self.rests_skipped += 1
            return
        self._sleep(rest_ns)

    def _sleep(self, rest_ns: int) -> None:
        """Rest ``rest_ns`` (cut short by :meth:`close`), counted in :attr:`rested_ns`."""
        with self._cond:
            if not self._stop:
                self._cond.wait_for(lambda: self._stop, rest_ns / 1e9)
        self.rested_ns += rest_ns

    def _claim(self, worker: int) -> _Plan | None:
        """Under the lock: the next pass of ``worker`` (its mode and cameras, now held), or None."""
        plan = self.plan_pass(worker)
        if plan is not None:
            self._held.update(plan.cameras)
            self._in_flight += 1
            self.in_flight_max = max(self.in_flight_max, self._in_flight)
        return plan

    def plan_pass(self, worker: int = 0) -> _Plan | None:
        """The pass ``worker`` would run now over the cameras no pass holds that have an unseen frame: packed (a
        canvas's worth of cameras, :meth:`_one_canvas`) or whole (the camera detected longest ago), whichever costs
        less per camera frame (:class:`ModeChooser`); None when no such camera has a new frame."""
        order = sorted(
            (c for c, src in self.sources.items() if c not in self._held and src.has_new_frame()),
            key=lambda c: self._detected_at[c],
        )
        if not order:
            return None
        session = self.sessions[worker]
        packed = tuple(order if session.canvas.batched else self._one_canvas(order))
        p_inputs = self.packer.pass_inputs(packed)
        p_pixels = sum(w * h for w, h in p_inputs)
        if self.chooser is None or self.packer.tile_ratio < 1.0:
            # Tiles below the whole-frame scale (the governor's deepest step): a whole pass cannot shrink, and the
            # chooser's costs are wall time, which a CPU budget's throttling inflates (paced every 1.5 s at 0.4 of a
            # core, the detector took 0.071 s/s choosing, 0.035 s/s all packed).
            return _Plan("packed", packed, p_pixels)
        first = order[0]
        ww, wh = session.whole.whole_frame_input(*self.packer.image_sizes[first])
        mode = self.chooser.choose(PassCost(len(packed), p_pixels), PassCost(1, ww * wh))
        return _Plan("packed", packed, p_pixels) if mode == "packed" else _Plan("whole", (first,), ww * wh)

    def _run_pass(self, plan: _Plan | None = None, worker: int = 0) -> dict[int, tuple[FrameRef, Detections2D]] | None:
        """One pass as planned (default: as :meth:`plan_pass` plans it now); None when none of its cameras had an
        unseen frame after all."""
        if plan is None:
            with self._cond:
                plan = self.plan_pass(worker)
            if plan is None:
                return None
        session = self.sessions[worker]
        inputs: list[tuple[int, int]] = []  # what the pass ran (refresh tiles included), for the cost per pixel
        t0 = self.clock()
        found = self._whole_pass(plan.cameras[0], session) if plan.mode == "whole" else self._packed_pass(
            plan.cameras, session, inputs)  # fmt: skip
        if found is None:
            return None
        busy = self.clock() - t0
        pixels = sum(w * h for w, h in inputs) if inputs else plan.pixels
        with self._cond:
            self.busy_ns += busy
            self.passes += 1
            for cam in found:
                self._detected_at[cam] = self.passes
            if self.chooser is not None:
                usable = sum(1 for _, d in found.values() if len(d) > 0)
                self.chooser.record(plan.mode, len(found), usable, pixels, busy)
        return found

    def _packed_pass(
        self,
        cameras: Sequence[int] | None = None,
        session: Session | None = None,
        inputs: list[tuple[int, int]] | None = None,
    ) -> dict[int, tuple[FrameRef, Detections2D]] | None:
        """A packed pass over ``cameras`` (default: those with an unseen frame, one canvas's worth as
        :meth:`plan_pass` picks them).

        One canvas's worth of cameras: those with an unseen frame, detected longest ago first, as many as share the
        canvases the first one needs. A pass over every camera would deliver each camera's detections only after
        all canvases ran, and make every camera wait that long again for its next frame; passes of one canvas each
        deliver as they go (the same inferences, a shorter detection delay).

        With a batched detector (a GPU: ``[detector] batch``) a pass takes every camera with an unseen frame
        instead: its canvases run in one inference that costs little more than one canvas (1.25-1.8 ms each in a
        batch of 4 against 5.5 ms alone on the H100), and one-canvas passes there ran 1.1 canvases a pass at ~20 ms,
        mostly the pass's own Python work, so live detection reached 0.32 of the detector alone (docs/daemon.md,
        "Issue 15: on a GPU"). Not measured live on a GPU since (no device lent)."""
        session = session if session is not None else self.sessions[0]
        if cameras is None:
            order = sorted((c for c, src in self.sources.items() if src.has_new_frame()),
                           key=lambda c: self._detected_at[c])  # fmt: skip
            if not order:
                return None
            cameras = order if session.canvas.batched else self._one_canvas(order)
        new: dict[int, FrameRef] = {}
        for cam in cameras:
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
        t0 = self.clock()
        (found,) = self.packer.detect([images], cameras=sorted(new), detector=session.canvas, inputs=inputs)
        cams = sorted(new)
        # The packer keeps YOLO's people for its ROIs; the landmarks replace the keypoints delivered.
        t1 = self.clock()
        marked = dict(zip(cams, mark(session.landmarks, [images[c] for c in cams], [found[c] for c in cams],
                                     t1 - t0, cams), strict=True))  # fmt: skip
        if session.hands is not None:
            body_ns = self.clock() - t1
            handed = hand_stage(session.hands, [images[c] for c in cams], [marked[c] for c in cams], cams, t1 - t0,
                                body_ns)  # fmt: skip
            marked = dict(zip(cams, handed, strict=True))
        return {cam: (ref, to_detections2d(marked[cam], self.columns)) for cam, ref in new.items()}

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

    def _whole_pass(
        self, camera: int | None = None, session: Session | None = None
    ) -> dict[int, tuple[FrameRef, Detections2D]] | None:
        """A whole-frame pass over ``camera`` (default: the camera detected longest ago with a new frame)."""
        session = session if session is not None else self.sessions[0]
        # The camera detected longest ago first: every camera gets its turn, none waits two rounds.
        order = [camera] if camera is not None else sorted(self.sources, key=lambda c: self._detected_at[c])
        for cam in order:
            got = self.sources[cam].take_newest()
            if got is None:
                continue
            image = np.asarray(cv2.cvtColor(got[1], cv2.COLOR_RGB2BGR), np.uint8)
            self._images[cam] = image
            t0 = self.clock()
            people = session.whole.detect(image)
            yolo_ns = self.clock() - t0
            # Counted once done, like ``passes``: a pass aborted by close() is neither (packed = passes - whole).
            with self._cond:
                self.whole_passes += 1
            self.packer.seed_rois(cam, people)  # packed passes start from where the people are now
            t1 = self.clock()
            (marked,) = mark(session.landmarks, [image], [people], yolo_ns, [cam])
            (marked,) = hand_stage(session.hands, [image], [marked], [cam], yolo_ns, self.clock() - t1)
            return {cam: (got[0], to_detections2d(marked, self.columns))}
        return None

    def close(self) -> None:
        """Abort the passes in flight and stop the workers (at once: nobody waits for their results)."""
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        for det in self._detectors():
            det.terminate()
        self.executor.shutdown(wait=True, cancel_futures=True)

    def _detectors(self) -> list[OnnxPoseDetector]:
        """Every distinct detector of the sessions and the packer."""
        out: list[OnnxPoseDetector] = []
        for det in (self.packer.detector, self.packer.canvas_detector,
                    *(d for s in self.sessions for d in (s.whole, s.canvas))):  # fmt: skip
            if all(det is not d for d in out):
                out.append(det)
        return out

    def _inference_ns(self) -> int:
        return sum(d.inference_ns for d in self._detectors())

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
            "sessions": len(self.sessions), "passes_in_flight_max": self.in_flight_max,
            "duty": self.duty, "rested_s": round(self.rested_ns / 1e9, 2), "rests_skipped": self.rests_skipped,
            "pace_s": self.pace_ns / 1e9, "tile_ratio": self.packer.tile_ratio,
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
