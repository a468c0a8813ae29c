"""Per-camera timeline of 2D detections, sampled at a solve time by linear interpolation (seed 003 §3.4.2).

A detector reports, per camera frame, an unordered set of 2D people (:class:`~mocapd.core.sorting.Detections2D`)
stamped with the frame's capture time. The fixed-latency scheduler asks for the detections at a solve time ``t``
that generally falls between two detected frames (cameras are not synchronised and the detector sub-samples):

- between two frames ``a`` (t_a <= t) and ``b`` (t_b > t), the people of ``b`` are matched to those of ``a`` by
  mean keypoint distance (Hungarian assignment, accepted below ``match_px``) and each matched pair is blended
  linearly; people seen only in the nearer frame are passed through unchanged, the others are left out;
- after the newest frame (the detector is late): the newest frame is *held* while it is at most ``max_age_ns``
  old, and nothing is returned once it is older (the camera then counts as missing: never extrapolated);
- before the oldest frame, or across a hole longer than ``max_gap_ns``: the nearer frame when it is within
  ``max_age_ns`` of ``t``, otherwise nothing.

Pure: time is an argument; nothing here reads a clock.
"""

from __future__ import annotations

import enum
from collections import deque
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mocapd.core.assignment import linear_sum_assignment
from mocapd.core.sorting import Detections2D

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


class SampleStatus(enum.Enum):
    """How a timeline answered a look-up."""

    INTERPOLATED = "interpolated"  # between two frames
    EXACT = "exact"  # t is a frame's time
    HELD = "held"  # after the newest frame, which is still young enough
    NEAREST = "nearest"  # before the oldest frame or across a gap: the nearer frame, young enough
    STALE = "stale"  # the data around t is older than max_age: nothing returned
    EMPTY = "empty"  # no frame yet


#: statuses that return detections
USABLE = frozenset({SampleStatus.INTERPOLATED, SampleStatus.EXACT, SampleStatus.HELD, SampleStatus.NEAREST})


@dataclass(frozen=True, slots=True)
class TimelineSample:
    """Detections at the requested time (empty unless the status is usable) and the frame times used.

    ``frame_ns`` names the observation the detections come from: the capture time of the frame they are (held,
    exact, nearest), or of the nearer of the two frames they are interpolated between (whose people are the ones
    passed through); -1 when none is usable. Ticks between two detector passes carry the same few frames, so the
    tracker counts evidence per frame, not per tick (:class:`~mocapd.core.tracking.SubjectTracker`, issue 41).
    """

    status: SampleStatus
    detections: Detections2D
    t_before: int
    t_after: int
    frame_ns: int = -1


class DetectionTimeline:
    """The last ``capacity`` detected frames of one camera.

    Parameters
    ----------
    n_kp : int
        Keypoints per person.
    capacity : int
        Frames kept (a few seconds' worth is plenty; the scheduler only looks ``latency`` back).
    max_age_ns : int
        Largest distance between ``t`` and the frame used when holding (no newer frame) or taking the nearest.
    max_gap_ns : int
        Largest spacing of two frames across which people are interpolated.
    match_px : float
        Largest mean keypoint distance (pixels) at which a person of one frame is the same as one of the next.
    """

    def __init__(
        self,
        n_kp: int,
        *,
        capacity: int = 256,
        max_age_ns: int = 100_000_000,
        max_gap_ns: int = 200_000_000,
        match_px: float = 80.0,
    ) -> None:
        self.n_kp = n_kp
        self.max_age_ns = max_age_ns
        self.max_gap_ns = max_gap_ns
        self.match_px = match_px
        self._frames: deque[tuple[int, Detections2D]] = deque(maxlen=capacity)
        self.rejected_out_of_order = 0
        self.frames_received = 0
        #: the last bracket's two frames and who in one is who in the other: at 60 Hz ticks and 30 Hz cameras
        #: consecutive ticks blend the same two frames at another ``alpha``, and the matching does not depend on it
        self._matched: tuple[Detections2D, Detections2D, Bracket] | None = None
        #: people matchings computed (one per bracket sampled, however many ticks sample it)
        self.matchings = 0

    def __len__(self) -> int:
        return len(self._frames)

    def push(self, t_ns: int, detections: Detections2D) -> bool:
        """Add a frame; returns False (and counts it) unless it is newer than the newest frame."""
        if self._frames and t_ns <= self._frames[-1][0]:
            self.rejected_out_of_order += 1
            return False
        self._frames.append((t_ns, detections))
        self.frames_received += 1
        return True

    def frames(self) -> tuple[list[int], list[Detections2D]]:
        """A copy of the kept frames, oldest first: (times, detections)."""
        frames = list(self._frames)
        return [t for t, _ in frames], [d for _, d in frames]

    def newest_ns(self) -> int | None:
        return self._frames[-1][0] if self._frames else None

    def sample(self, t_ns: int, with_people: bool = True) -> TimelineSample:  # noqa: PLR0911 (one per outcome)
        """The detections at ``t_ns`` (see the module docstring for the rules). ``with_people=False``: the status and
        frames only, for a caller that needs nothing else (a tick that carries its people on instead of solving
        them): between two frames the people are then neither matched nor blended, and the detections are empty."""
        if not self._frames:
            return TimelineSample(SampleStatus.EMPTY, self._empty(), 0, 0)
        first_t, first = self._frames[0]
        last_t, last = self._frames[-1]
        if t_ns >= last_t:
            if t_ns == last_t:
                return TimelineSample(SampleStatus.EXACT, last, last_t, last_t, last_t)
            if t_ns - last_t <= self.max_age_ns:
                return TimelineSample(SampleStatus.HELD, last, last_t, last_t, last_t)
            return TimelineSample(SampleStatus.STALE, self._empty(), last_t, last_t)
        if t_ns < first_t:
            if first_t - t_ns <= self.max_age_ns:
                return TimelineSample(SampleStatus.NEAREST, first, first_t, first_t, first_t)
            return TimelineSample(SampleStatus.STALE, self._empty(), first_t, first_t)
        # Newest first: the scheduler looks a fixed latency back, so the bracket is near the end.
        k = len(self._frames) - 2
        while self._frames[k][0] > t_ns:
            k -= 1
        t0, a = self._frames[k]
        t1, b = self._frames[k + 1]
        if t0 == t_ns:
            return TimelineSample(SampleStatus.EXACT, a, t0, t0, t0)
        if t1 - t0 > self.max_gap_ns:
            near_t, near = (t0, a) if t_ns - t0 <= t1 - t_ns else (t1, b)
            if abs(t_ns - near_t) <= self.max_age_ns:
                return TimelineSample(SampleStatus.NEAREST, near, t0, t1, near_t)
            return TimelineSample(SampleStatus.STALE, self._empty(), t0, t1)
        alpha = (t_ns - t0) / (t1 - t0)
        if not with_people:
            return TimelineSample(SampleStatus.INTERPOLATED, self._empty(), t0, t1, t0 if alpha <= 0.5 else t1)
        m = self._matched
        if m is None or m[0] is not a or m[1] is not b:
            m = self._matched = (a, b, Bracket(a, b, match_people(a, b, self.match_px)))
            self.matchings += 1
        people = m[2].at(alpha)
        return TimelineSample(SampleStatus.INTERPOLATED, people, t0, t1, t0 if alpha <= 0.5 else t1)

    def _empty(self) -> Detections2D:
        """Nobody (made only where a look-up answers with nobody: most ticks do not)."""
        return Detections2D.empty(self.n_kp)


def person_distances(a: Detections2D, b: Detections2D, min_confidence: float = 0.0) -> FloatArray:
    """Mean pixel distance over keypoints both people have, shape ``(len(a), len(b))`` (inf: none shared)."""
    na, nb = a.keypoints.shape[0], b.keypoints.shape[0]
    if na == 0 or nb == 0:
        return np.zeros((na, nb))
    shared = (a.confidences[:, None, :] > min_confidence) & (b.confidences[None, :, :] > min_confidence)
    d = np.linalg.norm(a.keypoints[:, None] - b.keypoints[None, :], axis=-1)  # (na, nb, n_kp)
    n = shared.sum(axis=-1)
    total = np.where(shared, d, 0.0).sum(axis=-1)
    return np.where(n > 0, total / np.maximum(n, 1), np.inf)


def match_people(a: Detections2D, b: Detections2D, match_px: float) -> list[tuple[int, int]]:
    """Who in frame ``a`` is who in frame ``b``: (index in a, index in b) of the assignment with the least total
    mean keypoint distance, pairs farther than ``match_px`` apart left out."""
    d = person_distances(a, b)
    if not d.size:
        return []
    rows, cols = linear_sum_assignment(np.where(np.isfinite(d), d, 1e12))
    return [(int(i), int(j)) for i, j in zip(rows, cols, strict=True) if d[i, j] <= match_px]


def interpolate_people(
    a: Detections2D, b: Detections2D, alpha: float, match_px: float, *, pairs: list[tuple[int, int]] | None = None
) -> Detections2D:
    """People of two frames blended at ``alpha`` in [0, 1] (0 = ``a``).

    Matched people: keypoints seen in both frames are blended linearly, with blended confidence; a keypoint seen
    in one frame only keeps that frame's position with its confidence scaled by that frame's weight. Unmatched
    people of the nearer frame are passed through; those of the farther frame are left out. ``pairs``: the
    frames' :func:`match_people` when the caller has it already (it does not depend on ``alpha``).
    """
    if pairs is None:
        pairs = match_people(a, b, match_px)
    return Bracket(a, b, pairs).at(alpha)


class Bracket:
    """Two frames' people, matched (``pairs``: :func:`match_people`), ready to blend at any ``alpha``
    (:func:`interpolate_people`'s rules).

    What does not depend on ``alpha`` is worked out once, when the bracket is first sampled: the matched people's
    rows, which keypoints each pair saw in both frames or in one, the steps between the frames, and the nearer
    frame's unmatched people. At 60 Hz ticks and 30 Hz cameras two ticks blend each bracket, so a tick only blends
    (a few element-wise operations for every pair at once, issue 39). The arithmetic is the pair-by-pair loop's,
    element by element: the same floats (``tests/test_timeline_bitwise.py``). The undistorted copies (made once per
    frame as it arrived) are blended like the pixels: the lens map is smooth over the few pixels a keypoint moves
    between two frames.
    """

    def __init__(self, a: Detections2D, b: Detections2D, pairs: list[tuple[int, int]]) -> None:
        self.n_kp = a.keypoints.shape[1]
        ia, jb = np.array(pairs, dtype=np.intp).reshape(-1, 2).T
        ca, cb = a.confidences[ia], b.confidences[jb]
        in_a = ca > 0
        self._both = in_a & (cb > 0)
        self._ca, self._cb, self._dc, self._in_a = ca, cb, cb - ca, in_a
        self._points = [self._pair_points(a.keypoints[ia], b.keypoints[jb], in_a)]
        if a.undistorted is not None and b.undistorted is not None:
            self._points.append(self._pair_points(a.undistorted[ia], b.undistorted[jb], in_a))
        #: per nearer frame (a, b): its people no pair holds, in their order (None: everyone is matched)
        self._rest = [self._unmatched(a, ia, len(self._points) > 1), self._unmatched(b, jb, len(self._points) > 1)]

    @staticmethod
    def _pair_points(pa: FloatArray, pb: FloatArray, in_a: BoolArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(a's points, the step to b's, the one frame's points where only one saw them), shapes (pairs, n_kp, 2)."""
        return pa, pb - pa, np.where(in_a[..., None], pa, pb)

    @staticmethod
    def _unmatched(frame: Detections2D, matched: NDArray[np.intp], with_und: bool) -> list[FloatArray] | None:
        """``frame``'s people not in ``matched``: [keypoints, confidences(, undistorted)]; None when there are none."""
        if len(matched) == frame.keypoints.shape[0]:  # the usual bracket: nobody left over, nothing to append
            return None
        rest = np.ones(frame.keypoints.shape[0], dtype=bool)
        rest[matched] = False
        out = [frame.keypoints[rest], frame.confidences[rest]]
        if with_und:
            assert frame.undistorted is not None
            out.append(frame.undistorted[rest])
        return out

    def at(self, alpha: float) -> Detections2D:
        """The people at ``alpha`` in [0, 1] (0 = frame a): matched pairs blended, then the unmatched people of the
        nearer frame passed through (those of the farther one left out)."""
        rest = self._rest[0 if alpha <= 0.5 else 1]
        if not len(self._ca) and rest is None:
            return Detections2D.empty(self.n_kp)
        in_a, ca, cb, both = self._in_a, self._ca, self._cb, self._both
        cf = np.where(both, ca + alpha * self._dc, np.where(in_a, ca * (1.0 - alpha), cb * alpha))
        both_xy = both[..., None]
        blended = [np.where(both_xy, pa + alpha * step, one) for pa, step, one in self._points]
        und = blended[1] if len(blended) > 1 else None
        if rest is None:
            return Detections2D(blended[0], cf, und)
        if und is not None:
            und = np.concatenate((und, rest[2]))
        return Detections2D(np.concatenate((blended[0], rest[0])), np.concatenate((cf, rest[1])), und)
