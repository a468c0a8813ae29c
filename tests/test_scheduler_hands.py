"""Fingers in the scheduler: hands on only when the detections carry hand keypoints, solved in the person's job, the
body's solve unchanged by them (hands off: the same code and the same work)."""

from __future__ import annotations

import numpy as np

from mocapd.core.hand_skeleton import HandSkeleton
from mocapd.core.hand_solver import FLEXION_HINGES, hand_fk
from mocapd.core.keypoints import COCO17_FORMAT, COCO17_HANDS_FORMAT, coco17_targets
from mocapd.core.kinematics import Kinematics
from mocapd.core.people import PeopleTracker
from mocapd.core.rotations import quat_angle, quat_from_matrix
from mocapd.core.skeleton import BONE_INDEX, Skeleton
from mocapd.core.sorting import Detections2D, DetectionSorter
from mocapd.core.synthetic import moving_sequence, ring_rig
from mocapd.core.tracking import SubjectTracker, TrackingOptions
from mocapd.eval.hands import _project, hand_motion
from mocapd.pipeline.hands import HandStage
from mocapd.pipeline.scheduler import FixedLatencyScheduler, PoseFrame, SchedulerOptions

S = 1_000_000_000
RATE = 60
LATENCY = 50_000_000
CAMERAS = ring_rig(6, radius=3.0)
PROJECTIONS = np.stack([c.projection_matrix for c in CAMERAS])
SKELETON = Skeleton.from_height(1.75)
HANDS = HandSkeleton.from_body(SKELETON)
HAND_BONES = (BONE_INDEX["LeftHand"], BONE_INDEX["RightHand"])


def _frames(seconds: float) -> tuple[list[list[Detections2D]], np.ndarray, np.ndarray]:
    """Per frame and camera: one person's COCO-17 keypoints followed by both hands' 42 (the ``coco17_hands``
    columns), noise-free; and the true θ and finger angles per frame."""
    n = round(seconds * RATE)
    thetas = moving_sequence(SKELETON, n, fps=RATE, seed=2, amplitude=0.5)
    fingers = np.stack([hand_motion(seconds, RATE), hand_motion(seconds, RATE, phase=0.8)], axis=1)
    kin = Kinematics(SKELETON)
    fk = kin.forward(thetas)
    targets = coco17_targets(SKELETON)
    body = kin.targets(fk, targets.bones, targets.offsets)
    out = []
    for i in range(n):
        points = [body[i]]
        for side, bone in enumerate(HAND_BONES):
            points.append(
                hand_fk(HANDS, side, fingers[i, side], fk.rotations[i, bone], fk.positions[i, bone]).landmarks
            )
        uv, seen = _project(CAMERAS, np.concatenate(points))
        out.append([Detections2D(uv[c][None], 0.9 * seen[c][None].astype(np.float64)) for c in range(len(CAMERAS))])
    return out, thetas, fingers


def _run(frames: list[list[Detections2D]], columns: int | None, hands: HandStage | None) -> list[PoseFrame]:
    tracker = PeopleTracker(SubjectTracker(DetectionSorter(CAMERAS), TrackingOptions(enrol_after_s=0.1)))
    sched = FixedLatencyScheduler(
        CAMERAS, SKELETON, coco17_targets(SKELETON), tracker,
        options=SchedulerOptions(rate_hz=RATE, latency_ns=LATENCY), hands=hands,
    )  # fmt: skip
    out = []
    for i, row in enumerate(frames):
        t = S + i * S // RATE
        for c, det in enumerate(row):
            cut = det if columns is None else Detections2D(det.keypoints[:, :columns], det.confidences[:, :columns])
            sched.add_detections(c, t, cut, t + LATENCY // 2)
        out.append(sched.tick(t + LATENCY))
    return out


def test_hands_are_on_only_when_the_detections_carry_them() -> None:
    assert HandStage.from_names(COCO17_FORMAT.keypoints, PROJECTIONS) is None
    stage = HandStage.from_names(COCO17_HANDS_FORMAT.keypoints, PROJECTIONS)
    assert stage is not None
    np.testing.assert_array_equal(stage.columns, np.arange(17, 59).reshape(2, 21))


def test_fingers_are_solved_with_the_body_and_leave_its_solve_alone() -> None:
    frames, _thetas, fingers = _frames(1.0)
    body_only = _run(frames, columns=17, hands=None)  # what a body-only detector delivers
    wide_off = _run(frames, columns=None, hands=None)  # hand columns present, hands off
    stage = HandStage.from_names(COCO17_HANDS_FORMAT.keypoints, PROJECTIONS)
    assert stage is not None
    on = _run(frames, columns=None, hands=stage)
    solved = 0
    errors, rest = [], []
    for a, b, c in zip(body_only, wide_off, on, strict=True):
        assert len(a.people) == len(b.people) == len(c.people)
        for pa, pb, pc in zip(a.people, b.people, c.people, strict=True):
            # hands off: no fingers, and the body as without hand columns (to round-off: the sorting triangulates
            # the hand columns with the body's, in one batch)
            assert pa.hands is None and pb.hands is None
            np.testing.assert_allclose(pa.theta, pb.theta, rtol=0, atol=1e-8)
            # hands on: the body's solve is the same; only the hand bones' rotations come from the hands
            body = np.ones(66, dtype=bool)
            for bone in HAND_BONES:
                body[3 + 3 * bone : 6 + 3 * bone] = False
            np.testing.assert_array_equal(pc.theta[body], pb.theta[body])
            np.testing.assert_array_equal(pc.joints, pb.joints)
            assert pc.hands is not None
            if pc.hands.present.all():
                solved += 1
                i = round((a.t_solve_ns - S) * RATE / S)
                truth_local = np.stack([
                    quat_from_matrix(hand_fk(HANDS, s, fingers[i, s], np.eye(3), np.zeros(3)).local) for s in (0, 1)
                ])  # fmt: skip
                errors.append(np.rad2deg(quat_angle(pc.hands.rotations, truth_local)))
                rest.append(np.rad2deg(quat_angle(np.array([1.0, 0.0, 0.0, 0.0]), truth_local)))
    assert solved >= 30
    assert stage.counters["hands_solved"] >= 60
    # noise-free keypoints: the finger bones within a few degrees of the truth (the prior pulls a little; the thumb's
    # roll is the least observed), where the flat hand is tens of degrees off
    assert float(np.mean(errors)) < 6.0 and float(np.median(errors)) < 3.0
    assert float(np.mean(rest)) > 20.0
    assert stage.cpu.count == sum(len(f.people) for f in on)
    assert len(FLEXION_HINGES) == 15


def test_a_released_person_is_forgotten() -> None:
    stage = HandStage.from_names(COCO17_HANDS_FORMAT.keypoints, PROJECTIONS)
    assert stage is not None
    views = {0: (np.zeros((59, 2)), np.zeros(59))}
    pose, theta = stage.solve("track:1", SKELETON, SKELETON.rest_pose(), views)
    assert not pose.present.any()
    np.testing.assert_array_equal(theta, SKELETON.rest_pose())
    stage.forget({"track:2"})
    assert stage._tracks == {}
