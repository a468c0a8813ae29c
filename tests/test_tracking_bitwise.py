"""The tracker's per-tick update made cheaper (issue 39: it runs on every output tick on the event loop) sorts and
tracks as before: the sorting and tracking code before issue 39 (kept here verbatim as the oracle: the candidates'
glue, claims, assignment, the keypoint distance, a candidate's centre, the other-views rule and enrolment) and the
new code (its pairing kernel giving up early on pairs that cannot pass) update two trackers on the same
detections, tick after tick, and give the same candidates (points, views and errors bit for bit), subjects,
detections, bystanders and events; on several people walking among four cameras with people missing from views,
a left/right-swapped view, a stray detection, low-confidence and NaN keypoints, and people leaving and coming
back."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
from numpy.typing import NDArray

from mocapd.core import _sorting_kernel
from mocapd.core.assignment import linear_sum_assignment
from mocapd.core.camera import MIN_DEPTH, Camera
from mocapd.core.lr_flips import COCO17_LR_PAIRS, lr_pairs
from mocapd.core.sorting import Candidate, Detections2D, DetectionSorter, mean_keypoint_distance
from mocapd.core.tracking import (
    _NS,
    FrameAssignment,
    Subject,
    SubjectTracker,
    TrackingEvent,
    TrackingOptions,
    _nearest_is,
    _Tentative,
)
from mocapd.errors import InputError
from mocapd.sim.world import SyntheticWorld

FloatArray = NDArray[np.float64]


def old_mean_keypoint_distance(a: FloatArray, b: FloatArray) -> float:
    """Mean distance over keypoints present in both (inf when none are)."""
    d = np.linalg.norm(a - b, axis=-1)
    ok = np.isfinite(d)
    return float(d[ok].mean()) if np.any(ok) else np.inf


def old_centre(c: Candidate) -> FloatArray:
    return np.asarray(np.nanmean(c.points, axis=0))


def old_resolve_claims(cands: list[Candidate]) -> list[Candidate]:
    def rank(c: Candidate) -> tuple[int, float]:
        return (-len(c.sources), float(np.mean(list(c.errors.values()))))

    owner: dict[tuple[int, int], int] = {}
    order = sorted(range(len(cands)), key=lambda k: rank(cands[k]))
    kept: list[Candidate] = []
    for k in order:
        c = cands[k]
        free = {cam: p for cam, p in c.sources.items() if (cam, p) not in owner}
        if len(free) < 2:
            continue
        for cam, p in free.items():
            owner[(cam, p)] = k
        kept.append(Candidate(c.points, free, {cam: c.errors[cam] for cam in free}))
    return kept


class OldSorter(DetectionSorter):
    """``DetectionSorter`` before issue 39: ``_partner``, ``candidates`` and ``assign`` verbatim, but for the
    kernel's ``prune`` argument, False: the kernel's code before issue 39 (the pruning is one skipped branch)."""

    def _partner(self, n_kp: int) -> NDArray[np.int64]:
        partner = np.arange(n_kp, dtype=np.int64)
        if len(self.keypoint_names) == n_kp:
            pairs = lr_pairs(self.keypoint_names)
        else:
            pairs = COCO17_LR_PAIRS if n_kp == 17 else ()
        for left, right in pairs:
            partner[left], partner[right] = right, left
        return partner

    def candidates(self, detections: list[Detections2D]) -> list[Candidate]:
        if len(detections) != len(self.cameras):
            raise InputError(f"sorting: {len(self.cameras)} cameras but detections for {len(detections)}")
        o = self.options
        counts = [len(d) for d in detections]
        if sum(1 for n in counts if n) < 2:
            return []
        n_kp = detections[0].keypoints.shape[1]
        kp = np.concatenate([d.keypoints for d in detections]).reshape(-1, n_kp, 2)
        usable = np.concatenate([d.confidences for d in detections]).reshape(-1, n_kp) >= o.min_confidence
        camera_of = np.repeat(np.arange(len(counts)), counts).astype(np.int64)
        person_of = np.concatenate([np.arange(n) for n in counts]).astype(np.int64)
        points, members, member_errors = _sorting_kernel.candidate_pairs(
            np.ascontiguousarray(kp), usable, camera_of, person_of, self._K, self._dist, self._R, self._t,
            self._widths, o.max_reprojection_error, o.min_shared_keypoints, o.same_person_distance, MIN_DEPTH,
            self._partner(n_kp), o.flip_aware, False,
        )  # fmt: skip
        cands = []
        for q in range(points.shape[0]):
            cams = np.flatnonzero(members[q] >= 0)
            cands.append(Candidate(points[q], {int(c): int(members[q, c]) for c in cams},
                                   {int(c): float(member_errors[q, c]) for c in cams}))  # fmt: skip
        return old_resolve_claims(cands)

    def assign(self, cands: list[Candidate], last_positions: list[FloatArray | None]) -> list[Candidate | None]:
        out: list[Candidate | None] = [None] * len(last_positions)
        if not cands or not last_positions:
            return out
        limit = self.options.max_interframe_movement
        dist = np.full((len(last_positions), len(cands)), np.inf)
        for i, last in enumerate(last_positions):
            if last is not None:
                for j, c in enumerate(cands):
                    dist[i, j] = old_mean_keypoint_distance(c.points, last)
        usable = dist < limit
        rows, cols = linear_sum_assignment(np.where(usable, dist, 1e6))
        for i, j in zip(rows, cols, strict=True):
            if usable[i, j]:
                out[i] = cands[j]
        return out


def old_nearest_is(
    camera: Camera,
    points: FloatArray,
    detections: Detections2D,
    person: int,
    partner: NDArray[np.int64],
    min_confidence: float,
) -> bool | None:
    """``tracking._nearest_is`` before the eighth session (``np.nanmedian``), verbatim."""
    uv = camera.project(points)
    inside = np.isfinite(uv).all(axis=1) & (uv[:, 0] >= 0) & (uv[:, 0] < camera.width)
    inside &= (uv[:, 1] >= 0) & (uv[:, 1] < camera.height)
    if inside.sum() < 5:
        return None
    kp, cf = detections.keypoints, detections.confidences
    d = np.minimum(np.linalg.norm(kp - uv, axis=-1), np.linalg.norm(kp - uv[partner], axis=-1))  # (n_people, n_kp)
    d = np.where(inside & (cf >= min_confidence) & np.isfinite(d), d, np.nan)
    ok = np.isfinite(d).sum(axis=1) >= 5
    if not ok[person]:
        return None
    med = np.where(ok, np.nanmedian(np.where(ok[:, None], d, 0.0), axis=1), np.inf)
    return bool(int(np.argmin(med)) == person)


class OldTracker(SubjectTracker):
    """``SubjectTracker`` before issue 39: the methods that read distances and centres, verbatim (with the old
    distance and centre)."""

    def _hold_other_views(self, c: Candidate, detections: list[Detections2D]) -> bool:
        seen = [s for s in self.subjects if s.seen and not (s.detections.keys() & c.sources.keys())]
        if not seen:
            return False
        dist = [old_mean_keypoint_distance(c.points, s.last_points) for s in seen]
        k = int(np.argmin(dist))
        s = seen[k]
        nearest_all = min(old_mean_keypoint_distance(c.points, o.last_points) for o in self.subjects if o.seen)
        if dist[k] >= self.sorter.options.max_interframe_movement or dist[k] > nearest_all:
            return False
        partner = self.sorter._partner(c.points.shape[0])
        cams, min_cf = self.sorter.cameras, self.sorter.options.min_confidence
        checked = [old_nearest_is(cams[cam], c.points, detections[cam], p, partner, min_cf)
                   for cam, p in s.detections.items()]  # fmt: skip
        checked += [old_nearest_is(cams[cam], s.last_points, detections[cam], p, partner, min_cf)
                    for cam, p in c.sources.items()]  # fmt: skip
        if False in checked or checked.count(True) < 2:
            return False
        s.detections.update(c.sources)
        return True

    def _inside(self, c: Candidate) -> bool:
        x, _, z = old_centre(c)
        (x0, z0), (x1, z1) = self.options.volume_min, self.options.volume_max
        return bool(x0 <= x <= x1 and z0 <= z <= z1)

    def _start_index(self, c: Candidate) -> int:
        o = self.options
        taken = {t.start_index for t in self._tentative}
        x, _, z = old_centre(c)
        for i, (sx, sz) in enumerate(o.start_positions):
            if np.hypot(x - sx, z - sz) <= o.start_radius and i not in taken:
                return i
        return -1

    def _enrol(
        self, t_ns: int, free: list[Candidate], detections: list[Detections2D]
    ) -> tuple[list[TrackingEvent], int]:
        o = self.options
        gap = o.tentative_gap_s * _NS
        self._tentative = [t for t in self._tentative if t_ns - t.last_ns <= gap]
        events: list[TrackingEvent] = []
        matched: set[int] = set()
        held = 0
        for c in free:
            if events and self._hold_other_views(c, detections):
                held += 1
                continue
            eligible = self._inside(c)
            if o.start_positions:
                near = any(old_mean_keypoint_distance(t.points, c.points) < o.start_radius for t in self._tentative)
                eligible = eligible and (self._start_index(c) >= 0 or near)
            if not eligible:
                continue
            best, best_d = None, np.inf
            for t in self._tentative:
                d = old_mean_keypoint_distance(t.points, c.points)
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


def _same_candidates(a: list[Candidate], b: list[Candidate]) -> None:
    assert len(a) == len(b)
    for x, y in zip(a, b, strict=True):
        assert np.array_equal(x.points, y.points, equal_nan=True)
        assert (x.sources, x.errors) == (y.sources, y.errors)
        assert np.array_equal(x.centre, old_centre(y), equal_nan=True)


def _same_frames(a: FrameAssignment, b: FrameAssignment) -> None:
    assert (a.bystanders, a.events) == (b.bystanders, b.events)
    assert len(a.subjects) == len(b.subjects)
    for s, o in zip(a.subjects, b.subjects, strict=True):
        assert (s.id, s.last_seen_ns, s.enrolled_ns, s.detections, s.seen) == (
            o.id, o.last_seen_ns, o.enrolled_ns, o.detections, o.seen)  # fmt: skip
        assert np.array_equal(s.last_points, o.last_points, equal_nan=True)


def _ticks(seed: int, n_people: int, n_ticks: int) -> list[list[Detections2D]]:
    """60 Hz ticks of a 4-camera rig (lens distortion on), with views missing people, a view's left and right
    exchanged, a stray detection, keypoints of low confidence, a NaN keypoint, and everyone gone for a while."""
    world = SyntheticWorld(4, n_people, 0, seed=seed)
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n_ticks):
        ticks = []
        for cam in range(4):
            d = world.detections(cam, k / 60.0, rng, noise_px=2.0)
            kp, cf = d.keypoints.copy(), d.confidences.copy()
            if len(d) and rng.random() < 0.15:  # a person missing from this view
                keep = np.arange(len(d)) != rng.integers(len(d))
                kp, cf = kp[keep], cf[keep]
            if len(kp) and rng.random() < 0.1:  # this view's left and right exchanged for one person
                kp[0, [5, 6, 7, 8, 9, 10]] = kp[0, [6, 5, 8, 7, 10, 9]]
            if rng.random() < 0.1:  # a stray detection
                kp = np.concatenate([kp, rng.uniform(0.0, 600.0, (1, 17, 2))])
                cf = np.concatenate([cf, rng.uniform(0.2, 0.9, (1, 17))])
            cf = np.where(rng.random(cf.shape) < 0.1, 0.1, cf)
            if len(kp) and rng.random() < 0.05:  # a keypoint not a number (the kernel then does not prune)
                kp[rng.integers(len(kp)), rng.integers(17)] = np.nan
            if 400 <= k < 560:  # everyone gone: subjects released after the grace period
                kp, cf = kp[:0], cf[:0]
            ticks.append(Detections2D(kp, cf))
        out.append(ticks)
    return out


def _run(seed: int, n_people: int, n_ticks: int, options: TrackingOptions) -> int:
    world = SyntheticWorld(4, n_people, 0, seed=seed)
    cams = [dataclasses.replace(c, dist=np.array([-0.21, 0.08, 0.0012, -0.0007, -0.012])) for c in world.cameras]
    new, old = DetectionSorter(cams), OldSorter(cams)
    tracker_new, tracker_old = SubjectTracker(new, options), OldTracker(old, options)
    events = 0
    for k, dets in enumerate(_ticks(seed, n_people, n_ticks)):
        _same_candidates(new.candidates(dets), old.candidates(dets))
        frames = [k // 2] * 4  # two ticks a detector pass
        t = k * 16_666_667
        a, b = tracker_new.update(t, dets, frames), tracker_old.update(t, dets, frames)
        _same_frames(a, b)
        events += len(a.events)
    return events


def test_the_tracker_sorts_and_tracks_as_before() -> None:
    events = _run(3, 3, 720, TrackingOptions())
    assert events >= 6  # three enrolled, released while everyone was gone, enrolled again


def test_with_start_positions_as_before() -> None:
    options = TrackingOptions(start_positions=((0.0, 2.3), (1.1, 0.35)), start_radius=1.0)
    assert _run(5, 2, 300, options) >= 1


def test_the_keypoint_distance_and_centre_as_before() -> None:
    rng = np.random.default_rng(0)
    for _ in range(300):
        a, b = rng.normal(0.0, 1.0, (2, 17, 3))
        a[rng.random(17) < 0.3] = np.nan
        b[rng.random(17) < 0.3, rng.integers(0, 3)] = np.nan
        assert mean_keypoint_distance(a, b) == old_mean_keypoint_distance(a, b)
        c = Candidate(a)
        assert np.array_equal(c.centre, old_centre(c), equal_nan=True)
    none = np.full((17, 3), np.nan)
    assert mean_keypoint_distance(none, none) == old_mean_keypoint_distance(none, none) == np.inf


def test_the_nearest_detection_is_judged_as_before() -> None:
    """``_nearest_is`` (each other-views check of a split person) decides as with ``np.nanmedian``: 1 to 4 people in
    the view, points partly outside the image, behind the camera or NaN, low confidences, NaN keypoints, people with
    fewer than 5 usable keypoints, flipped views, the partner exchanged or not."""
    rng = np.random.default_rng(8)
    world = SyntheticWorld(4, 3, 0, seed=2)
    cams = [dataclasses.replace(c, dist=np.array([-0.21, 0.08, 0.0012, -0.0007, -0.012])) for c in world.cameras]
    partner = DetectionSorter(cams)._partner(17)
    decided = {True: 0, False: 0, None: 0}
    for k in range(600):
        cam: Camera = cams[k % 4]
        dets = world.detections(k % 4, k / 60.0, rng, 2.0)
        n = int(rng.integers(1, 5))
        kp = rng.normal(0.0, 1.0, (n, 17, 2)) * 40.0 + rng.uniform(0.0, 600.0, (n, 1, 2))
        m = min(n, len(dets.keypoints))
        kp[:m] = dets.keypoints[:m] + rng.normal(0.0, 3.0, (m, 17, 2))
        cf = rng.uniform(0.0, 1.0, (n, 17))
        cf[rng.random((n, 17)) < 0.1] = 0.0
        kp[rng.random((n, 17)) < 0.05] = np.nan
        if k % 9 == 0:
            cf[0, 5:] = 0.0  # fewer than 5 usable
        points = world.sites_at(int(rng.integers(0, 3)), k / 60.0) + rng.normal(0.0, 0.05, (17, 3))
        if k % 7 == 0:
            points[rng.random(17) < 0.4] = np.nan
        if k % 11 == 0:
            points += 3.0 * (cam.center - points.mean(axis=0))  # much of it behind the camera or outside the image
        d = Detections2D(kp, cf)
        for person in range(n):
            for min_cf in (0.0, 0.3):
                with np.errstate(invalid="ignore"), warnings.catch_warnings():
                    warnings.simplefilter("ignore")  # np.nanmedian of an all-NaN row warns
                    want = old_nearest_is(cam, points, d, person, partner, min_cf)
                got = _nearest_is(cam, points, d, person, partner, min_cf)
                assert got is want, (k, person)
                decided[want] += 1
    assert min(decided.values()) > 50, decided
