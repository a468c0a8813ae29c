"""Fingers live (issue 44): the daemon makes the finger solve when its rig's detections carry both hands' keypoints
(and nothing of it otherwise: the same bytes out), /status reports it, and a view whose left/right labels are
swapped has its hands swapped with its arms."""

from __future__ import annotations

import numpy as np

from mocapd.core.keypoints import COCO17_HANDS_FORMAT, coco17_targets, hand_keypoint_names, keypoint_format
from mocapd.core.people import PeopleTracker
from mocapd.core.sorting import Detections2D, DetectionSorter
from mocapd.core.tracking import SubjectTracker, TrackingOptions
from mocapd.pipeline.detector_config import DetectorConfig
from mocapd.pipeline.detector_pool import target_columns
from mocapd.pipeline.hands import HandStage
from mocapd.pipeline.scheduler import FixedLatencyScheduler, PoseFrame, SchedulerOptions
from mocapd.protocols.session_format import encode_pose
from mocapd.service.config import parse_config
from mocapd.service.daemon import Daemon, Rig
from mocapd.service.outputs.recorder import pose_record
from mocapd.service.rig import detection_columns

from .test_scheduler_hands import CAMERAS, LATENCY, PROJECTIONS, RATE, SKELETON, S, _frames

TARGETS = coco17_targets(SKELETON)
HAND_COLUMNS = TARGETS.names + hand_keypoint_names("left") + hand_keypoint_names("right")


def _drive(
    sched: FixedLatencyScheduler, frames: list[list[Detections2D]], columns: int | None, gap: range = range(0)
) -> list[PoseFrame]:
    """Every frame through the scheduler; camera 0 sends nothing during the frames of ``gap``."""
    out = []
    for i, row in enumerate(frames):
        t = S + i * S // RATE
        for c, det in enumerate(row):
            if c == 0 and i in gap:
                continue
            cut = det if columns is None else Detections2D(det.keypoints[:, :columns], det.confidences[:, :columns])
            sched.add_detections(c, t, cut, t + LATENCY // 2)
        out.append(sched.tick(t + LATENCY))
    return out


def _daemon(keypoint_names: tuple[str, ...]) -> Daemon:
    config = parse_config({"daemon": {"latency_s": LATENCY / 1e9, "output_rate_hz": float(RATE)},
                           "tracking": {"enrolment": {"enrol_after_s": 0.1}}})  # fmt: skip
    rig = Rig(list(CAMERAS), [], SKELETON, TARGETS, keypoint_names=keypoint_names)
    return Daemon(config, rig)


def _bytes(frames: list[PoseFrame]) -> list[bytes]:
    return [encode_pose(pose_record(f)) for f in frames]


def test_the_daemon_solves_fingers_only_when_its_detections_carry_hands() -> None:
    frames, _thetas, _fingers = _frames(1.0)
    off = _daemon(())
    assert off.scheduler.hands is None and off.hand_status() is None
    on = _daemon(HAND_COLUMNS)
    assert on.scheduler.hands is not None
    np.testing.assert_array_equal(on.scheduler.hands.columns, np.arange(17, 59).reshape(2, 21))
    # the sorter's flip-aware matching pairs every column: the body's (left with right shoulder) and the hands'
    partner = on.scheduler.people.tracker.sorter._partner(59)
    assert partner[5] == 6 and partner[17] == 38 and partner[58] == 37
    # camera 0 silent for a while: its timeline's empty sample has every column too (hands included)
    published = _drive(on.scheduler, frames, None, gap=range(20, 45))
    assert any(f.missing_cameras for f in published)
    fingered = [p for f in published for p in f.people if p.hands is not None and p.hands.present.all()]
    assert len(fingered) >= 30
    # the fingers move: the solved finger bones are far from the flat hand's identity rotations
    assert max(float(np.abs(p.hands.rotations[..., 1:]).max()) for p in fingered if p.hands is not None) > 0.3
    status = on.hand_status()
    assert status is not None
    assert status["counters"]["hands_solved"] >= 60 and status["cpu_ms"]["count"] > 0
    # hands off: the daemon's frames are byte for byte a scheduler's made as before fingers (no ``hands``)
    tracker = PeopleTracker(
        SubjectTracker(
            DetectionSorter(CAMERAS, off.config.tracking.sorting.options(), keypoint_names=TARGETS.names),
            off.config.tracking.enrolment.options(),
        )
    )
    before = FixedLatencyScheduler(
        CAMERAS, SKELETON, TARGETS, tracker, options=off.scheduler.options, cost=off.scheduler.cost,
        lm=off.scheduler.lm, backend=off.config.solver.backend,
    )  # fmt: skip
    assert _bytes(_drive(off.scheduler, frames, 17)) == _bytes(_drive(before, frames, 17))


def _mirrored(det: Detections2D) -> Detections2D:
    """A view whose detector took the person's left arm for their right: the elbows and wrists swapped, and so the
    hands (their crops were placed from the arms)."""
    names = COCO17_HANDS_FORMAT.keypoints
    index = {n: i for i, n in enumerate(names)}

    def other(n: str) -> str:
        return n.replace("left_", "@").replace("right_", "left_").replace("@", "right_")

    arms = ("_elbow", "_wrist", "_hand_")
    order = [index[other(n)] if any(a in n for a in arms) else i for i, n in enumerate(names)]
    return Detections2D(det.keypoints[:, order], det.confidences[:, order])


def test_a_view_with_swapped_labels_has_its_hands_swapped_with_its_arms() -> None:
    frames, _thetas, _fingers = _frames(1.0)
    flipped = [[_mirrored(d) if c == 1 else d for c, d in enumerate(row)] for row in frames]

    def run(rows: list[list[Detections2D]]) -> tuple[list[PoseFrame], FixedLatencyScheduler]:
        names = COCO17_HANDS_FORMAT.keypoints
        tracker = PeopleTracker(
            SubjectTracker(DetectionSorter(CAMERAS, keypoint_names=names), TrackingOptions(enrol_after_s=0.1))
        )
        sched = FixedLatencyScheduler(
            CAMERAS, SKELETON, TARGETS, tracker, options=SchedulerOptions(rate_hz=RATE, latency_ns=LATENCY),
            hands=HandStage.from_names(names, PROJECTIONS),
        )  # fmt: skip
        return _drive(sched, rows, None), sched

    clean, _ = run(frames)
    swapped, sched = run(flipped)
    assert sched.counters["lr_swaps"] > 60  # view 1's arms were found swapped and put back
    compared = 0
    for a, b in zip(clean, swapped, strict=True):
        for pa, pb in zip(a.people, b.people, strict=True):
            assert pb.views == pa.views  # the mirrored view stays the person's
            if pa.hands is None or pb.hands is None or not (pa.hands.present.all() and pb.hands.present.all()):
                continue
            # with view 1's hands swapped back with its arms, the fingers come from the clean run's keypoints
            np.testing.assert_allclose(pb.hands.rotations, pa.hands.rotations, rtol=0, atol=1e-9)
            compared += 1
    assert compared >= 40


def test_a_local_rig_with_hands_on_delivers_the_hands_after_the_targets() -> None:
    body = keypoint_format("blazepose33").track_targets(SKELETON).names
    on = DetectorConfig(landmarks="full", hands="on")
    hands = detection_columns(on, body, remote=False)
    assert hands[: len(body)] == body and hands[len(body) :] == HAND_COLUMNS[17:]
    assert target_columns(on, hands).tolist() == list(range(75))  # blazepose33_hands: body, then both hands
    # hands off, or a rig of camera hosts (their keypoint stream carries the body alone): the targets' columns
    assert detection_columns(DetectorConfig(landmarks="full"), body, remote=False) == body
    assert detection_columns(on, body, remote=True) == body
