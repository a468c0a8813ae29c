"""How good are keypoints between detections: the live tracker (:mod:`mocapd.pipeline.keypoint_tracker`) replayed
on recorded or rendered frames under a live detection schedule, against a reference on every frame.

One camera's frames are replayed at their rate; the detector's output for frame ``n`` (``seeds``: every
``interval_frames``-th frame) reaches the tracker ``delay_frames`` later, as it would live, and the tracker steps
every ``track_every``-th frame. Three ways of having keypoints on a frame ``f`` are compared against the reference
of that frame (the detector run on every frame of real footage, or the truth of a rendered synthetic world):

* ``tracked``: what the tracker delivers for ``f`` (issue 31), available one frame's tracking after capture;
* ``interpolated``: the detections before and after ``f`` blended linearly, people matched as the scheduler's
  timeline does (:func:`~mocapd.pipeline.keypoint_timeline.interpolate_people`): the pipeline before issue 31,
  which has them only once the later detection arrived, ``interval + delay`` after the earlier frame;
* ``held``: the newest detection that has arrived by ``f`` (no waiting, no tracking).

Each method's people are matched to the reference's (Hungarian assignment on mean keypoint distance, accepted below
``MATCH_PX``); per keypoint with a reference (confidence >= 0.5 or visible truth) and an estimate (confidence > 0):
the distance in pixels, by joint group and by the age of the estimate (frames since the detection it comes from).
``coverage`` is the share of reference keypoints of matched people that the method gives.

:func:`held_out_view` is the multi-view check on calibrated footage: each camera's subject triangulated from the
other cameras' keypoints of a method, reprojected into the camera and compared with its own reference detection;
the real-video evaluation of issue 29 (``mocapd eval video``) builds the reusable held-out-view error, and
``held_out_view(..., error=...)`` takes that function in place of the simple confidence-weighted DLT here.

:func:`people_replay` is what the keypoints give the daemon downstream: every camera's keypoint sets pushed into its
scheduler timeline as they become available, sampled at each 60 Hz tick a latency behind, and sorted into people
by the daemon's own sorting and enrolment (:class:`~mocapd.core.people.PeopleTracker`) on calibrated footage:
how many of the ticks see each subject, how many identities were enrolled.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment

from mocapd.core.camera import Camera, triangulate
from mocapd.core.people import PeopleTracker
from mocapd.core.sorting import Detections2D, DetectionSorter
from mocapd.core.tracking import SubjectTracker, TrackingOptions
from mocapd.pipeline.detector_config import TrackingConfig
from mocapd.pipeline.keypoint_timeline import DetectionTimeline, interpolate_people
from mocapd.pipeline.keypoint_tracker import JOINT_GROUPS, KeypointTracker, joint_group

FloatArray = NDArray[np.float64]
Gray = NDArray[np.uint8]
MATCH_PX = 80.0
CONFIDENT = 0.5
METHODS = ("tracked", "interpolated", "held")


@dataclass(frozen=True)
class Schedule:
    """A camera's live detection schedule, in frames of the camera."""

    fps: float = 60.0
    interval_frames: int = 9
    """Frames between two detections of the camera (9 at 60 fps: 150 ms)."""
    delay_frames: int = 6
    """Frames between a detected frame and its detections' arrival (6 at 60 fps: 100 ms)."""
    track_every: int = 2
    """The tracker steps every this many frames (2 at 60 fps: 30 Hz)."""

    def seconds(self, frames: float) -> float:
        return frames / self.fps


@dataclass(frozen=True)
class Reference:
    """The reference keypoints of one frame: positions (P, K, 2) and which are known (P, K)."""

    keypoints: FloatArray
    known: NDArray[np.bool_]


@dataclass(frozen=True)
class Estimate:
    """A method's people on one frame, how old they are (frames since the detection they come from) and how long
    after the frame's capture the method has them (frames)."""

    people: Detections2D
    age_frames: int
    latency_frames: int


def replay_tracker(
    grays: Sequence[Gray],
    seeds: Mapping[int, Detections2D],
    schedule: Schedule,
    options: TrackingConfig,
    factor: int,
    names: Sequence[str] = (),
) -> tuple[dict[int, Estimate], KeypointTracker]:
    """One camera's tracker over ``grays`` (frames at the tracking resolution, downsampled by ``factor``) with
    the detections ``seeds`` (by frame) arriving ``delay_frames`` late. Returns its output on every tracked frame
    and the tracker (its own tracked-vs-detected statistics)."""
    n_kp = next(iter(seeds.values())).keypoints.shape[1]
    tracker = KeypointTracker(n_kp, dataclasses.replace(options, downsample=factor), names)
    arriving: dict[int, list[int]] = {}
    for n in seeds:
        arriving.setdefault(n + schedule.delay_frames, []).append(n)
    ns = 1e9 / schedule.fps
    out: dict[int, Estimate] = {}
    last_seed = None
    for f, gray in enumerate(grays):
        for n in arriving.get(f, []):
            tracker.detected(n, round(n * ns), seeds[n], grays[n])
            last_seed = n if last_seed is None else max(last_seed, n)
        if f % schedule.track_every:
            continue
        people = tracker.step(f, round(f * ns), gray)
        if people is not None and last_seed is not None:
            out[f] = Estimate(people, f - last_seed, 0)
    return out, tracker


def detection_baselines(
    seeds: Mapping[int, Detections2D], schedule: Schedule, n_frames: int
) -> tuple[dict[int, Estimate], dict[int, Estimate]]:
    """(interpolated, held) estimates on every frame, from the detections ``seeds`` (see the module docstring)."""
    frames = sorted(seeds)
    interpolated: dict[int, Estimate] = {}
    held: dict[int, Estimate] = {}
    for f in range(n_frames):
        before = [n for n in frames if n <= f]
        after = [n for n in frames if n > f]
        if before and after:
            a, b = before[-1], after[0]
            people = interpolate_people(seeds[a], seeds[b], (f - a) / (b - a), MATCH_PX) if f != a else seeds[a]
            interpolated[f] = Estimate(people, min(f - a, b - f), (b - f) + schedule.delay_frames)
        arrived = [n for n in frames if n + schedule.delay_frames <= f]
        if arrived:
            n = arrived[-1]
            held[f] = Estimate(seeds[n], f - n, 0)
    return interpolated, held


@dataclass
class Comparison:
    """Per compared keypoint: error px, joint group index, age in frames; and how much of the reference was given."""

    errors: list[float]
    groups: list[int]
    ages: list[int]
    latencies: list[int]
    reference_keypoints: int = 0
    given_keypoints: int = 0

    @staticmethod
    def empty() -> Comparison:
        return Comparison([], [], [], [])

    def add(self, other: Comparison) -> None:
        self.errors += other.errors
        self.groups += other.groups
        self.ages += other.ages
        self.latencies += other.latencies
        self.reference_keypoints += other.reference_keypoints
        self.given_keypoints += other.given_keypoints


def match_people(est: Detections2D, ref: Reference) -> list[tuple[int, int]]:
    """(estimate, reference) person pairs: Hungarian assignment on the mean distance of the keypoints both know."""
    if len(est) == 0 or ref.keypoints.shape[0] == 0:
        return []
    both = (est.confidences[:, None, :] > 0) & ref.known[None, :, :]
    d = np.linalg.norm(est.keypoints[:, None] - ref.keypoints[None, :], axis=-1)
    n = both.sum(axis=-1)
    mean = np.where(n > 0, np.where(both, d, 0.0).sum(axis=-1) / np.maximum(n, 1), np.inf)
    rows, cols = linear_sum_assignment(np.where(np.isfinite(mean), mean, 1e12))
    return [(int(r), int(c)) for r, c in zip(rows, cols, strict=True) if mean[r, c] <= MATCH_PX]


def compare(
    estimates: Mapping[int, Estimate], reference: Mapping[int, Reference], groups: Sequence[int], frames: Sequence[int]
) -> Comparison:
    """Errors of ``estimates`` against ``reference`` on ``frames`` (where both exist)."""
    out = Comparison.empty()
    g = np.asarray(groups)
    for f in frames:
        est, ref = estimates.get(f), reference.get(f)
        if est is None or ref is None:
            continue
        for i, j in match_people(est.people, ref):
            known = ref.known[j]
            given = known & (est.people.confidences[i] > 0)
            out.reference_keypoints += int(known.sum())
            out.given_keypoints += int(given.sum())
            err = np.linalg.norm(est.people.keypoints[i] - ref.keypoints[j], axis=-1)[given]
            out.errors += err.tolist()
            out.groups += g[given].tolist()
            out.ages += [est.age_frames] * int(given.sum())
            out.latencies += [est.latency_frames] * int(given.sum())
    return out


def summary(c: Comparison, schedule: Schedule) -> dict[str, Any]:
    """JSON-able: error median/p90 (all, per joint group), coverage, age and latency of the estimates (ms)."""
    e = np.asarray(c.errors)
    gr = np.asarray(c.groups)

    def pct(v: NDArray[np.float64]) -> dict[str, float | int | None]:
        if v.size == 0:
            return {"n": 0, "median": None, "p90": None}
        return {"n": int(v.size), "median": round(float(np.median(v)), 2), "p90": round(float(np.percentile(v, 90)), 2)}

    ms = 1e3 / schedule.fps
    return {
        "error_px": pct(e),
        "by_joint_group": {name: pct(e[gr == k])["median"] for k, name in enumerate(JOINT_GROUPS) if np.any(gr == k)},
        "coverage": round(c.given_keypoints / c.reference_keypoints, 3) if c.reference_keypoints else None,
        "age_ms_median": round(float(np.median(c.ages)) * ms, 1) if c.ages else None,
        "latency_ms_median": round(float(np.median(c.latencies)) * ms, 1) if c.latencies else None,
        "latency_ms_max": round(float(np.max(c.latencies)) * ms, 1) if c.latencies else None,
    }  # fmt: skip


def group_indices(names: Sequence[str]) -> list[int]:
    """Joint group index (:data:`JOINT_GROUPS`) of each keypoint name."""
    return [JOINT_GROUPS.index(joint_group(n)) for n in names]


def held_out_view(
    cameras: Sequence[Camera],
    subject: Mapping[int, Sequence[FloatArray | None]],
    reference: Mapping[int, Sequence[FloatArray | None]],
    error: Callable[[Sequence[Camera], FloatArray, FloatArray, int], FloatArray] | None = None,
) -> dict[str, Any]:
    """Held-out-view error of a method's keypoints of one subject: per frame and camera ``k``, the subject
    triangulated from the other cameras, reprojected into ``k`` and compared with ``k``'s reference.

    Parameters
    ----------
    cameras : sequence of Camera
        Calibrated at the images' size.
    subject : mapping frame -> per camera (K, 3) array (x, y, confidence) or None
        The method's keypoints of the subject on that frame (None: the method has none).
    reference : mapping frame -> per camera (K, 3) array or None
        The reference (a detection of the subject on that very frame).
    error : callable, optional
        ``error(cameras, uvc (n_cams, K, 3), ref (K, 3), k) -> (K,) px`` (NaN where not comparable); default the
        confidence-weighted DLT of :func:`~mocapd.core.camera.triangulate` from the other views reprojected into
        ``k``. Issue 29's held-out-view function plugs in here.

    Returns
    -------
    dict
        Median and p90 px over every compared keypoint, and per camera.
    """
    err_fn = error if error is not None else _dlt_held_out
    per_cam: dict[int, list[float]] = {k: [] for k in range(len(cameras))}
    for f, views in subject.items():
        ref = reference.get(f)
        if ref is None:
            continue
        for k, rk in enumerate(ref):
            others = [c for c in range(len(cameras)) if c != k and views[c] is not None]
            if rk is None or len(others) < 2:
                continue
            uvc = np.stack([v if v is not None else np.zeros_like(rk) for v in views])
            uvc[k, :, 2] = 0.0  # the held-out camera does not vote
            uvc[[c for c in range(len(cameras)) if views[c] is None], :, 2] = 0.0
            e = err_fn(cameras, uvc, rk, k)
            per_cam[k] += [float(x) for x in e[np.isfinite(e)]]
    every = np.asarray([x for v in per_cam.values() for x in v])

    def pct(v: Sequence[float] | NDArray[np.float64]) -> dict[str, float | int | None]:
        a = np.asarray(v, np.float64)
        if a.size == 0:
            return {"n": 0, "median": None, "p90": None}
        return {"n": int(a.size), "median": round(float(np.median(a)), 2), "p90": round(float(np.percentile(a, 90)), 2)}

    return {"all": pct(every), "per_camera": {cameras[k].name: pct(v) for k, v in per_cam.items()}}


def _dlt_held_out(cameras: Sequence[Camera], uvc: FloatArray, ref: FloatArray, k: int) -> FloatArray:
    """Reprojection into camera ``k`` of the confidence-weighted DLT of the other views, minus ``ref``'s confident
    keypoints (px, NaN elsewhere)."""
    w = np.where(uvc[..., 2] >= CONFIDENT, uvc[..., 2], 0.0)
    X, ok = triangulate(list(cameras), uvc[..., :2], w)
    uv = cameras[k].project(X)
    e = np.linalg.norm(uv - ref[:, :2], axis=-1)
    return np.where(ok & (ref[:, 2] >= CONFIDENT) & np.isfinite(e), e, np.nan)


@dataclass(frozen=True)
class KeypointStream:
    """One camera's keypoint sets as the scheduler receives them: (capture frame, set, frame it is available at)."""

    sets: list[tuple[int, Detections2D, int]]


def tracked_stream(estimates: Mapping[int, Estimate]) -> KeypointStream:
    """The tracker's sets: available on their own frame (one frame's tracking after capture)."""
    return KeypointStream([(f, e.people, f) for f, e in sorted(estimates.items())])


def detection_stream(seeds: Mapping[int, Detections2D], schedule: Schedule) -> KeypointStream:
    """The detections themselves (the pipeline before issue 31): available ``delay_frames`` after their frame."""
    return KeypointStream([(n, d, n + schedule.delay_frames) for n, d in sorted(seeds.items())])


def people_replay(
    cameras: Sequence[Camera],
    streams: Sequence[KeypointStream],
    latency_frames: int,
    n_frames: int,
    fps: float = 60.0,
    tracking: TrackingOptions | None = None,
    hold_s: float = 0.5,
    max_gap_s: float = 2.0,
) -> dict[str, Any]:
    """People sorted by the daemon's rules from keypoint streams, one tick per frame ``latency_frames`` behind.

    Each tick ``k`` pushes every set available by frame ``k`` into its camera's timeline, samples all timelines at
    frame ``k - latency_frames`` (interpolation, a hold of ``hold_s``, gaps up to ``max_gap_s``: the camera demo's
    settings) and updates one :class:`~mocapd.core.people.PeopleTracker`. Returns the ticks after the first second,
    the mean number of people solved per tick, the share of ticks with at least one and with two, and the identities
    enrolled over the run.
    """
    ns = 1e9 / fps
    n_kp = next(s[1].keypoints.shape[1] for st in streams for s in st.sets)
    timelines = [DetectionTimeline(n_kp, max_age_ns=round(hold_s * 1e9), max_gap_ns=round(max_gap_s * 1e9))
                 for _ in cameras]  # fmt: skip
    tracker = PeopleTracker(SubjectTracker(DetectionSorter(list(cameras)), tracking))
    queues = [sorted(st.sets, key=lambda s: (s[2], s[0])) for st in streams]
    heads = [0] * len(queues)
    counts: list[int] = []
    identities: set[str] = set()
    start = round(fps)  # the first second: enrolment takes enrol_after_s
    for k in range(n_frames):
        for c, q in enumerate(queues):
            while heads[c] < len(q) and q[heads[c]][2] <= k:
                f, dets, _ = q[heads[c]]
                timelines[c].push(round(f * ns), dets)
                heads[c] += 1
        t = k - latency_frames
        if t < 0:
            continue
        samples = [tl.sample(round(t * ns)) for tl in timelines]
        frame = tracker.update(round(t * ns), [s.detections for s in samples], frames=[s.frame_ns for s in samples])
        identities.update(p.identity for p in frame.people)
        if k >= start:
            counts.append(len(frame.people))
    per_tick = np.asarray(counts, np.float64)
    n = int(per_tick.size)
    return {
        "ticks": n, "latency_ms": round(latency_frames / fps * 1e3, 1),
        "people_per_tick": round(float(per_tick.mean()), 3) if n else None,
        "ticks_with_someone": round(float(np.mean(per_tick >= 1)), 3) if n else None,
        "ticks_with_two": round(float(np.mean(per_tick >= 2)), 3) if n else None,
        "identities": len(identities),
    }  # fmt: skip
