"""``[detector] hands = "auto"`` from measured costs (issue 44): the choice (pure, injected costs), and the real hand
model behind :class:`AutoHands` with an injected clock (its measured costs), hands off first when the budget is
short, off while the governor sheds the body landmarks, the keypoint set the same on passes without hands."""

from __future__ import annotations

import numpy as np
import pytest

from mocapd.core.keypoints import COCO17_FORMAT as COCO17
from mocapd.core.pose2d import PoseDetections
from mocapd.pipeline.detector_config import DetectorConfig
from mocapd.pipeline.hand_auto import AutoHands, HandCosts, choose_hands, front_status, hand_stage
from mocapd.pipeline.hand_landmarks import HandRunner
from mocapd.pipeline.landmark_auto import REPROBE_NS, AutoLandmarks, LandmarkCosts, choose_landmarks

MS = 1_000_000


def costs(body_ms: float, hand_ms: float | None = 10.0, crops: float = 2.0) -> HandCosts:
    return HandCosts(yolo_ms=60.0, idle_ms=0.0, body_ms=body_ms, crops=crops, hand_ms=hand_ms)


def test_the_hands_get_what_the_body_landmarks_left() -> None:
    assert choose_hands(costs(0.0, None)).run  # measuring first
    assert choose_hands(costs(10.0)) .every == 1  # 2 x 10 ms within 0.5 x 60 - 10 = 20 ms  # fmt: skip
    short = choose_hands(costs(25.0))  # 5 ms left for 20 ms of hands: every 4th pass
    assert short.run and short.every == 4 and "every 4" in short.reason
    # The budget is short: the body's full model still fits on every pass, the hands go off first.
    body = choose_landmarks(LandmarkCosts(yolo_ms=60.0, idle_ms=0.0, crops=1.0, landmark_ms={"full": 30.0}),
                            allowed=["full"])  # fmt: skip
    assert body.variant == "full" and body.every == 1
    hands = choose_hands(costs(30.0))
    assert not hands.run and "body landmarks take the budget" in hands.reason
    assert not choose_hands(costs(29.0)).run  # 1 ms left: every 20th pass, rarer than every 8th
    assert not choose_hands(costs(0.0, hand_ms=130.0)).run  # a pass of hands over 250 ms
    # Idle time is budget too (a fast machine waits for frames).
    idle = HandCosts(yolo_ms=60.0, idle_ms=40.0, body_ms=30.0, crops=2.0, hand_ms=10.0)
    assert choose_hands(idle).run and choose_hands(idle).every == 1


class StepClock:
    """Every reading 20 ms after the one before: the hand model's measured time per call is 20 ms."""

    def __init__(self) -> None:
        self.now = 0

    def __call__(self) -> int:
        self.now += 20 * MS
        return self.now


def person() -> PoseDetections:
    """One COCO-17 person whose forearms place a crop per hand on a grey image."""
    kp = np.zeros((1, 17, 3))
    names = COCO17.keypoints
    for side, x in (("left", 380.0), ("right", 260.0)):
        kp[0, names.index(f"{side}_shoulder")] = (x, 150.0, 0.9)
        kp[0, names.index(f"{side}_elbow")] = (x, 230.0, 0.9)
        kp[0, names.index(f"{side}_wrist")] = (x, 300.0, 0.9)
    return PoseDetections(np.array([[240.0, 100.0, 400.0, 400.0]]), np.array([0.9]), kp)


def test_auto_hands_measure_their_cost_and_go_off_first_when_the_body_takes_the_budget() -> None:
    image = np.full((480, 640, 3), 128, np.uint8)
    auto = AutoHands(HandRunner(COCO17.keypoints), clock=StepClock())
    hand_stage(auto, [image], [person()], [0], 60 * MS, 10 * MS)
    # The model's first run loaded it: not counted as its cost; the next pass measures it.
    assert auto.runner.crops_run == 2 and auto.costs().hand_ms is None
    assert auto.decide().reason == "measuring the hand model's cost per crop"
    runs = []
    for _ in range(5):  # YOLO 60 ms, body landmarks 10 ms: 20 ms left, the hands' 2 x 10 ms fit every pass
        (out,) = hand_stage(auto, [image], [person()], [0], 60 * MS, 10 * MS)
        assert out.keypoints.shape == (1, 17 + 42, 3)
        runs.append(auto.choice.run and auto.choice.every == 1)
    assert all(runs) and auto.hand_passes == 6 and auto.runner.crops_run == 12
    assert auto.costs().hand_ms == pytest.approx(10.0)  # 20 ms per call over two crops
    for _ in range(30):  # the body landmarks now take 40 ms a pass: nothing left
        (out,) = hand_stage(auto, [image], [person()], [0], 60 * MS, 40 * MS)
    assert not auto.choice.run and "body landmarks take the budget" in auto.choice.reason
    before = auto.runner.crops_run
    (out,) = hand_stage(auto, [image], [person()], [0], 60 * MS, 40 * MS)
    assert auto.runner.crops_run == before  # the model did not run
    assert out.keypoints.shape == (1, 59, 3) and not out.keypoints[0, 17:].any()  # hands "not seen"
    np.testing.assert_array_equal(out.keypoints[0, :17], person().keypoints[0])
    status = front_status((True, "auto"), "auto", [auto])
    assert status["auto"]["running"] == "off" and status["auto"]["passes"] == 37  # type: ignore[index]
    # Off, the model still runs once every REPROBE_NS to measure itself again (its last run moved 20 s back).
    assert auto._ran_ns is not None
    auto._ran_ns -= REPROBE_NS
    (out,) = hand_stage(auto, [image], [person()], [0], 60 * MS, 40 * MS)
    assert auto.runner.crops_run == before + 2 and not auto.choice.run
    hand_stage(auto, [image], [person()], [0], 60 * MS, 40 * MS)
    assert auto.runner.crops_run == before + 2


def test_the_governor_shedding_the_body_landmarks_turns_the_hands_off() -> None:
    body = AutoLandmarks({})
    auto = AutoHands(HandRunner(COCO17.keypoints), body, clock=StepClock())
    image = np.full((480, 640, 3), 128, np.uint8)
    hand_stage(auto, [image], [person()], [0], 60 * MS, 0)
    assert auto.choice.run
    body.shed = "missed ticks"
    hand_stage(auto, [image], [person()], [0], 60 * MS, 0)
    assert not auto.choice.run and "governor shed the body landmarks (missed ticks)" in auto.choice.reason


def test_auto_is_on_only_beside_the_body_landmarks() -> None:
    assert DetectorConfig(hands="auto", landmarks="off").hands_decision()[0] is False
    on, why = DetectorConfig(hands="auto", landmarks="auto").hands_decision()
    assert on and "measured costs" in why
