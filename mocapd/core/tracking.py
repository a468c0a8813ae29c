"""Tracked subjects over time: enrolment, bystander rejection and release (seed 003 §3.3.1 and beyond).

Each frame the :class:`~mocapd.core.sorting.DetectionSorter` gives 3D candidates; enrolled subjects take theirs
(Algorithm 1). Candidates no subject took are *tentative* people, followed frame to frame by proximity:

- with designated start positions (the seed's way) a tentative person standing within ``start_radius`` of a
  free start position for ``enrol_after_s`` becomes a subject;
- without them, a tentative person becomes a subject, up to ``max_subjects``, as soon as the views agree on them:
  seen inside the capture volume in ``enrol_frames`` frames by at least ``enrol_views`` cameras each (as many as
  the rig has, when fewer), every sighting within ``max_interframe_movement`` of the last (a consistent
  triangulation: the same 3D person, not views that paired up once), no gap longer than ``tentative_gap_s``, and
  for at least ``enrol_after_s``.

The evidence rule (issue 41): a person is published at their 3rd agreeing frame, once ``enrol_after_s`` has passed.
One frame's candidate can be two people's views paired up across a near-degenerate camera pair, or a
false-positive detection matched by chance, but such a pairing does not hold its place frame after frame; a real
person does from their first frames. A *frame* is an observation, not an update: the live daemon updates the
tracker on every output tick (60 Hz) from detections its timelines hold or interpolate between detector passes, so
it passes, per camera, the detection frame each camera's detections come from (``frames`` of :meth:`update`). A
sighting counts as a new frame only when at least ``enrol_views`` of its cameras each show another frame than the
one they showed at the person's last counted sighting: ticks that replay one detector pass are one sighting,
however many. And a sighting counts only when its triangulated body is human-sized (:func:`body_scale`): two
cameras' detections of two different people far away can meet in a consistent but tiny "person" inside the
volume, pass after pass (the camera demo's third identity with this rule: nose to knees 0.4 m, limbs at 0.37 of
an adult's).

A candidate no subject took may be a subject's *other views*: one person whose views disagree (two cameras'
keypoints against the other two's) comes out of the sorter as two candidates, each seen by its own pair of cameras.
Such a candidate joins the subject's detections rather than being enrolled as someone new (the rule:
:meth:`SubjectTracker._hold_other_views`; issue 39, the camera demo's third identity).

Everyone else is a bystander. A subject not seen for ``grace_period_s`` is released. Time is passed in (int64
nanoseconds); nothing here reads a clock.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from mocapd.core.body_size import COCO17_NAMES
from mocapd.core.camera import Camera
from mocapd.core.camera_watch import row_medians
from mocapd.core.norms import norms
from mocapd.core.sorting import Candidate, Detections2D, DetectionSorter, mean_keypoint_distance
from mocapd.errors import InputError

FloatArray = NDArray[np.float64]

_NS = 1_000_000_000

# Segments of a standing adult as fractions of the height (Winter, Biomechanics and Motor Control of Human
# Movement, 4th ed., fig. 4.1), each left and right: upper arm, forearm, thigh, shank, shoulder to hip.
_SEGMENTS = (("shoulder", "elbow", 0.186), ("elbow", "wrist", 0.146), ("hip", "knee", 0.245),
             ("knee", "ankle", 0.246), ("shoulder", "hip", 0.288))  # fmt: skip
_ADULT_M = 1.75
HUMAN_SCALE = (0.55, 1.6)
"""A sighting's :func:`body_scale` must lie in this range (a 0.96 m child to a 2.8 m giant): a person, not the
meeting point of two far-away people's rays."""


@dataclass(frozen=True)
class TrackingOptions:
    """Enrolment and release of subjects."""

    max_subjects: int = 4
    """At most this many subjects are tracked; further people are bystanders."""
    volume_min: tuple[float, float] = (-2.5, -2.5)
    """Capture volume, floor rectangle (x, z) minimum corner (m). People outside it are never enrolled."""
    volume_max: tuple[float, float] = (2.5, 2.5)
    """Capture volume (x, z) maximum corner (m)."""
    enrol_after_s: float = 1.0
    """A person must be seen at least this long (inside the volume / at a start position) to become a subject."""
    enrol_frames: int = 3
    """...and in this many distinct detection frames (sightings that agree, see the module docstring)."""
    enrol_views: int = 2
    """A sighting counts when this many cameras see the person (or every camera of a smaller rig)."""
    tentative_gap_s: float = 0.3
    """A tentative person unseen for longer than this starts over."""
    grace_period_s: float = 2.0
    """A subject unseen for longer than this is released."""
    start_positions: tuple[tuple[float, float], ...] = ()
    """Designated start positions (x, z) (m). When given, subjects enrol only there (the seed's way)."""
    start_radius: float = 0.5
    """How close (m, on the floor) to a start position a person must stand to enrol there."""


@dataclass
class Subject:
    """A tracked person."""

    id: int
    last_points: FloatArray  # (n_kp, 3)
    last_seen_ns: int
    enrolled_ns: int
    detections: dict[int, int] = field(default_factory=dict)  # this frame: camera -> 2D person index
    seen: bool = False  # seen this frame


@dataclass
class _Tentative:
    points: FloatArray
    first_ns: int
    last_ns: int
    start_index: int  # designated start position it stands at, or -1
    sightings: int = 0  # distinct frames seen by enough views
    counted: dict[int, int] = field(default_factory=dict)  # camera -> its frame at the last counted sighting


@dataclass(frozen=True)
class TrackingEvent:
    """Something the operator should see in status: ``kind`` is ``enrolled`` or ``released``."""

    t_ns: int
    kind: str
    subject: int


@dataclass(frozen=True)
class FrameAssignment:
    """The result of one frame.

    Attributes
    ----------
    subjects : list of Subject
        Every tracked subject (``seen`` tells whether it was assigned this frame; ``detections`` its 2D people).
    bystanders : int
        3D candidates this frame that belong to no subject.
    events : list of TrackingEvent
    """

    subjects: list[Subject]
    bystanders: int
    events: list[TrackingEvent]


class SubjectTracker:
    """Sorts each frame's detections into enrolled subjects and manages enrolment and release."""

    def __init__(self, sorter: DetectionSorter, options: TrackingOptions | None = None) -> None:
        self.sorter = sorter
        self.options = options if options is not None else TrackingOptions()
        o = self.options
        if min(o.max_subjects, o.enrol_after_s, o.grace_period_s, o.enrol_frames, o.enrol_views) < 0:
            raise InputError("tracking options must be non-negative")
        self.subjects: list[Subject] = []
        self._tentative: list[_Tentative] = []
        self._next_id = 1
        self._frames: list[int] = []  # this update's frame per camera (see update)

    def update(self, t_ns: int, detections: list[Detections2D], frames: Sequence[int] | None = None) -> FrameAssignment:
        """Process one frame's detections (one :class:`Detections2D` per camera) at time ``t_ns``.

        ``frames`` names, per camera, the observation its detections come from (the live daemon: the capture time
        of the detection frame sampled, :attr:`~mocapd.pipeline.keypoint_timeline.TimelineSample.frame_ns`); two
        updates with the same value for a camera saw the same frame of it, which counts once towards enrolment.
        None: every update is a new frame of every camera (a caller that updates once per detection frame).
        """
        if frames is not None and len(frames) != len(detections):
            raise InputError(f"{len(frames)} frame times for {len(detections)} cameras")
        self._frames = [t_ns] * len(detections) if frames is None else list(frames)
        cands = self.sorter.candidates(detections)
        for s in self.subjects:
            s.seen = False
            s.detections = {}
        taken = self.sorter.assign(cands, [s.last_points for s in self.subjects])
        for s, c in zip(self.subjects, taken, strict=True):
            if c is not None:
                s.last_points, s.last_seen_ns, s.seen = c.points, t_ns, True
                s.detections = dict(c.sources)
        events = self._release(t_ns)
        free = [c for c, used in zip(cands, self._used_mask(cands, taken), strict=True) if not used]
        free = [c for c in free if not self._hold_other_views(c, detections)]
        enrolled, held = self._enrol(t_ns, free, detections)
        events += enrolled
        return FrameAssignment(list(self.subjects), len(free) - len(enrolled) - held, events)

    def _hold_other_views(self, c: Candidate, detections: list[Detections2D]) -> bool:
        """Whether ``c`` is a seen subject's other views, which it then takes (its detections join the subject's).

        The sorter clusters pairs of views by the distance of their triangulations (``same_person_distance``); a
        person whose views disagree (a camera's keypoints older than the others', a detector's bias in a few
        views) can come out as two candidates, each seen by its own pair of cameras: on the camera demo one
        person's pairs of views triangulated 0.3-0.6 m apart for seconds on end. The subject takes one; the other
        used to be enrolled as a second person after ``enrol_after_s``. It is the subject's when: no camera of
        ``c`` holds the subject this frame (one camera sees a person once: a different 2D person in a shared
        camera is a different person), the subject is the seen subject nearest to ``c`` and within
        ``max_interframe_movement`` (the reach :meth:`DetectionSorter.assign` gives it), and in every camera of
        either, the other's keypoints project nearest to the detection the first holds there: a second person
        that close would be a detection of its own in the subject's cameras. Absolute reprojection limits do not
        separate the two cases (such a subject's points reproject 20-35 px from its other views' detections in
        272-px images, where the other person's lie 20-100 px away), the nearest detection does.
        """
        seen = [s for s in self.subjects if s.seen and not (s.detections.keys() & c.sources.keys())]
        if not seen:
            return False
        to = {id(o): mean_keypoint_distance(c.points, o.last_points) for o in self.subjects if o.seen}
        dist = [to[id(s)] for s in seen]
        k = int(np.argmin(dist))
        s = seen[k]
        nearest_all = min(to.values())
        if dist[k] >= self.sorter.options.max_interframe_movement or dist[k] > nearest_all:
            return False
        partner = self.sorter._partner(c.points.shape[0])
        cams, min_cf = self.sorter.cameras, self.sorter.options.min_confidence
        checked = [_nearest_is(cams[cam], c.points, detections[cam], p, partner, min_cf)
                   for cam, p in s.detections.items()]  # fmt: skip
        checked += [_nearest_is(cams[cam], s.last_points, detections[cam], p, partner, min_cf)
                    for cam, p in c.sources.items()]  # fmt: skip
        if False in checked or checked.count(True) < 2:
            return False
        s.detections.update(c.sources)
        return True

    @staticmethod
    def _used_mask(cands: list[Candidate], taken: list[Candidate | None]) -> list[bool]:
        ids = {id(c) for c in taken if c is not None}
        return [id(c) in ids for c in cands]

    def _release(self, t_ns: int) -> list[TrackingEvent]:
        keep, events = [], []
        for s in self.subjects:
            if (t_ns - s.last_seen_ns) > self.options.grace_period_s * _NS:
                events.append(TrackingEvent(t_ns, "released", s.id))
            else:
                keep.append(s)
        self.subjects = keep
        return events

    def _inside(self, c: Candidate) -> bool:
        x, _, z = c.centre
        (x0, z0), (x1, z1) = self.options.volume_min, self.options.volume_max
        return bool(x0 <= x <= x1 and z0 <= z <= z1)

    def _start_index(self, c: Candidate) -> int:
        """The free designated start position the candidate stands at, or -1."""
        o = self.options
        taken = {t.start_index for t in self._tentative}
        x, _, z = c.centre
        for i, (sx, sz) in enumerate(o.start_positions):
            if np.hypot(x - sx, z - sz) <= o.start_radius and i not in taken:
                return i
        return -1

    def _enrol(
        self, t_ns: int, free: list[Candidate], detections: list[Detections2D]
    ) -> tuple[list[TrackingEvent], int]:
        """Tentative people followed, confirmed ones enrolled: the enrolment events, and how many of ``free`` were
        the other views of a person enrolled in this frame (:meth:`_hold_other_views`)."""
        o = self.options
        gap = o.tentative_gap_s * _NS
        self._tentative = [t for t in self._tentative if t_ns - t.last_ns <= gap]
        events: list[TrackingEvent] = []
        matched: set[int] = set()
        held = 0
        for c in free:
            if events and self._hold_other_views(c, detections):
                held += 1  # the other views of a person enrolled a moment ago, in this frame
                continue
            eligible = self._inside(c)
            if o.start_positions:  # at a free start position, or still standing where a tentative one began
                near = any(mean_keypoint_distance(t.points, c.points) < o.start_radius for t in self._tentative)
                eligible = eligible and (self._start_index(c) >= 0 or near)
            if not eligible:
                continue
            best, best_d = None, np.inf
            for t in self._tentative:
                d = mean_keypoint_distance(t.points, c.points)
                if id(t) not in matched and d < best_d:
                    best, best_d = t, d
            if best is not None and best_d < self.sorter.options.max_interframe_movement:
                best.points, best.last_ns = c.points, t_ns
                matched.add(id(best))
            else:
                start = self._start_index(c) if o.start_positions else -1
                self._tentative.append(_Tentative(c.points, t_ns, t_ns, start))
                matched.add(id(self._tentative[-1]))
                best = self._tentative[-1]
            best.sightings += self._human_sized(c) and self._new_sighting(best, c)
            confirmed = best.sightings >= o.enrol_frames and best.last_ns - best.first_ns >= o.enrol_after_s * _NS
            if confirmed and len(self.subjects) < o.max_subjects:
                s = Subject(self._next_id, c.points, t_ns, t_ns, dict(c.sources), True)
                self._next_id += 1
                self.subjects.append(s)
                self._tentative = [t for t in self._tentative if t is not best]
                events.append(TrackingEvent(t_ns, "enrolled", s.id))
        return events, held

    def _human_sized(self, c: Candidate) -> bool:
        """Whether ``c`` may be a person by its size (:func:`body_scale`; True when its keypoints are not named
        or too few segments were triangulated: no verdict)."""
        n_kp = c.points.shape[0]
        names = self.sorter.keypoint_names
        if len(names) != n_kp:
            names = COCO17_NAMES if n_kp == len(COCO17_NAMES) else ()
        scale = body_scale(c.points, names)
        return scale is None or HUMAN_SCALE[0] <= scale <= HUMAN_SCALE[1]

    def _new_sighting(self, t: _Tentative, c: Candidate) -> bool:
        """Whether ``c`` is new evidence of ``t``: seen by ``enrol_views`` cameras (every camera of a smaller rig)
        that each show a frame other than the one they showed at ``t``'s last counted sighting. Interpolated or
        held ticks of one detector pass show the same frames: one sighting."""
        need = min(self.options.enrol_views, len(self.sorter.cameras))
        fresh = [cam for cam in c.sources if t.counted.get(cam) != self._frames[cam]]
        if len(c.sources) < need or len(fresh) < need:
            return False
        t.counted.update({cam: self._frames[cam] for cam in c.sources})
        return True


def body_scale(points: FloatArray, names: tuple[str, ...]) -> float | None:
    """How large the triangulated body ``points`` (n_kp, 3), keypoints named ``names``, is next to a 1.75 m adult:
    the median over the measured limb and trunk segments (:data:`_SEGMENTS`, left and right) of length / the
    adult's; None with fewer than 3 segments measured (no verdict)."""
    index = {n: i for i, n in enumerate(names)}
    ratios = []
    for a, b, fraction in _SEGMENTS:
        for side in ("left", "right"):
            i, j = index.get(f"{side}_{a}"), index.get(f"{side}_{b}")
            if i is not None and j is not None:
                d = float(np.linalg.norm(points[i] - points[j]))
                if np.isfinite(d):
                    ratios.append(d / (fraction * _ADULT_M))
    return float(np.median(ratios)) if len(ratios) >= 3 else None


def _nearest_is(
    camera: Camera,
    points: FloatArray,
    detections: Detections2D,
    person: int,
    partner: NDArray[np.int64],
    min_confidence: float,
) -> bool | None:
    """Whether ``points`` (n_kp, 3) project nearest to 2D person ``person`` of ``detections`` (median distance over
    the keypoints confident in the detection that ``points`` has, a left/right pair as labelled or exchanged: a view
    may be flipped); None when fewer than 5 keypoints project into the image (no evidence either way)."""
    uv = camera.project(points)
    inside = np.isfinite(uv).all(axis=1) & (uv[:, 0] >= 0) & (uv[:, 0] < camera.width)
    inside &= (uv[:, 1] >= 0) & (uv[:, 1] < camera.height)
    if inside.sum() < 5:
        return None
    kp, cf = detections.keypoints, detections.confidences
    d = np.minimum(norms(kp - uv), norms(kp - uv[partner]))  # (n_people, n_kp)
    use = inside & (cf >= min_confidence) & np.isfinite(d)
    ok = use.sum(axis=1) >= 5
    if not ok[person]:
        return None
    # Each person's median of the distances kept: np.nanmedian's to the bit (row_medians: np.median of the entries
    # used), without its masked-array path for small arrays (~20 times slower); a person with fewer than 5 is
    # never the nearest (np.nanmedian of their zeros was replaced by inf)
    med = np.where(ok, row_medians(d, use & ok[:, None]), np.inf)
    return bool(int(np.argmin(med)) == person)
