"""Detection sorting (seed 003 Algorithm 1), enrolment, bystanders and release on synthetic multi-person scenes."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mocapd.core.camera import Camera
from mocapd.core.keypoints import coco17_targets
from mocapd.core.skeleton import Skeleton
from mocapd.core.sorting import Detections2D, DetectionSorter
from mocapd.core.synthetic import ring_rig, scene_detections, walking_path
from mocapd.core.tracking import SubjectTracker, TrackingOptions
from mocapd.errors import InputError

FPS = 30.0
NS = int(1e9 / FPS)


def _scene(n_frames: int, noise_px: float = 1.5, seed: int = 0):  # type: ignore[no-untyped-def]
    sk = Skeleton.from_height(1.75)
    cams = ring_rig(4, radius=4.5)
    people = [
        walking_path(sk, n_frames, (-0.8, -0.8), (-0.6, 0.9), seed=1, fps=FPS),
        walking_path(sk, n_frames, (0.9, 0.6), (0.7, -0.9), seed=2, fps=FPS),
        walking_path(sk, n_frames, (3.0, -2.5), (3.0, 2.5), seed=3, fps=FPS),  # bystander, outside the volume
    ]
    dets, labels = scene_detections(cams, coco17_targets(sk), sk, people, np.random.default_rng(seed), noise_px)
    return cams, dets, labels


def _true_person(subject_detections: dict[int, int], labels: list[np.ndarray]) -> set[int]:
    return {int(labels[cam][idx]) for cam, idx in subject_detections.items()}


def test_candidates_group_views_of_the_same_person() -> None:
    cams, dets, labels = _scene(3)
    cands = DetectionSorter(cams).candidates(dets[0])
    assert len(cands) == 3  # two subjects and the bystander
    for c in cands:
        assert len(_true_person(c.sources, labels[0])) == 1  # never mixes people
        assert len(c.sources) >= 2


def test_subjects_enrol_and_keep_their_identity_bystander_rejected() -> None:
    cams, dets, labels = _scene(120)
    tracker = SubjectTracker(DetectionSorter(cams), TrackingOptions(enrol_after_s=0.5))
    identity: dict[int, int] = {}
    bystander_frames = 0
    for f, frame in enumerate(dets):
        out = tracker.update(f * NS, frame)
        bystander_frames += out.bystanders > 0
        for s in out.subjects:
            if not s.seen:
                continue
            truth = _true_person(s.detections, labels[f])
            assert len(truth) == 1, f"frame {f}: subject {s.id} mixes people {truth}"
            identity.setdefault(s.id, truth.pop())
            assert identity[s.id] == _true_person(s.detections, labels[f]).pop(), "identity switch"
    assert sorted(identity.values()) == [0, 1]  # both subjects, never the bystander (person 2)
    assert len(tracker.subjects) == 2
    assert bystander_frames > 100


def test_enrolment_waits_and_respects_max_subjects() -> None:
    cams, dets, _ = _scene(40)
    tracker = SubjectTracker(DetectionSorter(cams), TrackingOptions(enrol_after_s=0.5, max_subjects=1))
    n_before = [len(tracker.update(f * NS, dets[f]).subjects) for f in range(14)]
    assert n_before[0] == 0 and n_before[13] == 0  # 13 frames at 30 Hz < 0.5 s
    for f in range(14, 40):
        out = tracker.update(f * NS, dets[f])
    assert len(out.subjects) == 1 and out.bystanders == 2


def test_designated_start_positions() -> None:
    cams, dets, labels = _scene(60)
    opts = TrackingOptions(enrol_after_s=0.3, start_positions=((0.9, 0.6),))
    tracker = SubjectTracker(DetectionSorter(cams), opts)
    for f in range(60):
        out = tracker.update(f * NS, dets[f])
    assert len(out.subjects) == 1
    assert _true_person(out.subjects[0].detections, labels[59]) == {1}


def test_lost_subject_is_kept_for_the_grace_period_then_released() -> None:
    cams, dets, labels = _scene(60)
    tracker = SubjectTracker(DetectionSorter(cams), TrackingOptions(enrol_after_s=0.3, grace_period_s=0.5))
    for f in range(30):
        out = tracker.update(f * NS, dets[f])
    assert len(out.subjects) == 2
    gone = next(s.id for s in out.subjects if _true_person(s.detections, labels[29]) == {1})
    events = []
    for f in range(30, 60):  # person 1 disappears from every view
        frame = [
            Detections2D(d.keypoints[lb != 1], d.confidences[lb != 1]) for d, lb in zip(dets[f], labels[f], strict=True)
        ]
        out = tracker.update(f * NS, frame)
        events += out.events
        if f < 30 + 14:
            assert any(s.id == gone for s in out.subjects)  # within 0.5 s: kept
    assert [e.kind for e in events if e.subject == gone] == ["released"]
    assert [s.id for s in out.subjects] != [gone] and len(out.subjects) == 1


def test_sorter_needs_two_cameras_and_matching_input() -> None:
    cams = ring_rig(3)
    with pytest.raises(InputError, match="at least two cameras"):
        DetectionSorter(cams[:1])
    with pytest.raises(InputError, match="3 cameras but detections for 2"):
        DetectionSorter(cams).candidates([Detections2D.empty(17)] * 2)
    assert DetectionSorter(cams).candidates([Detections2D.empty(17)] * 3) == []
    assert DetectionSorter([]).candidates([]) == []  # a rig of IMU suits alone: nobody is ever found


def test_people_tracker_reports_pairing_and_events_in_status() -> None:
    import json

    from mocapd.core.people import PeopleTracker
    from mocapd.core.suit_binding import SuitBinder
    from mocapd.core.synthetic import suit_orientations

    cams, dets, labels = _scene(60)
    sk = Skeleton.from_height(1.75)
    people = [walking_path(sk, 60, (-0.8, -0.8), (-0.6, 0.9), seed=1, fps=FPS)]  # person 0 wears suit "A"
    tracker = PeopleTracker(SubjectTracker(DetectionSorter(cams), TrackingOptions(enrol_after_s=0.3)), SuitBinder(sk))
    rng = np.random.default_rng(5)
    for f in range(60):
        out = tracker.update(f * NS, dets[f], {"A": suit_orientations(sk, people[0][f], 20.0, rng)})
    status = json.loads(json.dumps(tracker.status()))  # JSON-able
    suited = next(p for p in out.people if p.suit == "A")
    assert suited.identity == "suit:A" and _true_person(suited.detections, labels[59]) == {0}
    assert status["suits"]["A"]["track"] == suited.track and status["suits"]["A"]["confidence"] > 0.5
    kinds = [e["kind"] for e in status["events"]]
    assert kinds.count("enrolled") == 2 and kinds.count("paired") == 1
    assert len(status["subjects"]) == 2 and status["bystanders"] == 1


def test_close_interaction_on_recorded_motion_keeps_identities(capsys: pytest.CaptureFixture[str]) -> None:
    """The evaluation's hardest scene on real clips through ``mocapd eval tracking``, as docs/tracking.md reports
    it (8 s, with and without suits): no switch, no bystander or ghost enrolled, everyone published within 0.2 s, and
    the documented fractions and joint errors (0.979 / 0.988 of the person-frames, 16.7–22.3 mm). Seeded, so the
    numbers repeat; the bounds leave room for other BLAS builds."""
    from mocapd.service.cli import main

    assert main(["eval", "tracking", "--scene", "close_interaction"]) == 0
    scenes = json.loads(capsys.readouterr().out)["scenes"]
    assert [(r["scene"], r["suits"], r["frames"]) for r in scenes] == [("close_interaction", True, 240),
                                                                     ("close_interaction", False, 240)]  # fmt: skip
    for r in scenes:
        assert r["motion"] == "real" and r["identity_switches"] == 0 and r["bystanders_enrolled"] == 0, r
        assert r["mixed_assignments"] == 0, r
        # At most 1 - 0.1 s enrolment / 8 s = 0.9875 of the visible person-frames can be followed (the evidence
        # rule with 0.1 s, issue 41; the 0.5 s these scenes ran with before left 0.9375).
        assert 0.97 <= r["correct_fraction"] <= 0.9875, r
        assert r["ghost_tracks"] == 0 and max(r["first_published_s"].values()) <= 0.2, r
        assert len(r["joint_error_mm"]) == 2, r
        assert all(v is not None and v < 25.0 for v in r["joint_error_mm"].values()), r
    assert main(["eval", "tracking", "--scene", "nowhere"]) == 2
    assert "unknown tracking scene" in capsys.readouterr().err


def test_default_enrolment_on_evidence_within_a_fifth_of_a_second() -> None:
    """The evidence rule (issue 41): a person the views agree on is a subject after 3 sightings and 0.1 s (by frame
    4 at 30 Hz: 0.13 s), not after a fixed second; a candidate that holds no place frame after frame never enrols."""
    cams, dets, _ = _scene(12)
    rule = TrackingOptions(enrol_after_s=0.1)
    tracker = SubjectTracker(DetectionSorter(cams), rule)
    counts = [len(tracker.update(f * NS, dets[f]).subjects) for f in range(12)]
    assert counts[:3] == [0, 0, 0] and counts[4] == 2, counts
    # A person-shaped candidate that the views put somewhere else every frame (a chance pairing, not a person):
    # never three agreeing sightings, never a subject.
    sk = Skeleton.from_height(1.75)
    jumping = walking_path(sk, 12, (0.0, 0.0), (0.0, 0.0), seed=4, fps=FPS)
    jumping[:, 0] = np.resize([-1.5, 0.0, 1.5], 12)
    jumping[:, 2] = np.resize([-1.5, 1.5], 12)
    ghost_dets, _ = scene_detections(cams, coco17_targets(sk), sk, [jumping], np.random.default_rng(1), 1.5)
    ghost = SubjectTracker(DetectionSorter(cams), rule)
    for f in range(12):
        ghost.update(f * NS, ghost_dets[f])
    assert not ghost.subjects


def test_enrolment_counts_distinct_frames_of_each_camera() -> None:
    """Issue 41, live: the tracker is updated every 60 Hz tick from detections its timelines hold or interpolate,
    so ticks are not evidence; the frames they come from are. One detection frame replayed for a second never
    enrols; three frames of two unsynchronised cameras enrol the person at the tick that shows the third frame of
    both; a third camera's new frames alone (the other two held) add nothing."""
    cams, dets, labels = _scene(12)
    one = [_only(dets[0][c], labels[0][c], {0})[0] for c in range(4)]
    rule = TrackingOptions(enrol_after_s=0.05)
    tracker = SubjectTracker(DetectionSorter(cams), rule)
    for k in range(60):
        out = tracker.update(k * TICK, one, [0, 0, 0, 0])
    assert not out.subjects and tracker._tentative[0].sightings == 1
    # Cameras 0 and 1 at 30 fps, camera 1 half a frame later; cameras 2 and 3 see nobody.
    tracker = SubjectTracker(DetectionSorter(cams), rule)
    enrolled_at = None
    for k in range(12):
        f0, f1 = k // 2, max(0, (k - 1) // 2)
        frame = [dets[f0][0], dets[f1][1], Detections2D.empty(17), Detections2D.empty(17)]
        out = tracker.update(k * TICK, frame, [f0, f1, -1, -1])
        if out.subjects and enrolled_at is None:
            enrolled_at = k
    assert enrolled_at == 5  # camera 0's 3rd frame at tick 4, camera 1's at tick 5 (0.083 s)
    # Three cameras, 2 and 3 held at one frame: camera 0's new frames alone are one view of new evidence.
    tracker = SubjectTracker(DetectionSorter(cams), rule)
    for k in range(12):
        tracker.update(k * TICK, [dets[k][0], Detections2D.empty(17), dets[0][2], dets[0][3]], [k, -1, 0, 0])
    assert not tracker.subjects


@pytest.mark.parametrize(("height", "enrolled"), [(0.7, False), (1.1, True), (1.75, True), (2.1, True)])
def test_only_a_human_sized_body_is_evidence(height: float, enrolled: bool) -> None:
    """The camera demo's third identity with the frame rule (issue 41): two cameras' detections of two far-away
    people met inside the volume in a body 0.4 m from nose to knees, the same place pass after pass. A body at 0.4
    of an adult's size is never a sighting; a 1.1 m child and a 2.1 m adult are."""
    from mocapd.core.body_size import COCO17_NAMES
    from mocapd.core.tracking import body_scale

    sk = Skeleton.from_height(height)
    cams = ring_rig(4, radius=4.5)
    person = walking_path(sk, 12, (0.0, 0.0), (0.2, 0.2), seed=1, fps=FPS)
    dets, _ = scene_detections(cams, coco17_targets(sk), sk, [person], np.random.default_rng(0), 1.0)
    tracker = SubjectTracker(DetectionSorter(cams), TrackingOptions(enrol_after_s=0.1))
    for f in range(12):
        tracker.update(f * NS, dets[f])
    assert bool(tracker.subjects) == enrolled
    scale = body_scale(tracker.sorter.candidates(dets[0])[0].points, COCO17_NAMES)
    assert scale == pytest.approx(height / 1.75, rel=0.15)


def test_enrolment_options_checked() -> None:
    with pytest.raises(InputError, match="non-negative"):
        SubjectTracker(DetectionSorter([]), TrackingOptions(enrol_frames=-1))


# -- one person, two pairs of views (issue 39) ---------------------------------------------------------------------
RATE = 60.0  # the daemon updates the tracker on every output tick
TICK = int(1e9 / RATE)


def _demo_rig() -> list[Camera]:
    """Four cameras round the volume with the camera demo's quarter-resolution portrait views (272 x 480 px): a
    mean reprojection error of 2.5 % of the width is 6.8 px there, so views that disagree by a few tenths of a metre
    no longer pair across."""
    return ring_rig(4, radius=4.5, width=272, image_height=480, focal=300.0)


def _walkers(cams: list[Camera], paths: list[tuple[tuple[float, float], tuple[float, float]]], seconds: float):  # type: ignore[no-untyped-def]
    sk = Skeleton.from_height(1.75)
    n = int(seconds * RATE)
    people = [walking_path(sk, n, a, b, seed=k + 1, fps=RATE) for k, (a, b) in enumerate(paths)]
    return scene_detections(cams, coco17_targets(sk), sk, people, np.random.default_rng(0), 1.5)


def _only(d: Detections2D, labels: np.ndarray, keep: set[int]) -> tuple[Detections2D, np.ndarray]:
    mask = np.isin(labels, sorted(keep))
    return Detections2D(d.keypoints[mask], d.confidences[mask]), labels[mask]


def test_a_person_whose_views_disagree_is_held_as_one_subject() -> None:
    """The camera demo's third identity (tests/test_demo_cameras.py, 8 of 12 loaded runs with the governor): one
    person's views disagreed, two cameras' keypoints against the other two's, so the sorter made two candidates of
    them, each seen by its own pair of cameras and 0.3-0.6 m apart; the subject took one and the other was enrolled
    as a new person a second later. Here cameras 2 and 3 deliver the keypoints of 0.3 s ago (a starved detector's
    held frames) while the person walks at 1.5 m/s, and for half a second cameras 0 and 1 deliver nothing at all.
    Before the fix: three identities, three at once. Now the subject holds all four views: two identities, each
    subject's views of one person throughout."""
    cams = _demo_rig()
    seconds, lag = 4.0, round(0.3 * RATE)
    dets, labels = _walkers(cams, [((-2.1, -2.1), (2.1, 2.1)), ((1.8, -0.6), (0.6, -1.8))], seconds)
    tracker = SubjectTracker(DetectionSorter(cams), TrackingOptions())
    identities: dict[int, int] = {}
    most_at_once, split, held = 0, 0, 0
    for f in range(len(dets)):
        frame, truth = [], []
        for c in range(4):
            g = max(0, f - lag) if c in (2, 3) else f
            d, lb = dets[g][c], labels[g][c]
            if c in (0, 1) and 150 <= f < 180:  # the detector starved: nothing from cameras 0 and 1
                d, lb = _only(d, lb, set())
            frame.append(d)
            truth.append(lb)
        cands = [c for c in tracker.sorter.candidates(frame) if _true_person(c.sources, truth) == {0}]
        # The walker's views split while they are a subject:
        apart = len(cands) == 2 and not (cands[0].sources.keys() & cands[1].sources.keys()) and 0 in identities.values()
        split += apart
        out = tracker.update(f * TICK, frame)
        seen = [s for s in out.subjects if s.seen]
        most_at_once = max(most_at_once, len(seen))
        for s in seen:
            who = _true_person(s.detections, truth)
            assert len(who) == 1, f"tick {f}: subject {s.id} holds views of {who}"
            assert identities.setdefault(s.id, who.pop()) == _true_person(s.detections, truth).pop()
            held += apart and identities[s.id] == 0 and len(s.detections) == 4
    assert split > 60  # the scene does split the walker's views (over a second of ticks)
    assert sorted(identities.values()) == [0, 1] and most_at_once == 2, identities
    assert held == split  # on every such tick the walker's subject held both pairs of views


def test_a_second_person_beside_a_subject_or_behind_other_cameras_is_enrolled() -> None:
    """What the subject's other views are not: a person who walks up to 0.5 m of a subject, seen by the same
    cameras (a different 2D person in a camera the subject holds), and one seen only by cameras that do not see the
    subject (each occluded in the other's cameras) 1.6 m away, beyond the subject's reach."""
    cams = _demo_rig()
    dets, labels = _walkers(cams, [((-0.3, 0.0), (-0.3, 0.2)), ((2.2, 0.0), (0.2, 0.1))], 3.0)
    tracker = SubjectTracker(DetectionSorter(cams), TrackingOptions())
    for f in range(len(dets)):
        out = tracker.update(f * TICK, dets[f])
    assert len(out.subjects) == 2 and all(len(s.detections) == 4 for s in out.subjects)
    dets, labels = _walkers(cams, [((-0.8, 0.0), (-0.8, 0.2)), ((0.8, 0.0), (0.8, 0.2))], 3.0)
    tracker = SubjectTracker(DetectionSorter(cams), TrackingOptions())
    for f in range(len(dets)):
        frame = [_only(dets[f][c], labels[f][c], {0} if c in (0, 1) else {1})[0] for c in range(4)]
        out = tracker.update(f * TICK, frame)
    assert len(out.subjects) == 2 and all(sorted(s.detections) in ([0, 1], [2, 3]) for s in out.subjects)
