"""``[detector] hands = "auto"``: the hand landmark model run per detection pass from what it costs (issue 44).

Two hand crops per person cost about one full BlazePose crop (docs/detection.md), so hands on every pass add as much
again to a detector that the body landmarks may already have stretched. "auto" weighs them as
:mod:`mocapd.pipeline.landmark_auto` weighs the body landmarks, from costs measured live by the session:

* ``yolo_ms``: the detector's time of a pass, ``idle_ms``: the wait between passes,
* ``body_ms``: the body landmark stage's time per pass (its average: 0 on the passes it skips),
* ``crops``: the hand crops of a pass (two per person), ``hand_ms``: the hand model's time per crop, measured when
  it ran (scaled by YOLO's change since, as the body's; its first run, which loads the model, not counted),

and :func:`choose_hands` (pure) turns them into a rate: the hands get what the body landmarks left of the same
allowance (:class:`~mocapd.pipeline.landmark_auto.LandmarkBudget`: ``share`` of a YOLO pass plus the idle time), on
every ``every``-th pass, the smallest that fits; off when nothing is left, when a pass of hands would take longer
than ``max_pass_ms`` or run rarer than every ``max_every``-th pass. So when the budget is short the hands go off
first and the body keeps its landmarks. The passes without hands give every person's 42 hand keypoints at
confidence 0 ("not seen"), so the keypoint set (``<body>_hands``) never changes. While off, the hand model still runs
on one pass every :data:`~mocapd.pipeline.landmark_auto.REPROBE_NS` to measure itself again, as the body's does.

The budget governor sheds the body landmarks (``[daemon] governor``, :func:`~mocapd.pipeline.landmark_auto.
shed_landmarks`); while it does, the hands are off too (their crops are placed from the body landmarks' hand points).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from mocapd.core.hand_roi import N_HAND
from mocapd.core.keypoints import HAND_SIDES
from mocapd.core.pose2d import PoseDetections
from mocapd.pipeline.hand_landmarks import HandRunner, hand_status, with_hand_landmarks
from mocapd.pipeline.landmark_auto import REPROBE_NS, AutoLandmarks, LandmarkBudget, LandmarkFront, _Mean


@dataclass(frozen=True)
class HandCosts:
    """What a pass of hands would cost and what the rest of the pass costs, measured (module docstring)."""

    yolo_ms: float
    idle_ms: float
    body_ms: float
    """The body landmark stage's average time per pass."""
    crops: float
    """Hand crops per pass (two per person)."""
    hand_ms: float | None
    """The hand model's time per crop (None: not measured yet)."""


@dataclass(frozen=True)
class HandChoice:
    """Whether the hands run, on every ``every``-th pass, and why."""

    run: bool
    every: int
    reason: str


def choose_hands(costs: HandCosts, budget: LandmarkBudget | None = None) -> HandChoice:
    """The hands' rate for ``costs`` (pure; the module docstring)."""
    b = budget if budget is not None else LandmarkBudget()
    if costs.hand_ms is None:
        return HandChoice(True, 1, "measuring the hand model's cost per crop")
    pass_ms = costs.hand_ms * costs.crops
    left = b.share * costs.yolo_ms + costs.idle_ms - costs.body_ms
    fits = (f"{costs.crops:.1f} crops x {costs.hand_ms:.0f} ms in {b.share:g} x {costs.yolo_ms:.0f} ms YOLO + "
            f"{costs.idle_ms:.0f} ms idle - {costs.body_ms:.0f} ms body landmarks")  # fmt: skip
    if pass_ms > b.max_pass_ms:
        return HandChoice(False, 1, f"off: a pass of hands would take {pass_ms:.0f} ms (at most {b.max_pass_ms:.0f})")
    if left <= 0.0:
        return HandChoice(False, 1, f"off: the body landmarks take the budget ({fits})")
    every = 1 if pass_ms <= left else math.ceil(pass_ms / left)
    if every > b.max_every:
        return HandChoice(False, 1, f"off: every {every}th pass at most ({fits}; every {b.max_every}th the rarest)")
    return HandChoice(True, every, f"every {every}: {fits}")


def without_hands(people: PoseDetections) -> PoseDetections:
    """``people`` with both hands' 42 keypoints at (0, 0), confidence 0, after their body keypoints."""
    zeros = np.zeros((len(people.keypoints), len(HAND_SIDES) * N_HAND, 3))
    return PoseDetections(people.boxes, people.scores, np.concatenate([people.keypoints, zeros], axis=1))


class AutoHands:
    """One detector session's hand stage under ``hands = "auto"`` (one per worker; :meth:`run` not thread-safe,
    :meth:`status` may be read from any thread).

    Parameters
    ----------
    runner : HandRunner
    body : LandmarkFront
        The session's body landmark stage: while the governor sheds it (:attr:`AutoLandmarks.shed`), hands are off.
    budget : LandmarkBudget, optional
    clock : callable returning int ns
    """

    def __init__(
        self,
        runner: HandRunner,
        body: LandmarkFront = None,
        budget: LandmarkBudget | None = None,
        clock: Callable[[], int] = time.perf_counter_ns,
    ) -> None:
        self.runner = runner
        self.body = body
        self.budget = budget if budget is not None else LandmarkBudget()
        self.clock = clock
        self.choice = HandChoice(False, 1, "no pass yet")
        self._yolo, self._idle, self._body, self._crops, self._per_crop = _Mean(), _Mean(), _Mean(), _Mean(), _Mean()
        self._yolo_then = 0.0
        self._warm = False  # the model has run once (its first run, loading it, is not counted as its cost)
        self._ran_ns: int | None = None  # when the model last ran
        self._since = 0
        self._last_end: int | None = None
        self._lock = threading.Lock()
        self.passes = 0
        self.hand_passes = 0

    @property
    def variant(self) -> str:
        return self.runner.variant

    def costs(self) -> HandCosts:
        """The costs measured so far; the hand model's scaled by how YOLO's pass time changed since it ran."""
        yolo = self._yolo.value or 0.0
        hand = self._per_crop.value
        if hand is not None and self._yolo_then > 0 and yolo > 0:
            hand *= yolo / self._yolo_then
        return HandCosts(yolo, self._idle.value or 0.0, self._body.value or 0.0, self._crops.value or 2.0, hand)

    def decide(self) -> HandChoice:
        """The choice for the next pass: off while the governor sheds the body landmarks, else :func:`choose_hands`."""
        if isinstance(self.body, AutoLandmarks) and self.body.shed is not None:
            return HandChoice(False, 1, f"off: the governor shed the body landmarks ({self.body.shed})")
        return choose_hands(self.costs(), self.budget)

    def run(
        self,
        images: Sequence[np.ndarray],
        people: Sequence[PoseDetections],
        cameras: Sequence[int] | None,
        yolo_ns: int,
        body_ns: int,
    ) -> list[PoseDetections]:
        """One pass's people with both hands' keypoints after their body's: the model's on a pass the choice runs
        it on, zeros (not seen) on the others. ``yolo_ns``, ``body_ns``: the pass's detector and body landmark
        times, measured by the caller just before."""
        start = self.clock() - yolo_ns - body_ns
        if self._last_end is not None:
            self._idle.add(max(0.0, (start - self._last_end) / 1e6))
        self._yolo.add(yolo_ns / 1e6)
        self._body.add(body_ns / 1e6)
        n_people = sum(len(p.keypoints) for p in people)
        if n_people:
            self._crops.add(2.0 * n_people)
        self.choice = choice = self.decide()
        self._since += 1
        shed = isinstance(self.body, AutoLandmarks) and self.body.shed is not None
        reprobe = (not choice.run and not shed and self._ran_ns is not None
                   and start - self._ran_ns >= REPROBE_NS)  # fmt: skip
        ran = n_people > 0 and ((choice.run and self._since >= choice.every) or reprobe)
        if ran:
            before, t0 = self.runner.crops_run, self.clock()
            out = with_hand_landmarks(self.runner, images, people, cameras)
            crops = self.runner.crops_run - before
            self._ran_ns = t0
            if crops and not self._warm:
                self._warm = True  # loading and first allocations: not what a pass costs
            elif crops:
                self._per_crop.add((self.clock() - t0) / 1e6 / crops)
                self._yolo_then = self._yolo.value or 0.0
            self._since = 0
        else:
            out = [without_hands(p) for p in people]
        self._last_end = self.clock()
        with self._lock:
            self.passes += 1
            self.hand_passes += int(ran)
        return out

    def status(self) -> dict[str, object]:
        """``/status`` ``detector.hands.auto``: the choice, its reason, the costs and the passes with hands."""
        c, choice = self.costs(), self.choice
        with self._lock:
            passes, hand_passes = self.passes, self.hand_passes
        return {
            "running": "on" if choice.run else "off",
            "every": choice.every,
            "reason": choice.reason,
            "costs": {"yolo_ms": round(c.yolo_ms, 1), "idle_ms": round(c.idle_ms, 1), "body_ms": round(c.body_ms, 1),
                      "crops_per_pass": round(c.crops, 2),
                      "hand_ms_per_crop": None if c.hand_ms is None else round(c.hand_ms, 1)},
            "passes": passes,
            "hand_passes": hand_passes,
        }  # fmt: skip


HandFront = HandRunner | AutoHands | None
"""A detector session's hand stage: always (``hands = "on"``), "auto", or none."""


def hand_stage(
    front: HandFront,
    images: Sequence[np.ndarray],
    people: Sequence[PoseDetections],
    cameras: Sequence[int] | None = None,
    yolo_ns: int = 0,
    body_ns: int = 0,
) -> list[PoseDetections]:
    """The people of one pass through the session's hand stage (:meth:`AutoHands.run` under "auto", which also
    takes the pass's detector and body landmark times; :func:`with_hand_landmarks` otherwise)."""
    if isinstance(front, AutoHands):
        return front.run(images, people, cameras, yolo_ns, body_ns)
    return with_hand_landmarks(front, images, people, cameras)


def runner_of(front: HandFront) -> HandRunner | None:
    """The hand model behind a session's hand stage (``/status`` counts its crops and hands)."""
    return front.runner if isinstance(front, AutoHands) else front


def front_status(decision: tuple[bool, str], asked: str, fronts: Sequence[HandFront]) -> dict[str, object]:
    """``/status`` ``detector.hands`` for the sessions' hand stages: :func:`~mocapd.pipeline.hand_landmarks.
    hand_status`, and under "auto" the first session's choice, reason and costs with every session's passes."""
    out = hand_status(decision, asked, [runner_of(f) for f in fronts])
    autos = [f for f in fronts if isinstance(f, AutoHands)]
    if autos:
        auto = autos[0].status()
        auto["passes"] = sum(a.passes for a in autos)
        auto["hand_passes"] = sum(a.hand_passes for a in autos)
        out["auto"] = auto
    return out
