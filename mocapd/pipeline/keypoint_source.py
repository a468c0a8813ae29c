"""Keypoint sources: what feeds each camera's detection timeline.

A source is one camera's "frames in, timestamped 2D people out" stage. :class:`DetectorKeypointSource` runs any
:data:`Detector` (the onnxruntime detector of issue 6 plugs in here) on the frames of an Aravis or replay source
in a worker thread, so it never blocks the event loop; until the detector lands,
:class:`mocapd.sim.world.SyntheticKeypointSource` plays a detector's output for a
synthetic world: frames captured at the camera rate (cameras unsynchronised: each has its own phase), detections
delivered ``detection_delay_s`` after capture, stamped with the capture time.

With a :class:`~mocapd.pipeline.keypoint_tracker.KeypointTracker`, a detector source delivers keypoints for every
tracked frame instead of its detections: the tracker carries the detected people from frame to frame (on the
capture thread, or on a tracking pool), and each detection re-seeds it (:mod:`mocapd.pipeline.keypoint_tracker`).
The scheduler then gets keypoints at the tracking rate, one frame's tracking after capture, not a detection delay
plus a detection interval.
"""

from __future__ import annotations

import asyncio
import logging
import statistics
import threading
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Executor
from typing import Any, Protocol

import cv2
import numpy as np
from numpy.typing import NDArray

from mocapd.core.sorting import Detections2D
from mocapd.errors import InputError
from mocapd.io.device_state import OpenState
from mocapd.io.loop_mailbox import LoopMailbox, loop_mailbox
from mocapd.pipeline.clocksync import ClockSync
from mocapd.pipeline.frame_ring import FrameRef, FrameRing, image_gray
from mocapd.pipeline.keypoint_tracker import KeypointTracker
from mocapd.pipeline.latency import LatencyStats

log = logging.getLogger(__name__)
TOKENS_MAX = 1.5  # a frame the camera dropped leaves half a frame of credit: the next two frames are tracked
TOKEN_SLACK = 1e-6  # 0.5 + 0.5 tokens is a frame, however the sums round
#: Tracking steps back (the camera delivers its detections, as without tracking) while the median delay of its last
#: DELAY_WINDOW detections exceeds this share of what the tracker can carry a detection across (the shorter of
#: [detector.tracking] history_s and max_age_s), and steps in again below STEP_IN of it.
STEP_BACK = 0.5
STEP_IN = 0.35
DELAY_WINDOW = 8

#: (camera index, capture time ns, detections, arrival time ns) -> None
KeypointSink = Callable[[int, int, Detections2D, int], None]


class KeypointSource(Protocol):
    """One camera's detections, delivered to a sink as they become available."""

    name: str
    camera: int

    async def run(self, sink: KeypointSink) -> None:
        """Deliver detections until cancelled; raise :class:`~mocapd.errors.DeviceError` on a device failure
        (the daemon's supervisor restarts the source with back-off)."""
        ...

    def status(self) -> dict[str, Any]:
        """JSON-able health for /status."""
        ...

    def open_state(self) -> OpenState:
        """Whether the source's device has opened (the daemon waits for every device before READY)."""
        ...


class FrameProducer(Protocol):
    """A frame source (:class:`mocapd.io.frame_source.ThreadedSource`: Aravis camera, video, image folder)."""

    name: str
    ring: FrameRing

    async def run(self, on_frame: Callable[[FrameRef], None]) -> None: ...

    def open_state(self) -> OpenState: ...


#: a 2D detector: one image (height, width, channels) uint8 in, the people it sees out (called in a worker thread)
Detector = Callable[[NDArray[np.uint8]], Detections2D]


class DetectorKeypointSource:
    """Frames of a camera through a detector, never blocking the event loop.

    The detector runs in a worker thread on the newest frame of the ring when a worker takes the job; the frames
    captured meanwhile are skipped (temporal sub-sampling, as in seed 003 §3.4.2: the detector sets the detection
    rate, the scheduler interpolates) and counted. Detections are stamped with the frame's host capture time, or, with
    ``device_clock``, with the camera's own frame timestamp mapped to the host clock: a camera stamps the
    exposure, so the stamp leaves out the frame's transfer and the capture thread's wake-up (the map is the
    lower envelope of host arrival vs device stamp, :class:`~mocapd.pipeline.clocksync.ClockSync`, so what
    remains is exposure + the least transfer delay seen).

    With a ``tracker``, the sink gets the tracked keypoints of every tracked frame (at most ``rate_hz`` of its
    options a second, plus the frames the detector takes) and the detections only re-seed the tracker (see the
    module docstring). It runs on the frame source's capture thread (``frame_hook``, where the source has one and
    no ``tracking_pool`` is given) or on ``tracking_pool``.
    """

    def __init__(
        self,
        camera: int,
        frames: FrameProducer,
        detector: Detector,
        *,
        executor: Executor | None = None,
        clock: Callable[[], int] = time.monotonic_ns,
        device_clock: ClockSync | None = None,
        tracker: KeypointTracker | None = None,
        tracking_pool: Executor | None = None,
        cpu_clock: Callable[[], int] = time.thread_time_ns,
    ) -> None:
        self.camera = camera
        self.name = frames.name
        self.frames = frames
        self.detector = detector
        self.executor = executor
        self.clock = clock
        self.device_clock = device_clock
        self.detected = 0
        self.detected_people = 0  # people in all detections (the people in view, as the detector saw them)
        self.skipped = 0
        self.lost = 0  # copies overtaken by the ring's writer (a newer frame is taken; counted in skipped too)
        self.captured = 0
        self._last_seq = -1  # ring sequence number of the last frame detected
        self.transfer_ns = 0  # sum over detected frames of host arrival - capture stamp
        self.tracker = tracker
        self.tracking_pool = tracking_pool
        self._cpu = cpu_clock
        self.detection_delay = LatencyStats(1024)  # capture -> detections received (the tracker hides it downstream)
        # Tracking: keypoint sets delivered (people in them), frames tracked, the CPU of it all (gray image, steps).
        self.tracking = {"sets": 0, "person_sets": 0, "frames": 0, "gray_missed": 0, "errors": 0,
                         "cpu_ns": 0, "detections_without_image": 0, "steps_back": 0,
                         "detections_delivered": 0}  # fmt: skip
        #: tracking delivers the keypoints now (False: it stepped back, the detections go out themselves)
        self.tracking_active = tracker is not None
        #: the governor's share of the configured tracking rate (1: as configured, 0.5: half, 0: tracking off,
        #: the detections go out themselves as when tracking steps back)
        self.tracking_rate_scale = 1.0
        self._delays: deque[int] = deque(maxlen=DELAY_WINDOW)
        self._last_sent_ns = -(2**62)  # stamp of the newest keypoint set sent (tracked, or a detection)
        self._last_frame_ns: tuple[int, int] | None = None  # (device, host) time of the last frame offered
        self._tokens = 0.0  # frames the tracker may take now (rate_hz token bucket)
        self._mailbox: LoopMailbox | None = None  # the loop's: tracked keypoints cross to it there
        self._sink: KeypointSink | None = None
        self._grays: dict[int, NDArray[np.uint8]] = {}  # gray images of the frames the detector took, by seq
        self._grays_lock = threading.Lock()

    async def run(self, sink: KeypointSink) -> None:
        loop = asyncio.get_running_loop()
        wake = asyncio.Event()
        self._mailbox, self._sink = loop_mailbox(loop), sink
        pool = self.tracking_pool
        in_capture = self.tracker is not None and pool is None and hasattr(self.frames, "frame_hook")
        if self.tracker is not None and pool is None and not in_capture:
            raise InputError(f"camera {self.name}: tracking needs a frame source with a capture thread or a pool")

        def on_frame(ref: FrameRef) -> None:
            self.captured += 1
            if self.device_clock is not None:
                self.device_clock.update(ref.device_ns, ref.host_ns)
            self.frame_arrived(ref)
            wake.set()
            if pool is not None and self.tracker is not None and self.tracking_active and self._due(ref):
                pool.submit(self._track, ref)

        async def detect_loop() -> None:
            while True:
                await wake.wait()
                wake.clear()
                done = await self._detection(loop)
                if done is None:
                    continue
                ref, dets = done
                stamp = self.capture_ns(ref)
                arrival = self.clock()
                if self.tracker is not None and self._tracking_reaches(arrival - stamp):
                    self._reseed(ref, dets)
                elif self.tracker is None:
                    sink(self.camera, stamp, dets, arrival)
                elif stamp > self._last_sent_ns:  # not older than a tracked set already sent (stepping back)
                    self._last_sent_ns = stamp
                    sink(self.camera, stamp, dets, arrival)
                    self.tracking["detections_delivered"] += 1
                self.detection_delay.add(arrival - stamp)
                self.detected += 1
                self.detected_people += len(dets)
                self.transfer_ns += ref.host_ns - stamp

        if in_capture:
            self.frames.frame_hook = self._track_in_capture  # type: ignore[attr-defined]  # ThreadedSource
        try:
            async with asyncio.TaskGroup() as tg:
                worker = tg.create_task(detect_loop())
                await self.frames.run(on_frame)  # returns at the end of a replay; errors propagate to the supervisor
                worker.cancel()
        finally:
            if in_capture:
                self.frames.frame_hook = None  # type: ignore[attr-defined]

    # ----------------------------------------------------------------------------------------------- tracking
    def _tracking_reaches(self, delay_ns: int) -> bool:
        """Whether tracking carries this camera's detections now, given the delay of the newest one.

        A detection later than the tracker's history, or older than its people's age limit, re-seeds nothing: a
        starved detector (1-2 s late on a loaded 2-core machine) would leave the camera with nobody, where its
        detections alone, behind a longer latency, still have the people. Tracking then steps back and the
        detections go out as they are (the scheduler's auto latency follows them) until the delay is short again;
        stepping in, the tracker starts afresh from the next detection. Its CPU goes to the detector meanwhile."""
        assert self.tracker is not None
        o = self.tracker.options
        self._delays.append(delay_ns)
        reach = min(o.history_s, o.max_age_s) * 1e9
        delay = float(statistics.median(self._delays))  # 8 ints: a fraction of numpy's call overhead, on the loop
        if self.tracking_rate_scale <= 0.0:  # the governor shed it: the detections go out themselves
            if self.tracking_active:
                self.tracking_active = False
                log.info("camera %s: keypoint tracking off (the governor sheds it)", self.name)
            return False
        if self.tracking_active and delay > STEP_BACK * reach:
            self.tracking_active = False
            self.tracking["steps_back"] += 1
            log.info("camera %s: detections %.0f ms late: tracking steps back", self.name, delay / 1e6)
        elif not self.tracking_active and delay < STEP_IN * reach:
            self.tracker.reset()
            self.tracking_active = True
            log.info("camera %s: detections %.0f ms late: tracking again", self.name, delay / 1e6)
        return self.tracking_active

    def _due(self, ref: FrameRef) -> bool:
        """Whether frame ``ref`` is tracked: ``rate_hz`` frames a second on average, never more than the camera
        sends (a token bucket: a 60 fps camera at 30 Hz gives every other frame, one at 56 fps 30 of its 56). Time
        is the camera's own stamps where they advance plausibly (exposures are evenly spaced; arrivals come in
        bursts after a stalled thread, which would overflow the bucket), else the host's arrival times."""
        assert self.tracker is not None
        last = self._last_frame_ns
        self._last_frame_ns = (ref.device_ns, ref.host_ns)
        if last is None:
            return True
        dt = ref.device_ns - last[0]
        if not 0 < dt < 1_000_000_000:
            dt = max(0, ref.host_ns - last[1])
        rate = self.tracker.options.rate_hz * self.tracking_rate_scale
        self._tokens = min(TOKENS_MAX, self._tokens + rate * dt / 1e9)
        if self._tokens < 1.0 - TOKEN_SLACK:
            return False
        self._tokens -= 1.0
        return True

    def _track_in_capture(self, ref: FrameRef) -> None:
        """On the capture thread, right after ``ref`` was published."""
        if self.tracking_active and self._due(ref):
            self._track(ref)

    def _track(self, ref: FrameRef) -> None:
        """Track frame ``ref`` (capture thread or tracking pool) and hand its keypoints to the event loop."""
        tracker, mailbox = self.tracker, self._mailbox
        assert tracker is not None and mailbox is not None
        c0 = self._cpu()
        try:
            gray = self.frames.ring.gray(ref.seq, tracker.factor)
            if gray is None:  # the writer overtook us (a stalled thread): the next frame is tracked instead
                self.tracking["gray_missed"] += 1
                return
            people = tracker.step(ref.seq, ref.host_ns, gray)
            self.tracking["frames"] += 1
            if people is not None:
                # Arrival = now, when the keypoints exist: the loop runs the queued delivery before any tick due
                # later, so a stalled loop delays the ticks too and is no reason for a longer latency. (Dropped
                # once the loop is closed.)
                mailbox.post(self._deliver_tracked, ref, people, self.clock())
        except (cv2.error, InputError):
            self.tracking["errors"] += 1
            log.exception("camera %s: tracking frame %d failed", self.name, ref.seq)
        finally:
            self.tracking["cpu_ns"] += self._cpu() - c0

    def _deliver_tracked(self, ref: FrameRef, people: Detections2D, done_ns: int) -> None:
        """On the event loop: one tracked frame's keypoints to the sink, stamped like a detection (``done_ns``:
        when tracking finished)."""
        stamp = self.capture_ns(ref)
        if self._sink is None or not self.tracking_active or stamp <= self._last_sent_ns:
            return
        self._last_sent_ns = stamp
        self._sink(self.camera, stamp, people, done_ns)
        self.tracking["sets"] += 1
        self.tracking["person_sets"] += len(people)

    def _reseed(self, ref: FrameRef, dets: Detections2D) -> None:
        """A detection of frame ``ref`` goes to the tracker with that frame's gray image (taken with the frame)."""
        assert self.tracker is not None
        with self._grays_lock:
            gray = self._grays.pop(ref.seq, None)
        if gray is None:
            self.tracking["detections_without_image"] += 1
            return
        self.tracker.detected(ref.seq, ref.host_ns, dets, gray)

    def _keep_gray(self, ref: FrameRef, image: NDArray[np.uint8]) -> None:
        """The gray image of a frame the detector took (its detections re-seed the tracker); detector thread."""
        if self.tracker is None:
            return
        factor = self.tracker.factor
        gray = self.frames.ring.gray(ref.seq, factor)  # a Bayer ring makes it from the mosaic
        if gray is None:
            gray = image_gray(image, factor)
        with self._grays_lock:
            self._grays[ref.seq] = gray
            while len(self._grays) > 8:  # results that never came (a failed pass): forget the oldest
                del self._grays[min(self._grays)]

    def frame_arrived(self, ref: FrameRef) -> None:
        """Called on the event loop for every captured frame (a shared detector's worker wakes up here)."""

    def capture_ns(self, ref: FrameRef) -> int:
        """The frame's capture time on the host clock (never later than its arrival)."""
        mapped = self.device_clock.to_host_ns(ref.device_ns) if self.device_clock is not None else None
        return ref.host_ns if mapped is None else min(mapped, ref.host_ns)

    async def _detection(self, loop: asyncio.AbstractEventLoop) -> tuple[FrameRef, Detections2D] | None:
        # The frame is chosen when a worker is free, not when it was queued: with several cameras sharing the
        # workers, a frame chosen at queueing time would be stale (or overwritten) by then.
        return await loop.run_in_executor(self.executor, self._detect_newest)

    def has_new_frame(self) -> bool:
        """Whether the ring holds a frame newer than the last one taken."""
        ref = self.frames.ring.latest()
        return ref is not None and ref.seq > self._last_seq

    def take_newest(self) -> tuple[FrameRef, NDArray[np.uint8]] | None:
        """The newest frame not taken yet, copied out of the ring (None if there is none); counts the frames
        skipped since the last one taken. Called by one worker at a time."""
        ring = self.frames.ring
        for _ in range(3):  # the writer may overtake the copy; then the newer frame is the one to take
            ref = ring.latest()
            if ref is None or ref.seq <= self._last_seq:
                return None
            image = ring.read(ref.seq)
            if image is None:
                self.lost += 1
                continue
            if self._last_seq >= 0:
                self.skipped += ref.seq - self._last_seq - 1
            self._last_seq = ref.seq
            self._keep_gray(ref, image)
            return ref, image
        return None

    def _detect_newest(self) -> tuple[FrameRef, Detections2D] | None:
        """In a worker: detect the newest frame not detected yet (None if there is none)."""
        got = self.take_newest()
        return None if got is None else (got[0], self.detector(got[1]))

    def open_state(self) -> OpenState:
        return self.frames.open_state()

    def status(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "name": self.name, "kind": "detector", "captured": self.captured, "detected": self.detected,
            "detected_people": self.detected_people,
            "skipped": self.skipped, "lost": self.lost,
            "transfer_ms_mean": round(self.transfer_ns / self.detected / 1e6, 2) if self.detected else None,
        }  # fmt: skip
        delay = self.detection_delay.percentiles_ms((50, 95))
        out["detection_delay_ms"] = delay
        if self.tracker is not None:
            t = self.tracking
            cpu = t["cpu_ns"]
            out["tracking"] = {
                "keypoint_sets": t["sets"], "person_keypoint_sets": t["person_sets"], "frames": t["frames"],
                "gray_missed": t["gray_missed"], "errors": t["errors"],
                "detections_without_image": t["detections_without_image"], "cpu_s": round(cpu / 1e9, 3),
                "cpu_ms_per_frame": round(cpu / t["frames"] / 1e6, 3) if t["frames"] else None,
                "cpu_ms_per_person_frame": round(cpu / t["person_sets"] / 1e6, 3) if t["person_sets"] else None,
                "thread": "pool" if self.tracking_pool is not None else "capture",
                "active": self.tracking_active, "steps_back": t["steps_back"],
                "rate_hz": round(self.tracker.options.rate_hz * self.tracking_rate_scale, 1),
                "detections_delivered": t["detections_delivered"],
                "tracker": self.tracker.status(),
            }  # fmt: skip
        capture = getattr(self.frames, "capture_status", None)  # frame sources of mocapd.io report their device
        if callable(capture):
            out["capture"] = capture()
        return out
