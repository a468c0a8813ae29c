"""Detection timelines: linear interpolation between frames, people matched across frames, late data held
for at most max_age and then dropped (never extrapolated)."""

from __future__ import annotations

import numpy as np

from mocapd.core.sorting import Detections2D
from mocapd.pipeline.keypoint_timeline import DetectionTimeline, SampleStatus, interpolate_people

MS = 1_000_000


def _person(x: float, y: float, n_kp: int = 17) -> tuple[np.ndarray, np.ndarray]:
    kp = np.stack([np.full(n_kp, x), y + np.arange(n_kp, dtype=float)], axis=1)
    return kp, np.full(n_kp, 0.9)


def _frame(*people: tuple[float, float]) -> Detections2D:
    parts = [_person(x, y) for x, y in people]
    return Detections2D(np.stack([p[0] for p in parts]), np.stack([p[1] for p in parts]))


def test_linear_interpolation_between_frames_matches_people_in_any_order() -> None:
    tl = DetectionTimeline(17)
    assert tl.push(0, _frame((100, 100), (500, 300)))
    assert tl.push(40 * MS, _frame((520, 300), (140, 100)))  # order swapped, both moved
    s = tl.sample(10 * MS)  # a quarter of the way
    assert s.status is SampleStatus.INTERPOLATED
    xs = sorted(s.detections.keypoints[:, 0, 0])
    np.testing.assert_allclose(xs, [110.0, 505.0])
    np.testing.assert_allclose(s.detections.confidences, 0.9)
    assert (s.t_before, s.t_after) == (0, 40 * MS)


def test_the_people_of_a_bracket_are_matched_once_for_every_tick_that_samples_it() -> None:
    # 60 Hz ticks between 30 Hz frames: two ticks or more blend the same two frames; who is who does not depend on
    # where between them the tick falls, so it is matched once per bracket (issue 39: per-tick work on the loop).
    tl = DetectionTimeline(17)
    frames = [_frame((100, 100), (500, 300)), _frame((520, 300), (140, 100)), _frame((150, 100), (530, 300))]
    for k, f in enumerate(frames):
        assert tl.push(k * 40 * MS, f)
    ticks = [5, 15, 25, 35, 45, 55, 65]  # ms: four in the first bracket, three in the second
    for t in ticks:
        s = tl.sample(t * MS)
        assert s.status is SampleStatus.INTERPOLATED
        k = t // 40
        alpha = (t - 40 * k) / 40
        direct = interpolate_people(frames[k], frames[k + 1], alpha, tl.match_px)  # matched on every call
        np.testing.assert_array_equal(s.detections.keypoints, direct.keypoints)
        np.testing.assert_array_equal(s.detections.confidences, direct.confidences)
    assert tl.matchings == 2


def test_keypoint_missing_in_one_frame_keeps_the_other_with_lower_confidence() -> None:
    a, b = _frame((100, 100)), _frame((120, 100))
    b.confidences[0, 3] = 0.0
    out = interpolate_people(a, b, 0.25, match_px=80.0)
    assert out.keypoints[0, 3, 0] == 100.0  # only a has it
    np.testing.assert_allclose(out.confidences[0, 3], 0.9 * 0.75)
    np.testing.assert_allclose(out.keypoints[0, 0, 0], 105.0)


def test_unmatched_people_come_from_the_nearer_frame_only() -> None:
    a = _frame((100, 100))
    b = _frame((102, 100), (900, 500))  # someone appears in b
    assert interpolate_people(a, b, 0.2, 80.0).keypoints.shape[0] == 1
    assert interpolate_people(a, b, 0.8, 80.0).keypoints.shape[0] == 2
    far = _frame((400, 100))  # moved more than match_px: not the same person
    assert interpolate_people(a, far, 0.3, 80.0).keypoints[0, 0, 0] == 100.0


def test_late_detections_are_held_then_dropped_never_extrapolated() -> None:
    tl = DetectionTimeline(17, max_age_ns=100 * MS)
    tl.push(0, _frame((100, 100)))
    tl.push(33 * MS, _frame((110, 100)))
    held = tl.sample(100 * MS)
    assert held.status is SampleStatus.HELD
    assert held.detections.keypoints[0, 0, 0] == 110.0  # the newest frame as it was, not moved on
    stale = tl.sample(134 * MS)
    assert stale.status is SampleStatus.STALE
    assert stale.detections.keypoints.shape[0] == 0


def test_gaps_before_oldest_empty_and_out_of_order() -> None:
    tl = DetectionTimeline(17, max_age_ns=50 * MS, max_gap_ns=200 * MS)
    assert tl.sample(0).status is SampleStatus.EMPTY
    tl.push(1000 * MS, _frame((100, 100)))
    assert not tl.push(1000 * MS, _frame((100, 100)))
    assert not tl.push(900 * MS, _frame((100, 100)))
    assert tl.rejected_out_of_order == 2
    tl.push(1500 * MS, _frame((300, 100)))  # a 500 ms hole: no interpolation across it
    near = tl.sample(1040 * MS)
    assert near.status is SampleStatus.NEAREST
    assert near.detections.keypoints[0, 0, 0] == 100.0
    assert tl.sample(1250 * MS).status is SampleStatus.STALE
    assert tl.sample(960 * MS).status is SampleStatus.NEAREST
    assert tl.sample(900 * MS).status is SampleStatus.STALE
    assert tl.sample(1500 * MS).status is SampleStatus.EXACT
