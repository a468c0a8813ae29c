"""``[detector] landmarks = "auto"``: the landmark model chosen per detection pass from what it costs (issue 40).

A BlazePose crop costs more than the YOLO pass that placed it on a CPU (full 16-107 ms, heavy 49-272 ms per person
and view on the 2-core laptop, against 40-100 ms for a whole YOLO pass), so landmarks on every pass would halve the
detector's rate or worse, and the keypoint tracking between detections, which the output's rate rests on, would
carry the people for longer. "auto" therefore picks, per pass, from costs measured live:

* ``yolo_ms``: the detector's time of a pass (moving average),
* ``idle_ms``: how long a worker waited between passes (for frames; a GPU or a fast CPU waits, a loaded laptop
  never does),
* ``crops``: the people of a pass's views (each one crop),
* ``landmark_ms``: each model's time per crop, measured when it ran (heavy is estimated as
  :data:`HEAVY_OVER_FULL` times full until it has run once); a model's first run is not counted: it loads the model
  and allocates its tensors (a fresh daemon measured full at several times its cost on that run, chose off, and never
  ran full again to see its mistake),

and :func:`choose_landmarks` (pure) turns them into a model and a rate: run the model on every ``every``-th pass,
where ``every`` is the smallest that keeps the landmarks' average cost per pass within the allowance
(``share`` of a YOLO pass plus the idle time, :class:`LandmarkBudget`), heavy where it runs at least half as often as
full would, full otherwise, and off (YOLO's keypoints with tracking between, the floor) when a single landmark
pass would take longer than ``max_pass_ms`` or run rarer than every ``max_every``-th pass. The passes between give
YOLO's 17 points in the 33-point layout (the feet and hand points at confidence 0, "not seen"), so the keypoint
set the solver receives never changes. While the costs hold it off, the cheapest model still runs on one pass every
:data:`REPROBE_NS` to measure itself again: a cost is otherwise measured only when the model runs, and one measured
under a load that has passed (beyond what YOLO's own time tells, below) would keep "auto" off for good.

The governor (:mod:`mocapd.pipeline.governor`, ``[daemon] governor``) sheds the landmark model as one step of its
ladder: :attr:`AutoLandmarks.shed` then holds the choice at off, with the governor's reason, until it restores
the step. Without the governor the cost-based choice alone runs.

``/status`` ``detector.landmarks`` (:func:`auto_status`): the choice, its reason, the costs it came from, and per
camera the rate of passes with landmarks (every person of such a pass gets a crop: the per-person rate of
BlazePose's keypoints) beside the rate of all its detections.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from mocapd.core.keypoints import BLAZEPOSE33_FORMAT, COCO17_FORMAT
from mocapd.core.pose2d import PoseDetections
from mocapd.pipeline.landmarks import LandmarkRunner, landmark_status, with_landmarks

VARIANTS = ("heavy", "full")
"""The models "auto" chooses among, best first."""

HEAVY_OVER_FULL = 3.2
"""Heavy's cost per crop over full's until heavy has run (LiteRT on the 2-core laptop: 259-272 against 68-107 ms
loaded, 49-60 against 16-19 ms quieter; :mod:`mocapd.pipeline.landmarks`)."""

RATE_WINDOW_NS = 2_000_000_000
"""The per-camera rates in ``/status`` count this much of the run."""

REPROBE_NS = 20_000_000_000
"""While the measured costs hold the landmarks off, the cheapest model runs on one pass this often to measure itself
again (one pass's landmarks every 20 s: at most ``max_pass_ms``-ish late detections that often)."""

#: Where YOLO's COCO-17 points go in the 33-point layout (passes without landmarks).
_COCO_IN_33 = np.array([BLAZEPOSE33_FORMAT.index(n) for n in COCO17_FORMAT.keypoints], dtype=np.intp)


@dataclass(frozen=True)
class LandmarkCosts:
    """What a landmark pass would cost, measured (see the module docstring)."""

    yolo_ms: float
    """The detector's time of a pass."""
    idle_ms: float
    """The time a worker waited between passes."""
    crops: float
    """Crops a pass runs (the people of its views)."""
    landmark_ms: Mapping[str, float | None]
    """Per model of :data:`VARIANTS`: its time per crop (None: not measured yet)."""


@dataclass(frozen=True)
class LandmarkBudget:
    """How much of the detector the landmarks may take."""

    share: float = 0.5
    """On average a pass may grow by this share of its YOLO time (plus the idle time): the detector's rate falls
    to 1 / (1 + share) of YOLO's alone at most, which keypoint tracking fills."""
    max_pass_ms: float = 250.0
    """A pass with landmarks may take at most this long (its frames' detections are that much later)."""
    max_every: int = 8
    """Landmarks rarer than on every this-many-th pass are not run (off)."""
    heavy_factor: float = 2.0
    """Heavy is chosen while it runs at least 1 / heavy_factor as often as full would."""


@dataclass(frozen=True)
class LandmarkChoice:
    """What runs: ``variant`` ("heavy", "full" or None: off) on every ``every``-th pass, and why."""

    variant: str | None
    every: int
    reason: str


def _every(per_crop_ms: float, costs: LandmarkCosts, budget: LandmarkBudget) -> int | None:
    """The smallest rate divisor at which a model of ``per_crop_ms`` fits the budget (None: it does not)."""
    pass_ms = per_crop_ms * costs.crops
    if pass_ms > budget.max_pass_ms:
        return None
    allowance = budget.share * costs.yolo_ms + costs.idle_ms
    every = 1 if pass_ms <= allowance else math.ceil(pass_ms / max(allowance, 1e-6))
    return every if every <= budget.max_every else None


def choose_landmarks(
    costs: LandmarkCosts, budget: LandmarkBudget | None = None, allowed: Sequence[str] = VARIANTS
) -> LandmarkChoice:
    """The model and rate for ``costs`` (pure; see the module docstring). ``allowed``: the models that may run
    (empty: off, the governor shed them)."""
    b = budget if budget is not None else LandmarkBudget()
    if not allowed:
        return LandmarkChoice(None, 1, "shed by the governor")
    full = costs.landmark_ms.get("full")
    if "full" in allowed and full is None:
        return LandmarkChoice("full", 1, "measuring full's cost per crop")
    heavy = costs.landmark_ms.get("heavy")
    heavy_guess = heavy if heavy is not None else (full * HEAVY_OVER_FULL if full is not None else None)
    n_full = _every(full, costs, b) if full is not None and "full" in allowed else None
    n_heavy = _every(heavy_guess, costs, b) if heavy_guess is not None and "heavy" in allowed else None
    fits = (f"{costs.crops:.1f} crops x {{ms:.0f}} ms in {b.share:g} x {costs.yolo_ms:.0f} ms YOLO + "
            f"{costs.idle_ms:.0f} ms idle")  # fmt: skip
    if n_heavy is not None and (n_full is None or n_heavy <= b.heavy_factor * n_full):
        assert heavy_guess is not None
        why = fits.format(ms=heavy_guess) + ("" if heavy is not None else " (estimated from full; measuring)")
        return LandmarkChoice("heavy", n_heavy, f"heavy every {n_heavy}: {why}")
    if n_full is not None:
        assert full is not None
        return LandmarkChoice("full", n_full, f"full every {n_full}: {fits.format(ms=full)}")
    if "heavy" in allowed and heavy_guess is None:  # only heavy allowed and never measured
        return LandmarkChoice("heavy", 1, "measuring heavy's cost per crop")
    cheapest = min((v for v in (full, heavy_guess) if v is not None), default=0.0)
    return LandmarkChoice(None, 1, f"off: no model fits ({fits.format(ms=cheapest)}, at most "
                                   f"{b.max_pass_ms:.0f} ms a pass, every {b.max_every}th at the rarest)")  # fmt: skip


class _Mean:
    """An exponential moving average (None until the first value)."""

    def __init__(self, alpha: float = 0.2) -> None:
        self.alpha = alpha
        self.value: float | None = None

    def add(self, x: float) -> None:
        self.value = x if self.value is None else self.value + self.alpha * (x - self.value)


def as_33(people: PoseDetections) -> PoseDetections:
    """YOLO's COCO-17 people in the 33-point layout: the other points at (0, 0), confidence 0."""
    kp = np.zeros((len(people.keypoints), len(BLAZEPOSE33_FORMAT.keypoints), 3))
    if len(kp):
        kp[:, _COCO_IN_33] = people.keypoints[..., :3]
    return PoseDetections(people.boxes, people.scores, kp)


class AutoLandmarks:
    """One detector session's landmark front end under ``landmarks = "auto"`` (one per worker; not thread-safe
    for :meth:`run`, :meth:`status` may be read from any thread).

    Parameters
    ----------
    runners : mapping of str to LandmarkRunner
        The models it may run, by variant (made lazily by the runners: a model never chosen is never loaded).
    budget : LandmarkBudget, optional
    clock : callable returning int ns
        Measures the landmark models' time and the idle time between passes.
    """

    def __init__(
        self,
        runners: Mapping[str, LandmarkRunner],
        budget: LandmarkBudget | None = None,
        clock: Callable[[], int] = time.perf_counter_ns,
    ) -> None:
        self.runners = dict(runners)
        self.budget = budget if budget is not None else LandmarkBudget()
        self.clock = clock
        #: the governor's reason while it sheds the landmark model (None: not shed)
        self.shed: str | None = None
        self.choice = LandmarkChoice(None, 1, "no pass yet")
        self._yolo, self._idle, self._crops = _Mean(), _Mean(), _Mean()
        self._per_crop: dict[str, _Mean] = {v: _Mean() for v in self.runners}
        self._yolo_then: dict[str, float] = {}  # YOLO's pass time when each model's cost was last measured
        self._warm: set[str] = set()  # the models that have run once (their first run is not counted as their cost)
        self._ran_ns: dict[str, int] = {}  # when each model last ran
        self._since = 0  # passes since the last one with landmarks
        self._last_end: int | None = None
        self.passes = 0
        self.landmark_passes = {v: 0 for v in self.runners}
        self.crops = 0
        self._lock = threading.Lock()
        self._seen: dict[int, deque[int]] = {}  # camera -> end times of its passes
        self._marked: dict[int, deque[int]] = {}  # camera -> end times of its passes with landmarks

    def costs(self) -> LandmarkCosts:
        """The costs measured so far (YOLO 0 ms and one crop until the first pass).

        A model's cost per crop is measured only when it runs, YOLO's on every pass: a model measured on a busier
        (or quieter) CPU than now is scaled by how YOLO's pass time changed since, both being the same kind of CPU
        work. Otherwise one measurement under a passing load spike would hold "auto" at off for good."""
        yolo = self._yolo.value or 0.0
        per_crop: dict[str, float | None] = {}
        for v, m in self._per_crop.items():
            then = self._yolo_then.get(v, 0.0)
            per_crop[v] = None if m.value is None else (m.value * yolo / then if then > 0 and yolo > 0 else m.value)
        return LandmarkCosts(yolo, self._idle.value or 0.0, self._crops.value or 1.0, per_crop)

    def decide(self) -> LandmarkChoice:
        """The choice for the next pass from the costs so far (:func:`choose_landmarks`), the governor's shedding
        first."""
        if self.shed is not None:
            return LandmarkChoice(None, 1, f"shed by the governor: {self.shed}")
        return choose_landmarks(self.costs(), self.budget, [v for v in VARIANTS if v in self.runners])

    def current(self) -> LandmarkChoice:
        """The choice of the last pass, or the governor's shedding at once (before the next pass)."""
        return self.decide() if self.shed is not None else self.choice

    def run(
        self,
        images: Sequence[np.ndarray],
        people: Sequence[PoseDetections],
        detector_ns: int,
        cameras: Sequence[int] | None = None,
    ) -> list[PoseDetections]:
        """One pass's people in the 33-point layout, with landmarks when this pass is one the choice runs them on.

        Parameters
        ----------
        images : sequence of uint8 array, shape (H, W, 3), BGR
        people : sequence of PoseDetections
            YOLO's people of each image (COCO-17).
        detector_ns : int
            The detector's time of this pass (measured by the caller around YOLO).
        cameras : sequence of int, optional
            The camera of each image (per-camera rates in ``/status``; None: counted as camera -1).
        """
        start = self.clock() - detector_ns
        if self._last_end is not None:
            self._idle.add(max(0.0, (start - self._last_end) / 1e6))
        self._yolo.add(detector_ns / 1e6)
        n_people = sum(len(p.keypoints) for p in people)
        if n_people:
            self._crops.add(float(n_people))
        self.choice = choice = self.decide()
        self._since += 1
        out = [as_33(p) for p in people]
        variant = choice.variant if self._since >= choice.every else None
        if choice.variant is None and self.shed is None:
            variant = self._reprobe(start)
        ran = False
        if variant is not None and n_people:
            t0 = self.clock()
            found = self.runners[variant].run(images, [p.keypoints for p in people])
            crops = sum(r is not None for lm in found for r in lm.rois)
            self._ran_ns[variant] = t0
            if crops and variant not in self._warm:
                self._warm.add(variant)  # loading and first allocations: not what a pass costs
            elif crops:
                self._per_crop[variant].add((self.clock() - t0) / 1e6 / crops)
                self._yolo_then[variant] = self._yolo.value or 0.0
            for i, lm in enumerate(found):
                for j, roi in enumerate(lm.rois):
                    if roi is not None:  # a person without a crop keeps YOLO's points
                        out[i].keypoints[j] = lm.keypoints[j]
            self._since = 0
            ran = True
            with self._lock:
                self.landmark_passes[variant] += 1
                self.crops += crops
        end = self.clock()
        self._last_end = end
        with self._lock:
            self.passes += 1
            for cam in cameras if cameras is not None else [-1] * len(images):
                self._window(self._seen, cam, end)
                if ran:
                    self._window(self._marked, cam, end)
        return out

    def _reprobe(self, now: int) -> str | None:
        """While the costs hold the landmarks off: the cheapest measured model, when it last ran
        :data:`REPROBE_NS` or more before ``now`` (None otherwise)."""
        c = self.costs().landmark_ms
        measured = [v for v in self.runners if c.get(v) is not None]
        if not measured:
            return None
        cheapest = min(measured, key=lambda v: c[v] or 0.0)
        return cheapest if now - self._ran_ns.get(cheapest, now) >= REPROBE_NS else None

    @staticmethod
    def _window(times: dict[int, deque[int]], cam: int, now: int) -> None:
        q = times.setdefault(cam, deque())
        q.append(now)
        while q and q[0] < now - RATE_WINDOW_NS:
            q.popleft()

    def rates(self, now: int | None = None) -> dict[int, dict[str, float]]:
        """Per camera: its detection passes and those with landmarks per second, over the last two seconds."""
        now = self.clock() if now is None else now
        out = {}
        with self._lock:
            for cam, seen in self._seen.items():
                marked = self._marked.get(cam, deque())
                out[cam] = {
                    "detect_hz": sum(t >= now - RATE_WINDOW_NS for t in seen) / (RATE_WINDOW_NS / 1e9),
                    "landmark_hz": sum(t >= now - RATE_WINDOW_NS for t in marked) / (RATE_WINDOW_NS / 1e9),
                }
        return out


def auto_status(fronts: Sequence[AutoLandmarks], camera_names: Sequence[str] = ()) -> dict[str, object]:
    """``/status`` ``detector.landmarks`` under "auto": the first session's choice and reason, the costs it came
    from, and over all sessions the passes, the landmark passes per model, the crops and the per-camera rates."""
    first = fronts[0]
    choice = first.current()
    c = first.costs()
    per_cam: dict[int, dict[str, float]] = {}
    for f in fronts:
        for cam, r in f.rates().items():
            acc = per_cam.setdefault(cam, {"detect_hz": 0.0, "landmark_hz": 0.0})
            acc["detect_hz"] += r["detect_hz"]
            acc["landmark_hz"] += r["landmark_hz"]

    def name(cam: int) -> str:
        return camera_names[cam] if 0 <= cam < len(camera_names) else ("all" if cam < 0 else str(cam))

    return {
        "asked": "auto",
        "running": choice.variant or "off",
        "every": choice.every,
        "reason": choice.reason,
        "shed": first.shed is not None,
        "costs": {"yolo_ms": round(c.yolo_ms, 1), "idle_ms": round(c.idle_ms, 1), "crops_per_pass": round(c.crops, 2),
                  "landmark_ms_per_crop": {v: None if m is None else round(m, 1) for v, m in c.landmark_ms.items()}},
        "passes": sum(f.passes for f in fronts),
        "landmark_passes": {v: sum(f.landmark_passes.get(v, 0) for f in fronts) for v in VARIANTS},
        "crops": sum(f.crops for f in fronts),
        # Every person of a pass with landmarks gets a crop: landmark_hz is each person's rate of BlazePose points.
        "cameras": {name(cam): {k: round(v, 1) for k, v in r.items()} for cam, r in sorted(per_cam.items())},
    }  # fmt: skip


LandmarkFront = LandmarkRunner | AutoLandmarks | None
"""A detector session's landmark stage: a fixed model, "auto", or none."""


def mark(
    front: LandmarkFront,
    images: Sequence[np.ndarray],
    people: Sequence[PoseDetections],
    detector_ns: int = 0,
    cameras: Sequence[int] | None = None,
) -> list[PoseDetections]:
    """The people of one pass through the session's landmark stage (:func:`with_landmarks` for a fixed model or
    none, :meth:`AutoLandmarks.run` under "auto", which also takes the pass's detector time and cameras)."""
    if isinstance(front, AutoLandmarks):
        return front.run(images, people, detector_ns, cameras)
    return with_landmarks(front, images, people)


def landmark_front(asked: str, threads: int) -> LandmarkFront:
    """The landmark stage ``[detector] landmarks = asked`` gives one session (ModelError when a model it needs was
    not fetched): None for "off", a :class:`LandmarkRunner` for "full"/"heavy", :class:`AutoLandmarks` over both for
    "auto"."""
    if asked == "off":
        return None
    if asked == "auto":
        return AutoLandmarks({v: LandmarkRunner(v, threads=threads) for v in VARIANTS})
    return LandmarkRunner(asked, threads=threads)


def front_status(asked: str, fronts: Sequence[LandmarkFront], camera_names: Sequence[str] = ()) -> dict[str, object]:
    """``/status`` ``detector.landmarks`` for the sessions' ``fronts``."""
    autos = [f for f in fronts if isinstance(f, AutoLandmarks)]
    if autos:
        return auto_status(autos, camera_names)
    return landmark_status(asked, [f for f in fronts if isinstance(f, LandmarkRunner)])


def has_auto(fronts: Sequence[LandmarkFront]) -> bool:
    """Whether any of ``fronts`` is "auto" (the governor's ladder then has the landmark step)."""
    return any(isinstance(f, AutoLandmarks) for f in fronts)


def shed_landmarks(fronts: Sequence[LandmarkFront], reason: str | None) -> None:
    """The governor's hook: hold every "auto" front at off with ``reason`` (None: restore the cost-based choice).
    A model named in the config ("full", "heavy") is what the user asked for and is left running."""
    for f in fronts:
        if isinstance(f, AutoLandmarks):
            f.shed = reason


def status_field(fronts: Sequence[LandmarkFront]) -> str | None:
    """The console status line's part for "auto": ``landmarks full every 3 (2.0 of 6.1 Hz)`` (landmark passes and
    all detection passes per second, summed over the cameras); None without "auto"."""
    autos = [f for f in fronts if isinstance(f, AutoLandmarks)]
    if not autos:
        return None
    choice = autos[0].current()
    rates = [r for f in autos for r in f.rates().values()]
    marked, seen = sum(r["landmark_hz"] for r in rates), sum(r["detect_hz"] for r in rates)
    every = f" every {choice.every}" if choice.variant is not None and choice.every > 1 else ""
    return f"landmarks {choice.variant or 'off'}{every} ({marked:.1f} of {seen:.1f} Hz)"
