"""Keypoints for every camera frame: each detected person carried forward on the camera's own images between two
detections (pyramidal Lucas-Kanade, OpenCV), so that the scheduler gets keypoints at the camera rate.

Why. A CPU detector shared by four 60 fps cameras detects each camera 4-8 times a second; the scheduler could only
interpolate between two detections it already had, so the latency had to cover a detection delay plus a detection
interval (300-400 ms). Sparse optical flow on the keypoints' neighbourhoods costs well under a millisecond a frame
and follows the people in between: the latency then covers one frame's tracking.

How, per camera (:class:`KeypointTracker`, thread-safe; the caller decides which thread runs it):

* :meth:`KeypointTracker.step` with each tracked frame (a gray image, downsampled by :attr:`~KeypointTracker.factor`)
  carries every tracked keypoint from the previous tracked frame with pyramidal Lucas-Kanade (OpenCV's
  ``calcOpticalFlowPyrLK`` arithmetic on pyramids built once per frame, :mod:`mocapd.pipeline.optical_flow`), then
  back again; a keypoint whose forward-backward error exceeds ``max_fb_px`` (or that LK loses) is lost for good until
  the next detection. On the Pose2Sim demo (544x960) a lost keypoint was 9-23 px from the detector's next answer
  (median), a kept one 2-3 px (``tools/track_quality.py``).
* :meth:`KeypointTracker.detected` with a detection of frame ``N`` (its gray image, from the detector's own copy
  of the frame): at the next step the detection *replaces* the tracked people. It arrives a detection delay after
  frame ``N`` was captured, so its keypoints are carried from ``N`` through the tracked frames kept since
  (``history_s``) to the newest one (catch-up), and those frames' states are rewritten. Before that, the old
  tracked keypoints are carried to frame ``N`` itself: their distance to the detection there is the tracking
  error this module reports (px, per joint group and by age), measured on every detection.
* Confidence: the detector's, halved every ``half_life_s`` after the detection's frame, zero for lost keypoints.
* People: only a detection makes people (tracking never invents one); a person is dropped when fewer than
  ``min_keypoints`` of their confidently detected keypoints are still tracked, and everyone is dropped once the
  last detection that found them is ``max_age_s`` old (the camera then says nothing until the detector finds people
  again: its keypoint stream stops, as a late detector's does). A person one detection missed is kept until a second
  misses them too. A keypoint the tracker lost follows its person's median motion at ``lost_confidence`` times
  the detector's confidence (:meth:`KeypointTracker._coast`).

Times are arguments (the frames' host capture times); the only clock read is the thread CPU clock for the cost
accounting (injected).
"""

from __future__ import annotations

import bisect
import itertools
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mocapd.core.assignment import linear_sum_assignment
from mocapd.core.sorting import Detections2D
from mocapd.errors import InputError
from mocapd.pipeline.detector_config import TrackingConfig
from mocapd.pipeline.optical_flow import LKOptions, Pyramid, build_pyramid, carry_keypoints

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
Gray = NDArray[np.uint8]

CONFIDENT = 0.5  # a keypoint detected at least this confidently counts for a person's survival and the error stats
MATCH_PX = 80.0  # a detected person is the tracked one when their mean keypoint distance is below this
ERROR_WINDOW = 8192  # tracked-vs-detected keypoint errors kept for the percentiles
AGE_BUCKETS_MS = (50, 100, 200, 400, 800)
#: joint groups of the error report, by keypoint name
JOINT_GROUPS = ("head", "shoulders", "elbows", "wrists", "hips", "knees", "ankles", "other")
_GROUP_WORDS = (
    ("head", ("nose", "eye", "ear", "head", "neck", "mouth")),
    ("shoulders", ("shoulder",)),
    ("elbows", ("elbow",)),
    ("wrists", ("wrist", "hand")),
    ("hips", ("hip", "pelvis")),
    ("knees", ("knee",)),
    ("ankles", ("ankle", "heel", "toe", "foot", "feet")),
)


def joint_group(name: str) -> str:
    """The joint group of a keypoint name ("left_wrist" -> "wrists"; unknown names -> "other")."""
    low = name.lower()
    return next((g for g, words in _GROUP_WORDS if any(w in low for w in words)), "other")


@dataclass
class _People:
    """The tracked people at one frame.

    Attributes
    ----------
    keypoints : ndarray, shape (P, K, 2)
        Camera pixels.
    alive : ndarray of bool, shape (P, K)
        Still tracked (False once lost, until the next detection).
    coasting : ndarray of bool, shape (P, K)
        Lost by the tracker, carried by their person's median motion since (see :meth:`KeypointTracker._carry`).
    confidence : ndarray, shape (P, K)
        As the detector gave them.
    t_det_ns : ndarray of int64, shape (P,)
        Capture time of the detection frame each comes from (the last detection that found them).
    """

    keypoints: FloatArray
    alive: BoolArray
    confidence: FloatArray
    t_det_ns: NDArray[np.int64]
    coasting: BoolArray

    @staticmethod
    def from_detections(d: Detections2D, t_ns: int) -> _People:
        kp = np.asarray(d.keypoints, np.float64).copy()
        conf = np.asarray(d.confidences, np.float64).copy()
        alive = (conf > 0) & np.all(np.isfinite(kp), axis=-1)
        return _People(kp, alive, conf, np.full(len(kp), t_ns, np.int64), np.zeros_like(alive))

    def select(self, keep: BoolArray | NDArray[np.int64]) -> _People:
        return _People(self.keypoints[keep], self.alive[keep], self.confidence[keep], self.t_det_ns[keep],
                       self.coasting[keep])  # fmt: skip

    def extend(self, other: _People) -> _People:
        return _People(
            np.concatenate([self.keypoints, other.keypoints]), np.concatenate([self.alive, other.alive]),
            np.concatenate([self.confidence, other.confidence]), np.concatenate([self.t_det_ns, other.t_det_ns]),
            np.concatenate([self.coasting, other.coasting]),
        )  # fmt: skip

    def __len__(self) -> int:
        return int(self.keypoints.shape[0])


@dataclass
class _Frame:
    """A tracked frame: its gray image's pyramid (built once, for every flow computation the frame takes part
    in) and the people on it (None before the first detection)."""

    seq: int
    t_ns: int
    pyramid: Pyramid
    people: _People | None


@dataclass
class _Pending:
    seq: int
    t_ns: int
    detections: Detections2D
    gray: Gray
    pyramid: Pyramid | None = None


class KeypointTracker:
    """One camera's keypoints carried from frame to frame between detections (see the module docstring).

    Parameters
    ----------
    n_kp : int
        Keypoints per person (the delivered columns).
    options : TrackingConfig
    names : sequence of str, optional
        The keypoints' names, for the per-joint-group error report.
    image_size : (width, height), optional
        The camera's image size: fixes :attr:`factor`, the downsampling of the gray images it is given
        (``options.factor_for``; without a size, ``options.downsample`` or 1 for "auto").
    cpu_clock : callable returning int ns
        The calling thread's CPU clock (cost per step and per person).
    """

    def __init__(
        self,
        n_kp: int,
        options: TrackingConfig | None = None,
        names: Sequence[str] = (),
        image_size: tuple[int, int] | None = None,
        cpu_clock: Callable[[], int] = time.thread_time_ns,
    ) -> None:
        self.n_kp = n_kp
        self.options = options if options is not None else TrackingConfig()
        o = self.options
        self.factor = o.factor_for(*image_size) if image_size is not None else (
            o.downsample if isinstance(o.downsample, int) else 1)  # fmt: skip
        if names and len(names) != n_kp:
            raise InputError(f"keypoint tracker: {len(names)} names for {n_kp} keypoints")
        self._groups = np.array([JOINT_GROUPS.index(joint_group(n)) for n in names] if names else
                                [JOINT_GROUPS.index("other")] * n_kp, np.int8)  # fmt: skip
        self._cpu = cpu_clock
        # OpenCV's calcOpticalFlowPyrLK with the criteria (count 30, epsilon 0.01) this tracker always used.
        self._lk_options = LKOptions(o.window_px, o.levels, 30, 0.01)
        self._lock = threading.Lock()
        self._pending_lock = threading.Lock()
        self._history: list[_Frame] = []  # tracked frames in seq order, the last history_s of them
        self._pending: list[_Pending] = []
        self._shape: tuple[int, int] | None = None
        # Tracked-vs-detected errors: px, joint group, age of the tracked keypoint (ms).
        self._err = np.zeros(ERROR_WINDOW, np.float32)
        self._err_group = np.zeros(ERROR_WINDOW, np.int8)
        self._err_age = np.zeros(ERROR_WINDOW, np.float32)
        self._n_err = 0
        self.counters = dict.fromkeys(
            ("steps", "frames_skipped", "people_steps", "lk_calls", "pyramids_built", "keypoints_lost", "detections",
             "detections_late", "retracked_frames", "people_dropped_age", "people_dropped_keypoints",
             "people_kept_missed"),
            0)  # fmt: skip
        self.cpu_ns = 0
        self.people_now = 0
        self._last_det_ns = -1  # capture time of the detection that replaced the tracked people last
        self._silent = False  # everyone aged out since the last detection (step says nothing)
        self._max_age_ns = self.options.max_age_s * 1e9

    # ------------------------------------------------------------------------------------------------- input
    def detected(self, seq: int, t_ns: int, detections: Detections2D, gray: Gray) -> None:
        """A detection of frame ``seq`` (captured at ``t_ns``, host ns), with that frame's gray image at the
        tracking resolution; it replaces the tracked people at the next :meth:`step`."""
        if detections.keypoints.shape[1:] != (self.n_kp, 2):
            raise InputError(f"keypoint tracker: detections of shape {detections.keypoints.shape}, "
                             f"expected (P, {self.n_kp}, 2)")  # fmt: skip
        with self._pending_lock:  # not the tracking lock: a step (a catch-up) may hold that for a while
            self._pending.append(_Pending(seq, t_ns, detections, gray))

    def reset(self) -> None:
        """Forget the tracked frames, people and pending detections (the next detection starts afresh)."""
        with self._lock, self._pending_lock:
            self._history.clear()
            self._pending.clear()
            self._last_det_ns = -1
            self._silent = False
            self.people_now = 0

    def step(self, seq: int, t_ns: int, gray: Gray) -> Detections2D | None:
        """Track to frame ``seq`` (captured at ``t_ns``, host ns; ``gray`` at the tracking resolution).

        Returns the people on this frame (empty: nobody), or None when there is nothing to say: no detection so
        far, everyone aged out (``max_age_s``) waiting for the next one, or the frame is not newer than the newest
        tracked one.
        """
        with self._lock:
            c0 = self._cpu()
            try:
                return self._step(seq, t_ns, gray)
            finally:
                self.cpu_ns += self._cpu() - c0

    def _step(self, seq: int, t_ns: int, gray: Gray) -> Detections2D | None:
        self._check_shape(gray)
        with self._pending_lock:
            pending, self._pending = self._pending, []
        if pending:
            self._apply_pending(pending)
        last = self._history[-1] if self._history else None
        if last is not None and seq <= last.seq:
            self.counters["frames_skipped"] += 1
            return None
        people = None
        pyramid = self._pyramid(gray)
        if last is not None and last.people is not None:
            people = self._carry(last.people, last.pyramid, pyramid)
        frame = _Frame(seq, t_ns, pyramid, people)
        self._history.append(frame)
        self._trim(t_ns)
        self.counters["steps"] += 1
        if frame.people is None:
            return None
        carried = frame.people
        frame.people = self._prune(carried, t_ns)
        if len(carried) and not len(frame.people) and np.all(t_ns - carried.t_det_ns > self._max_age_ns):
            self._silent = True
        if self._silent:
            # Everyone aged out waiting for a detection: the tracker knows nothing now, which is not "nobody" (the
            # scheduler then holds the camera's last keypoints, then counts it missing, as for a late detector).
            self.people_now = 0
            return None
        self.people_now = len(frame.people)
        self.counters["people_steps"] += len(frame.people)
        return self._output(frame.people, t_ns)

    def _check_shape(self, gray: Gray) -> None:
        shape = (int(gray.shape[0]), int(gray.shape[1]))
        if gray.ndim != 2 or (self._shape is not None and shape != self._shape):
            raise InputError(f"keypoint tracker: gray images must be 2-D of one size, got {gray.shape}")
        self._shape = shape

    # ------------------------------------------------------------------------------------------------- tracking
    def _pyramid(self, gray: Gray) -> Pyramid:
        """The image pyramid of a frame, built once whatever number of flow computations it takes part in."""
        self.counters["pyramids_built"] += 1
        return build_pyramid(gray, self._lk_options)

    def _carry(self, people: _People, g0: Pyramid, g1: Pyramid) -> _People:
        """``people`` tracked from image ``g0`` to ``g1`` (their pyramids): forward and back; lost where the two
        disagree (or the keypoint left the image).

        Keypoints the tracker lost (now or before) follow their person: each moves by the median motion of the
        person's keypoints tracked this step (none: they stay). A person seen in fewer views than the sorting
        needs is lost to the solve, and the detector's next answer for a lost keypoint is a few pixels from where
        its person's motion carries it (tools/track_quality.py): better there, less trusted
        (``lost_confidence``), than missing until the next detection. All of it one compiled call
        (:func:`~mocapd.pipeline.optical_flow.carry_keypoints`)."""
        out = _People(people.keypoints.copy(), people.alive.copy(), people.confidence, people.t_det_ns,
                      people.coasting.copy())  # fmt: skip
        if not out.alive.any():
            return out
        lost = carry_keypoints(g0, g1, out.keypoints, out.alive, out.coasting, self.factor, self.options.max_fb_px,
                               self.options.lost_confidence > 0, self._lk_options)  # fmt: skip
        self.counters["lk_calls"] += 2
        self.counters["keypoints_lost"] += lost
        return out

    def _prune(self, people: _People, t_ns: int) -> _People:
        """Drop everyone once the detection is ``max_age_s`` old, and people with too few keypoints left."""
        if len(people) == 0:
            return people
        young = t_ns - people.t_det_ns <= self.options.max_age_s * 1e9
        if not young.all():
            self.counters["people_dropped_age"] += int((~young).sum())
            people = people.select(young)
        # Keypoints still followed: tracked, or coasting with their person (lost_confidence > 0).
        followed = people.alive | people.coasting if self.options.lost_confidence > 0 else people.alive
        kept = (followed & (people.confidence >= CONFIDENT)).sum(axis=1) >= self.options.min_keypoints
        if not kept.all():
            self.counters["people_dropped_keypoints"] += int((~kept).sum())
            return people.select(kept)
        return people

    def _output(self, people: _People, t_ns: int) -> Detections2D:
        decay = 0.5 ** (np.maximum(0, t_ns - people.t_det_ns) / (self.options.half_life_s * 1e9))
        lost = np.where(people.coasting, people.confidence * self.options.lost_confidence, 0.0)
        conf = np.where(people.alive, people.confidence, lost) * decay[:, None]
        return Detections2D(people.keypoints.copy(), conf)

    def _trim(self, t_ns: int) -> None:
        horizon = t_ns - int(self.options.history_s * 1e9)
        drop = 0
        while drop < len(self._history) - 1 and self._history[drop].t_ns < horizon:
            drop += 1
        del self._history[:drop]

    # ------------------------------------------------------------------------------------------------- detections
    def _apply_pending(self, pending: list[_Pending]) -> None:
        pending = sorted(pending, key=lambda p: p.seq)
        tracked = None
        for p in pending:
            self._check_shape(p.gray)
            tracked = self._measure(p)
        self._replace(pending[-1], tracked)

    def _measure(self, p: _Pending) -> _People | None:
        """Distance between the tracked keypoints carried to the detection's frame and the detection there; the
        tracked people on that frame (None: nobody was tracked before it)."""
        seqs = [f.seq for f in self._history]
        i = bisect.bisect_right(seqs, p.seq) - 1
        if i < 0 or self._history[i].people is None:
            return None
        before = self._history[i]
        assert before.people is not None
        if before.seq == p.seq:
            tracked = before.people
        else:
            tracked = self._carry(before.people, before.pyramid, self._pending_pyramid(p))
        tracked = self._prune(tracked, p.t_ns)
        if len(tracked) == 0 or len(p.detections) == 0:
            return tracked
        age_ms = (p.t_ns - tracked.t_det_ns) / 1e6
        det_kp, det_conf = p.detections.keypoints, p.detections.confidences
        both = tracked.alive[:, None, :] & (tracked.confidence[:, None, :] >= CONFIDENT) & (
            det_conf[None, :, :] >= CONFIDENT)  # fmt: skip
        d = np.linalg.norm(tracked.keypoints[:, None] - det_kp[None, :], axis=-1)  # (P_t, P_d, K)
        n = both.sum(axis=-1)
        mean = np.where(n > 0, np.where(both, d, 0.0).sum(axis=-1) / np.maximum(n, 1), np.inf)
        rows, cols = linear_sum_assignment(np.where(np.isfinite(mean), mean, 1e12))
        for r, c in zip(rows, cols, strict=True):
            if mean[r, c] > MATCH_PX:
                continue
            sel = both[r, c]
            self._record(d[r, c][sel], self._groups[sel], float(age_ms[r]))
        return tracked

    def _record(self, errors: FloatArray, groups: NDArray[np.int8], age_ms: float) -> None:
        for e, g in zip(errors, groups, strict=True):
            k = self._n_err % ERROR_WINDOW
            self._err[k], self._err_group[k], self._err_age[k] = e, g, age_ms
            self._n_err += 1

    def _pending_pyramid(self, p: _Pending) -> Pyramid:
        """The pyramid of a detection's frame (built by :meth:`_measure` already, or now)."""
        if p.pyramid is None:
            p.pyramid = self._pyramid(p.gray)
        return p.pyramid

    def _missed(self, tracked: _People, fresh: _People) -> _People:
        """The tracked people a detection did not find that tracking keeps: those found by the camera's previous
        detection (missed once: a packed detector's region or a weak pass misses a person now and then; the next
        detection decides) that no detected person overlaps. Dropped on the second miss in a row."""
        if len(tracked) == 0:
            return tracked.select(np.zeros(0, np.int64))
        followed = tracked.alive | tracked.coasting
        once = tracked.t_det_ns == self._last_det_ns
        if len(fresh):
            lo = np.where(fresh.alive[..., None], fresh.keypoints, np.inf).min(axis=1)  # (P_d, 2) boxes
            hi = np.where(fresh.alive[..., None], fresh.keypoints, -np.inf).max(axis=1)
            for r in np.flatnonzero(once):
                pts = tracked.keypoints[r][followed[r]]
                if pts.shape[0] == 0:
                    once[r] = False
                    continue
                centre = np.median(pts, axis=0)
                margin = 0.1 * (hi - lo).max(axis=1, keepdims=True)
                once[r] = not np.any(np.all((centre >= lo - margin) & (centre <= hi + margin), axis=1))
        self.counters["people_kept_missed"] += int(once.sum())
        return tracked.select(once)

    def _replace(self, p: _Pending, tracked: _People | None = None) -> None:
        """The detection's people replace the tracked ones from its frame on: carried through the kept frames
        after it to the newest (their states rewritten); tracked people it missed once stay (:meth:`_missed`)."""
        self.counters["detections"] += 1
        fresh = _People.from_detections(p.detections, p.t_ns)
        if tracked is not None:
            fresh = fresh.extend(self._missed(tracked, fresh))
        self._last_det_ns = p.t_ns
        self._silent = False
        seqs = [f.seq for f in self._history]
        if not self._history or p.seq > seqs[-1]:
            self._history.append(_Frame(p.seq, p.t_ns, self._pending_pyramid(p), fresh))
            return
        if p.seq < seqs[0]:
            self.counters["detections_late"] += 1  # older than every kept frame: cannot be carried forward
            return
        i = bisect.bisect_left(seqs, p.seq)
        if seqs[i] == p.seq:
            self._history[i].people = fresh
        else:
            self._history.insert(i, _Frame(p.seq, p.t_ns, self._pending_pyramid(p), fresh))
        for j in range(i + 1, len(self._history)):
            prev, cur = self._history[j - 1], self._history[j]
            assert prev.people is not None
            cur.people = self._prune(self._carry(prev.people, prev.pyramid, cur.pyramid), cur.t_ns)
            self.counters["retracked_frames"] += 1

    # ------------------------------------------------------------------------------------------------- report
    @property
    def error_count(self) -> int:
        """Tracked-vs-detected keypoint errors measured so far (the newest :data:`ERROR_WINDOW` are kept)."""
        return self._n_err

    def errors(self, since: int = 0) -> tuple[NDArray[np.float32], NDArray[np.int8], NDArray[np.float32]]:
        """Copies of the kept tracked-vs-detected errors measured after the first ``since`` (an earlier
        :attr:`error_count`), oldest first: px, joint group index (:data:`JOINT_GROUPS`), age of the tracking ms."""
        with self._lock:
            n = self._n_err
            k = np.arange(max(since, n - ERROR_WINDOW), n) % ERROR_WINDOW
            return self._err[k], self._err_group[k], self._err_age[k]

    def status(self) -> dict[str, Any]:
        """JSON-able: counters, CPU per step and per person-step, the error against the detections (px)."""
        with self._lock:
            c = dict(self.counters)
            cpu_ns, people = self.cpu_ns, self.people_now
        err, group, age = self.errors()
        out: dict[str, Any] = {
            **c, "people": people, "cpu_s": round(cpu_ns / 1e9, 3),
            "cpu_ms_per_step": round(cpu_ns / c["steps"] / 1e6, 3) if c["steps"] else None,
            "cpu_ms_per_person_step": round(cpu_ns / c["people_steps"] / 1e6, 3) if c["people_steps"] else None,
            "error_vs_detection_px": error_summary(err, group, age),
        }  # fmt: skip
        return out


def _pct(values: NDArray[np.float32]) -> dict[str, float | int | None]:
    if values.size == 0:
        return {"n": 0, "median": None, "p90": None}
    p50, p90 = np.percentile(values, (50, 90))
    return {"n": int(values.size), "median": round(float(p50), 2), "p90": round(float(p90), 2)}


def error_summary(err: NDArray[np.float32], group: NDArray[np.int8], age_ms: NDArray[np.float32]) -> dict[str, Any]:
    """Median and p90 of tracked-vs-detected keypoint errors: all, per joint group, per age bucket (ms)."""
    by_group = {g: _pct(err[group == k]) for k, g in enumerate(JOINT_GROUPS) if np.any(group == k)}
    edges = (0, *AGE_BUCKETS_MS, np.inf)
    by_age = {}
    for lo, hi in itertools.pairwise(edges):
        sel = (age_ms >= lo) & (age_ms < hi)
        if sel.any():
            by_age[f"{lo}-{hi:g}" if np.isfinite(hi) else f">{lo}"] = _pct(err[sel])
    return {"all": _pct(err), "by_joint_group": by_group, "by_age_ms": by_age}
