"""The governor: holds the output tick on a machine too slow for everything the daemon could do (issue 39).

The output tick is what a user sees: a VR avatar or a game character at the configured rate. When the tick's work
does not fit its period (a slower CPU, a game sharing the laptop, more people), something has to give, and it must
not be the tick. The governor measures, every ``window_s``, how long the tick took (wall time from its scheduled
instant to its publication, p95 over the window, which includes the CPU it did not get) and how many ticks were
missed, and moves one step along a fixed ladder of work to leave out:

====  =====================================  ======================================================================
step  what is shed                           what it costs
====  =====================================  ======================================================================
0     nothing                                —
1     landmark model off                     with ``[detector] landmarks = "auto"``: YOLO's keypoints alone, no
                                             feet or hand points (the landmark model is the detector's costliest
                                             part on a CPU: 16-272 ms a crop); a model named in the config keeps
                                             running; without "auto" the step is left out (:func:`ladder`)
2     detector at 75 % duty                  each detector worker rests a third of a pass after each pass (at most
                                             0.3 s, none while a camera has gone a second without a detection):
                                             fewer detections (tracking carries the people between them), the CPU
                                             (or the CPU budget's quota) and the interpreter left to the tick
3     detector at 50 % duty
4     detector at 35 % duty
5     ... and keypoint tracking 60 -> 36 Hz  each camera's keypoints between detections at 60 % of the rate (the
                                             scheduler interpolates between them; ``latency_s = "auto"`` covers a
                                             longer frame interval): still above the 30 Hz a camera and person
6     ... and keypoint tracking 60 -> 33 Hz  at 55 % of the rate: 30 Hz or more a camera and person when a frame
                                             is lost now and then (at half the rate, 30 Hz nominal, 27.6-29.8 Hz
                                             were measured: below the target)
7     ... and people solved at half rate     the scheduler solves people on every other tick only; on the ticks
                                             between, each person is their last solve carried one period on at
                                             the velocity of their last two (:mod:`mocapd.core.carry`, marked
                                             ``filled``): the output keeps its rate, the solves (the tick's
                                             costliest part) halve. On every rig (the synthetic rig's ladder is
                                             step 0, this and the next): a filled frame guesses, and misses a turn
                                             of motion until the next solve
8     ... people solved on every third tick  the deeper rungs, for a machine the steps above leave late (the quiet
                                             2-core demo; a CPU budget of 0.8 of a core): ``solve_every = 3``, two
                                             ticks of three carried (the carry covers one and two periods alike);
                                             on every rig
9     ... keypoint tracking at a third       20 Hz a 60 fps camera, keypoints 50 ms apart, interpolated: below the
                                             30 Hz target, so last of the steps that keep the detector's duty,
                                             where keypoint tracking runs
10    ... the detector paced (each camera    where a packed detector and keypoint tracking run: no duty; after each
      every 1 s) on half-scale tiles         pass the worker rests until the camera detected longest ago is 1 s
                                             past its detection, and every packed tile is at half its whole-frame
                                             scale (``PackedDetector.tile_ratio``; passes all packed), so that one
                                             canvas takes the four demo cameras' people: half the CPU a camera
                                             frame, the keypoints ~1.5 % of the image height from full-scale
                                             tiles'. For a CPU budget of 0.4 of a core on the 2-core EPYC (0.8
                                             of one on the issue's slower CPU; docs/daemon.md, "The paced
                                             detector"). The tracking carries the people between detections (its
                                             ``max_age_s``, 2 s, bounds the pace: the daemon paces at most 3/4 of
                                             it; paced at 1.5 s, a camera's people were lost and came back as new
                                             identities). Shed into only from a window that missed
                                             ``pace_missed`` (6 %) of its ticks: the quiet 2-core demo's windows
                                             at step 9 missed 2-6 of ~120 and it held its ticks there
====  =====================================  ======================================================================

Why this order, and why it ends there. Steps 8 and 9 come after the half-rate solve because each costs the user more
than any step above it (two guessed frames of three, keypoints below 30 Hz): they are for a machine the first seven
leave late. The solves go first of the two, so that a machine that holds its ticks at step 8 keeps the keypoints at 30
Hz or more; the tracking at a third (20 Hz) is the last resort. The quiet 2-core camera demo walks to step 9 in either
order (its windows at step 8 still missed 2-6 of ~120 ticks) and holds its ticks there (0.6-1.1 % missed) at 19-21 Hz of
keypoints a camera and person; at 0.8 of a core the tracking at a third saved more CPU than the solves (docs/daemon.md,
"The deeper rungs"). The detector at a duty below 35 % is not on the ladder: at 20 % it took no CPU away, on the 2-core
demo or at 0.8 of a core, because its passes already leave some camera a second without a detection there, and then it
does not rest (a rest would age that camera's tracked people out). Under a CPU budget a pass's wall time is mostly the
quota's throttling, and a duty's rest is a multiple of that wall time: at 20 % duty, with the guard lengthened to
1.6 s, the detector still took 0.09 s/s of a 0.4-core budget. The last step paces it instead (a rest until the
camera detected longest ago is due, whatever a pass took) on half-scale tiles: 0.035-0.045 s/s, and the ticks held
(docs/daemon.md, "The paced detector"). It comes last because each detection is coarser (a network pixel is twice
the source pixels) and a camera's people are carried by the tracking alone for a second or more.

Each of the first seven steps is placed by what it saved, measured with the step pinned (``[daemon] governor_pin_step``)
on the 2-core camera demo, against what it costs the user (docs/daemon.md, "The ladder's order, measured"). The tracking
rate went first while the tracking's optical flow cost ~0.5 of a core; compiled, four 60 fps cameras' tracking costs
~0.27 of a core, so halving it saves little, and it costs the keypoint rate itself (28-29 Hz a camera and person at half
rate, below the 30 Hz target) and a frame interval of latency. The detector's duty costs only how often the tracked
keypoints are re-anchored (the tracking carries the people between detections, one frame after capture: the latency a
user feels is the tracking's): it goes first, the tracking rate last. Tracking itself is never shed: a starved detector
delivers a camera's keypoints 1-3 times a second, too far apart for the scheduler to interpolate
(``keypoint_max_gap_s``), so people dropped out of the solve and came back as new identities (the camera demo's test, 2
runs of 6 with a last step "tracking off"), and the latency became the detector's (1-2 s). The left/right flip search is
not on the ladder either: compiled, it costs ~0.15 ms a person a tick (``person_cpu_ms.unflip`` in ``/status``), and
reusing a decision on ticks between searches swapped a view's limbs whenever the detector had re-labelled it meanwhile
(a demo person's arms sized 25 % long).

It sheds one step when, in two windows in a row, the tick's p95 exceeded ``shed_above`` of the period or more than
``max_missed`` of the window's ticks were missed (one slow window, a start-up burst, is no reason; but one window
that missed ``severe_missed`` of its ticks, a quarter, sheds at once, without waiting for the step before to be
judged: most of the output is being lost; so does, after a step, a window that was still late by the same rule
while the other programs used under ``others_share`` of the machine: see "Fast when the lateness is ours" below),
and restores one step only after ``hold_s`` in which the p95 stayed below ``restore_below`` of the period with no
tick missed (hysteresis: a step is not taken back the moment it helped). Its time starts at the first published
tick, not when the daemon is built: opening the cameras and loading the models can outlast the ``settle_s`` in
which nothing is shed.

A cause test before the next step. Shedding helps only when the lateness is this process's work: on a machine
loaded by other programs (load 15-20 on 2 cores) the tick's p95 stayed at 45-60 ms while the governor walked down
the whole ladder in 10 s. So each step is on trial for ``judge_windows`` windows (nothing else changes meanwhile)
and judged against the windows before it at the level it left, on medians and pooled counts, never on one window:
a window's p95 varies by ~17 % on a quiet machine, and the first window after a useful step was once 30 % worse
(60.9 -> 79.9 ms) and took the step back. The step *helped* when the median p95 fell by ``helped_by``, or the
pooled missed ticks fell significantly (a one-sided binomial test at ``significance``), or the tick fits again:
the next step may follow. When it did not, and it took work away (the median of the daemon's process CPU per
second, passed to :meth:`Governor.step`, fell by ``bite`` or more), whose lateness it is depends on what the
other programs on the machine used in its trial (the machine's busy CPU time less this process's, per second, over
the same windows: :mod:`mocapd.io.machine_cpu`, passed to :meth:`Governor.step`). When they used ``others_share`` of
the machine's CPUs or more (a VR game takes a core or more), the lateness is not ours: the step is taken back and
nothing more is shed for ``retry_s`` (doubling, up to 4 x, while retries keep failing). When they used less, nobody
else was loading the machine, so the lateness is ours and the step was the wrong one to help it: the step is kept
and the next may follow. On the quiet 2-core ``mocapd demo`` the daemon used ~1.35-1.6 cores, its fake cameras
~0.24 together, nothing else ran, and the tick thread waited for a core 15 % of the time: the old rule took a
useful ladder back there in about half the runs ("did not help: tick p95 70.8 -> 71.0 ms ... process CPU 1.61 ->
1.51 s/s") and the run lost 300-700 ticks. Where the machine's CPU cannot be read (psutil cannot read its CPU times),
the old rule stands: a step that took CPU away without helping is taken back. A step that took no measurable CPU
away (a landmark model that was not running) proves nothing either way: the next may follow.

Fast when the lateness is ours. While the other programs use under ``others_share`` of the machine, every
verdict a trial can reach keeps the step and lets the next follow: it helped (the next follows), it did not help
but took CPU (kept: the lateness is ours), it took no CPU (proves nothing: the next follows). Waiting for the
verdict then only costs windows of missed ticks: on the quiet 2-core `mocapd demo` each of the trials' windows
missed 5-9 of ~120 ticks while the ladder was walked, below the tenth a window had to miss to end its trial early,
and most of a run's missed ticks fell in those ~24 s. So a step on trial whose window was still late (p95 over
``shed_above`` periods or more than ``max_missed`` missed) while the others used under ``others_share`` is kept at
once, unjudged, and the next step is shed in the same window ("step 2 kept unjudged: the window after it was still
late while the others used under 25 % of the machine (the lateness is ours)"). Where the others used more, or
their CPU is not measured, each step is judged over its trial as before. Restoring is unchanged: a machine shed
too far gets a step back after ``hold_s`` of calm.

Pure state: times are arguments; the daemon feeds it (:meth:`Governor.observe` and :meth:`Governor.step` per
tick) and applies :attr:`Governor.level`'s settings to the keypoint sources, the detectors and the scheduler
(``solve_every``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.special import bdtr

from mocapd.io.machine_cpu import MachineCpu


@dataclass(frozen=True)
class Level:
    """What one step of the ladder runs."""

    name: str
    tracking_rate: float  # keypoint tracking's rate as a share of its configured rate (0: off)
    detector_duty: float  # the share of wall time each detector worker may spend in passes
    landmarks: bool = True  # landmarks = "auto" may run a landmark model (False: YOLO's keypoints alone)
    solve_every: int = 1  # the scheduler solves people on every n-th tick, carrying them on the ticks between
    pace_s: float = 0.0  # > 0: the detector's passes paced (not by duty): each camera detected about this often
    tile_ratio: float = 1.0  # packed tiles at most this multiple of their camera's whole-frame scale


def _named(
    tracking_rate: float,
    detector_duty: float,
    landmarks: bool = False,
    solve_every: int = 1,
    pace_s: float = 0.0,
    tile_ratio: float = 1.0,
) -> Level:
    """A level named by what it sheds, in the ladder's words (the landmark model is named only where nothing else
    is shed: every later step keeps it off)."""
    shed = []
    if pace_s > 0.0:
        shed.append(f"detector paced (each camera every {pace_s:g} s, packed tiles at {tile_ratio:g} scale)")
    elif detector_duty < 1.0:
        shed.append(f"detector at {detector_duty * 100:g} % duty")
    if tracking_rate < 1.0:
        shed.append(f"keypoint tracking at {_TRACKING_RATES.get(tracking_rate, f'{tracking_rate * 100:g} % rate')}")
    if solve_every > 1:
        shed.append(_SOLVES.get(solve_every, f"people solved on every {solve_every}th tick"))
    name = ", ".join(shed) or ("nothing shed" if landmarks else "landmark model off")
    return Level(name, tracking_rate, detector_duty, landmarks, solve_every, pace_s, tile_ratio)


#: keypoint tracking's rate at steps 6-8: 33 Hz of a 60 fps camera, so that the keypoints stay at 30 Hz or more a
#: camera and person when a frame is lost now and then (at half rate, 30 Hz nominal, 27.6-29.8 Hz were measured)
NEAR_HALF = 0.55
_TRACKING_RATES = {0.6: "60 % rate", NEAR_HALF: "55 % rate", 1 / 3: "a third of its rate"}
_SOLVES = {2: "people solved at half rate", 3: "people solved on every third tick"}
THIRD = 1 / 3  # keypoint tracking's rate at the deepest tracking step
#: the deepest step (issue 39, a CPU budget of 0.8 of a core on the issue's slower CPU): the detector's passes
#: paced, one detection a camera a second (the tracking carries the people between; its ``max_age_s`` of 2 s bounds
#: it: at 1.5 s a camera's people were lost and re-enrolled, docs/daemon.md), on packed tiles at half their
#: whole-frame scale (a pass of half the CPU)
PACE_S = 1.0
HALF_SCALE = 0.5

LADDER: tuple[Level, ...] = (
    _named(1.0, 1.0, True),
    _named(1.0, 1.0),
    _named(1.0, 0.75),
    _named(1.0, 0.5),
    _named(1.0, 0.35),
    _named(0.6, 0.35),
    _named(NEAR_HALF, 0.35),
    _named(NEAR_HALF, 0.35, solve_every=2),
    # The deeper rungs, for a machine the steps above leave late (the quiet 2-core demo, a CPU budget of 0.8 of a
    # core): docs/daemon.md, "The deeper rungs".
    _named(NEAR_HALF, 0.35, solve_every=3),
    _named(THIRD, 0.35, solve_every=3),
    # The detector paced on half-scale tiles, where a packed detector and keypoint tracking run: docs/daemon.md,
    # "The paced detector".
    _named(THIRD, 0.35, solve_every=3, pace_s=PACE_S, tile_ratio=HALF_SCALE),
)
#: the tracking steps alone, for a rig whose keypoint tracking runs without a detector of its own to rest
TRACKING_ALONE = (_named(0.6, 1.0), _named(NEAR_HALF, 1.0))


def ladder(landmarks: bool, tracking: bool = True, detector: bool = True) -> tuple[Level, ...]:
    """:data:`LADDER` with only the steps that shed something this daemon runs: the landmark step where a detector
    runs ``landmarks = "auto"``, the detector's duty steps where a detector of its own runs, the tracking steps where
    keypoint tracking runs, then, on every rig, people solved at half rate and on every third tick, and last, where
    keypoint tracking runs, tracking at a third of its rate (the synthetic rig's simulated detections have none of
    the others: its ladder is step 0 and the two solve steps). A step that
    sheds nothing would cost a trial, and say it shed what is not there."""
    steps = [LADDER[0]]
    if landmarks:
        steps.append(LADDER[1])
    if detector:
        steps.extend(LADDER[2:5])
    if tracking:
        steps.extend(LADDER[5:7] if detector else TRACKING_ALONE)
    last = steps[-1]
    steps.append(_named(last.tracking_rate, last.detector_duty, last.landmarks, 2))
    steps.append(_named(last.tracking_rate, last.detector_duty, last.landmarks, 3))
    if tracking:
        steps.append(_named(THIRD, last.detector_duty, False, 3))
        if detector:  # the detector paced: the tracking carries each camera's people between its detections
            steps.append(LADDER[10])
    return tuple(steps)


@dataclass(frozen=True)
class GovernorOptions:
    """When the governor sheds and restores work."""

    window_s: float = 2.0
    """Decisions are made on this much of the run."""
    shed_above: float = 2.5
    """Shed a step when the tick's p95 (schedule to publication) exceeds this many periods (a tick published late
    still counts, within ``max_catch_up_s``: 2-core laptops whose ticks fit ran at 28 ms p95, issue 31) ..."""
    max_missed: float = 0.01
    """... or more than this share of the window's ticks were missed."""
    restore_below: float = 0.6
    """Restore a step when the p95 stayed below this share of the period, with no tick missed, ..."""
    hold_s: float = 6.0
    """... for this long (and at least this long after the last change)."""
    settle_s: float = 5.0
    """Nothing is shed in the first seconds after the first tick (caches warming up, people enrolling), unless a
    window in them missed ``severe_missed`` of its ticks: on the quiet 2-core `mocapd demo` the settling time's
    windows lost 25-60 % of their ticks (output at 16-35 Hz) and the walk down the ladder began only after it, ~170-240
    of a run's ~330-390 missed ticks falling in its first 10 s (seventh session); a step shed needlessly on a faster
    machine is restored after ``hold_s`` of calm."""
    helped_by: float = 0.05
    """A step helped when the median of the windows' p95 after it was at least this share lower than before it (or
    its missed ticks significantly fewer, or the tick fits again). Half the 10 % a step must bring to count: the
    threshold between no effect and an effect worth its cost, so that window-to-window noise (~17 % of a window's
    p95 on the quiet 2-core camera demo) errs as often either way."""
    judge_windows: int = 3
    """A step is judged on this many windows after it (no further step meanwhile), against up to this many before
    it at the level it left: medians, so that one window's noise decides nothing."""
    severe_missed: float = 0.25
    """A window that missed at least this share of its ticks sheds the next step at once: the step before is not
    kept on trial and one such window is enough. With seven steps judged over three windows each, walking the ladder
    took 31 s of 23-34 Hz output in `mocapd demo` on the 2-core machine (docs/daemon.md); below this share the cause
    test judges each step as before."""
    hurry_missed: float = 0.0
    """A step on trial whose window was still late (by the rule that sheds: p95 over ``shed_above`` periods or more
    than ``max_missed`` missed) and missed at least this share of its ticks, while the other programs used under
    ``others_share`` of the machine in it, is kept at once and the next step follows (as after a
    ``severe_missed`` window): with nobody else loading the machine every verdict of the trial keeps the step (the
    lateness is ours). 0: any late window. It was a tenth until the eighth session, and on the quiet 2-core `mocapd
    demo` the trials' windows missed 5-9 of ~120 ticks, under it, while most of a run's missed ticks fell in the
    ~24 s the ladder took. Where the others' CPU is high or not measured, the trial runs as before."""
    significance: float = 0.05
    """Fewer missed ticks after a step count as help when a one-sided binomial test on the pooled counts (before
    against after, in proportion to their ticks) gives a p-value below this."""
    bite: float = 0.05
    """A step took work away when the process's CPU per second fell by at least this share."""
    retry_s: float = 30.0
    """After a step that took work away without bringing the lateness down: nothing shed for this long (doubled
    for each further such step in a row, up to 4 x)."""
    pace_missed: float = 0.06
    """The detector is paced (the last step) only after a window that missed at least this share of its ticks: on
    the quiet 2-core `mocapd demo` the windows at the step before missed 2-6 of ~120 ticks (the lateness the fast
    walk sheds on) and it held its ticks there (0.6-1.1 % missed, eighth session), where the paced step would cost
    coarser detections for nothing; at a CPU budget of 0.4 of a core on the 2-core EPYC they missed 7-18 %."""
    others_share: float = 0.25
    """A step that took work away without helping is taken back only when the other programs on the machine used
    at least this share of its CPUs in the trial (the median of its windows; below it the lateness is this
    process's own and the step stays). A quarter: on the quiet 2-core demo the fake cameras, the only other
    programs, used ~0.24 of a core (12 %), a VR game takes a core or more (50 % of 2 cores)."""


@dataclass(frozen=True)
class _Window:
    """What one window measured (or several pooled: :func:`_pooled`)."""

    p95_ns: float
    missed: int
    ticks: int
    cpu_rate: float | None  # the process's CPU seconds per wall second (None: not measured)
    others_rate: float | None = None  # the other programs' CPU seconds per wall second (None: not measured)

    @property
    def missed_share(self) -> float:
        return self.missed / self.ticks if self.ticks else 0.0

    def cpu_text(self, cpus: int | None) -> str:
        text = "" if self.cpu_rate is None else f", process CPU {self.cpu_rate:.2f} s/s"
        if self.others_rate is not None and cpus:
            text += f", others' CPU {self.others_rate:.2f} s/s of {cpus} cores"
        return text


def _median(values: Sequence[float | None]) -> float | None:
    """The median, or None when any is None (not measured in every window)."""
    known = [v for v in values if v is not None]
    return float(np.median(known)) if known and len(known) == len(values) else None


def _pooled(windows: Sequence[_Window]) -> _Window:
    """Windows as one: the median of their p95s and of their CPU rates, ours and the others' (one noisy window moves
    none of them), their missed ticks and ticks summed."""
    return _Window(
        float(np.median([w.p95_ns for w in windows])),
        sum(w.missed for w in windows),
        sum(w.ticks for w in windows),
        _median([w.cpu_rate for w in windows]),
        _median([w.others_rate for w in windows]),
    )


def fewer_missed(before: _Window, after: _Window, significance: float) -> bool:
    """Whether ``after`` missed significantly fewer ticks than ``before``, for their numbers of ticks: a one-sided
    binomial test of the missed ticks' split between the two, against the split of their ticks (a Poisson rate
    comparison: what a halving of 3 missed ticks to 1 cannot show, 40 to 20 does)."""
    total = before.missed + after.missed
    if total == 0 or after.missed_share >= before.missed_share:
        return False
    share = after.ticks / (after.ticks + before.ticks)
    return float(bdtr(after.missed, total, share)) < significance  # P(at most after.missed of them after)


@dataclass
class _Trial:
    """A step just taken: the step it left, the windows before it (at the level it left) and those since."""

    from_index: int
    before: tuple[_Window, ...]
    after: list[_Window] = field(default_factory=list)


class Governor:
    """Chooses the step of its ladder (:data:`LADDER` by default) the daemon runs at (see the module docstring)."""

    def __init__(
        self,
        period_ns: int,
        options: GovernorOptions | None = None,
        start_ns: int = 0,
        steps: tuple[Level, ...] = LADDER,
        pin: int | None = None,
    ) -> None:
        """``pin``: hold the level at this step of ``steps`` (a developer's way to measure what a step saves,
        ``[daemon] governor_pin_step``); it still measures the windows. Raises ValueError when the ladder has no
        such step."""
        self.options = options if options is not None else GovernorOptions()
        self.ladder = steps  # LADDER, or :func:`ladder`'s steps for what the rig runs
        self.period_ns = period_ns
        if pin is not None and not 0 <= pin < len(steps):
            raise ValueError(f"step {pin} is not on this rig's ladder (steps 0..{len(steps) - 1}: "
                             f"{', '.join(lv.name for lv in steps)})")  # fmt: skip
        self.pinned = pin is not None
        self.step_index = pin or 0
        self._start_ns = start_ns
        self._window_start = start_ns
        self._first_tick: int | None = None  # the first published tick's instant: settling counts from it
        self._calm_since: int | None = start_ns
        self._changed_ns = start_ns
        self._durations: list[int] = []
        self._missed = 0
        self.changes = 0
        self.last_reason = "start" if pin is None else f"pinned at step {pin} ([daemon] governor_pin_step)"
        self.last_p95_ms: float | None = None
        #: the last changes: (seconds since the first tick, step, reason), oldest first
        self.history: list[tuple[float, int, str]] = []
        self._cpu_at: tuple[int, int] | None = None  # (wall, process CPU) at the window's start
        #: (wall, process CPU, the machine's busy CPU) at the window's start, where the machine's is measured
        self._machine_at: tuple[int, int, int] | None = None
        self.cpus: int | None = None  # the machine's CPUs (None: its CPU not measured)
        self._last: _Window | None = None  # the last window closed (for /status)
        self._level_windows: list[_Window] = []  # the windows since the level last changed (the last few)
        self._trial: _Trial | None = None  # the step taken last, until it is judged
        self._verdict = ""  # the judgement of the last step on trial, said with the next step shed in its window
        self._no_shed_until = start_ns
        self._futile = 0  # steps in a row that took work away and did not help

    @property
    def level(self) -> Level:
        return self.ladder[self.step_index]

    def observe(self, tick_ns: int, missed: int = 0) -> None:
        """One published tick: how long after its scheduled instant it was published (ns), and the ticks skipped
        before the next one."""
        self._durations.append(tick_ns)
        self._missed += missed

    def due(self, now_ns: int) -> bool:
        """Whether :meth:`step` at ``now_ns`` starts the governor or closes a window: the instants it needs the
        machine's CPU at (reading it on every tick would cost the tick for nothing)."""
        return self._first_tick is None or now_ns - self._window_start >= self.options.window_s * 1e9

    def step(self, now_ns: int, cpu_ns: int | None = None, machine: MachineCpu | None = None) -> bool:
        """After each published tick (it acts once a window ``window_s`` has passed): shed or restore a step.
        ``cpu_ns``: the daemon's process CPU time now (any origin; None: not measured, then a step that did not
        help is taken back as one that took work away). ``machine``: the machine's CPU counters now, needed only
        where :meth:`due` (None: not read now; never given: not measured, then the others' share is unknown and
        such a step is taken back as before). Returns True when the level changed."""
        measured = None
        if self._first_tick is None:
            self._start(now_ns, cpu_ns, machine)
        else:
            measured = self._close_window(now_ns, cpu_ns, machine)
        if measured is None or self.pinned:
            return False
        window, began = measured
        o = self.options
        self._level_windows = [*self._level_windows, window][-o.judge_windows :]
        calm = window.p95_ns < o.restore_below * self.period_ns and window.missed == 0
        if self._calm_since is None and calm:
            self._calm_since = began  # calm since this window began
        elif not calm:
            self._calm_since = None
        self._verdict, trial = "", self._trial
        severe = window.missed_share >= o.severe_missed
        hurried = False
        if trial is not None:
            trial.after.append(window)
            # Still late while nobody else loads the machine: every verdict the trial could reach keeps the step
            # (the lateness is ours), so it ends here rather than lose more windows' ticks to its verdict.
            hurried = (not severe and len(trial.after) < o.judge_windows and self._overran(window)
                       and window.missed_share >= o.hurry_missed and self._ours(window))  # fmt: skip
            if len(trial.after) < o.judge_windows and not (severe or hurried):
                return False  # a step on trial: no other change until it is judged
            self._trial = None
            if severe:  # most of the output is lost: no time for a trial, the step stays and the next follows
                self._verdict = (f"step {trial.from_index + 1} kept unjudged: {window.missed} of {window.ticks} "
                                 f"ticks missed in the window after it")  # fmt: skip
            elif hurried:
                self._verdict = (f"step {trial.from_index + 1} kept unjudged: the window after it was still late "
                                 f"while the others used under {o.others_share * 100:g} % of the machine (the "
                                 f"lateness is ours)")  # fmt: skip
            elif self._judge(trial, now_ns):
                return True
        if self._overran(window) and (
            severe or hurried or (len(self._level_windows) >= 2 and self._overran(self._level_windows[-2]))
        ):
            return self._shed(now_ns)  # two windows in a row: one slow window (a start-up burst) sheds nothing
        if calm:
            return self._restore(window, now_ns)
        return False

    def _start(self, now_ns: int, cpu_ns: int | None, machine: MachineCpu | None) -> None:
        """The first tick: the governor's time starts here, not at the daemon's construction (opening the cameras
        and loading the models can take longer than the settling time); what was observed before is dropped."""
        self._first_tick = self._start_ns = self._window_start = self._changed_ns = now_ns
        self._calm_since = self._no_shed_until = now_ns
        self._durations, self._missed = [], 0
        self._cpu_at = None if cpu_ns is None else (now_ns, cpu_ns)
        self._machine_at = None
        self._mark_machine(now_ns, cpu_ns, machine)

    def _mark_machine(self, now_ns: int, cpu_ns: int | None, machine: MachineCpu | None) -> None:
        """The machine's counters at a window's start (with the process's CPU at the same instant)."""
        if cpu_ns is not None and machine is not None:
            self._machine_at = (now_ns, cpu_ns, machine.busy_ns)
            self.cpus = machine.cpus

    def _ours(self, w: _Window) -> bool:
        """Whether the other programs used under ``others_share`` of the machine in ``w`` (False: not measured)."""
        cpus = self.cpus or 0
        return w.others_rate is not None and cpus > 0 and w.others_rate < self.options.others_share * cpus

    def _overran(self, w: _Window) -> bool:
        return w.p95_ns > self.options.shed_above * self.period_ns or w.missed_share > self.options.max_missed

    def _close_window(self, now_ns: int, cpu_ns: int | None, machine: MachineCpu | None) -> tuple[_Window, int] | None:
        """The window's measurements and its start, once ``window_s`` has passed and the start settled."""
        o = self.options
        if cpu_ns is not None and self._cpu_at is None:
            self._cpu_at = (now_ns, cpu_ns)
        if now_ns - self._window_start < o.window_s * 1e9:
            return None
        durations, missed, began = self._durations, self._missed, self._window_start
        self._durations, self._missed, self._window_start = [], 0, now_ns
        cpu_rate = others_rate = None
        if cpu_ns is not None and self._cpu_at is not None and now_ns > self._cpu_at[0]:
            cpu_rate = (cpu_ns - self._cpu_at[1]) / (now_ns - self._cpu_at[0])
            self._cpu_at = (now_ns, cpu_ns)
        at = self._machine_at
        if cpu_ns is not None and machine is not None and at is not None and now_ns > at[0]:
            # The machine's busy time counts in clock ticks (10 ms) and ours exactly: a small negative is rounding.
            others_rate = max(0.0, ((machine.busy_ns - at[2]) - (cpu_ns - at[1])) / (now_ns - at[0]))
        self._machine_at = None
        self._mark_machine(now_ns, cpu_ns, machine)
        if not durations:
            return None
        p95 = float(np.percentile(durations, 95))
        self.last_p95_ms = round(p95 / 1e6, 2)
        window = _Window(p95, missed, len(durations) + missed, cpu_rate, others_rate)
        self._last = window
        if now_ns - self._start_ns < o.settle_s * 1e9 and window.missed_share < o.severe_missed:
            return None  # settling; but a window that lost a quarter of its ticks is the machine, not a burst
        return window, began

    def _shed(self, now_ns: int) -> bool:
        """One more step, unless at the last or waiting after a step that was taken back."""
        if self.step_index + 1 >= len(self.ladder) or now_ns < self._no_shed_until:
            return False
        before = tuple(self._level_windows)
        w = before[-1]
        if self.ladder[self.step_index + 1].pace_s > 0.0 and w.missed_share < self.options.pace_missed:
            return False  # the paced detector is for a machine far behind (see ``pace_missed``)
        self.step_index += 1
        verdict = f"; {self._verdict}" if self._verdict else ""  # the step before it, judged in this window
        self._changed(now_ns, f"tick p95 {w.p95_ns / 1e6:.1f} ms of a {self.period_ns / 1e6:.1f} ms period, "
                      f"{w.missed} of {w.ticks} ticks missed{w.cpu_text(self.cpus)}{verdict}")  # fmt: skip
        self._trial = _Trial(self.step_index - 1, before)
        return True

    def _restore(self, w: _Window, now_ns: int) -> bool:
        """A calm window: one step back after ``hold_s`` of calm."""
        o = self.options
        assert self._calm_since is not None
        calm_for = now_ns - max(self._calm_since, self._changed_ns)
        if self.step_index > 0 and calm_for >= o.hold_s * 1e9:
            self.step_index -= 1
            self._changed(now_ns, f"tick p95 {w.p95_ns / 1e6:.1f} ms, no tick missed for {o.hold_s:g} s")
            self._calm_since = now_ns
            return True
        return False

    def _judge(self, trial: _Trial, now_ns: int) -> bool:
        """The cause test of the step on trial, on the medians of its windows before and after (see the module
        docstring): True when it was taken back."""
        o = self.options
        before, after = _pooled(trial.before), _pooled(trial.after)
        helped = (
            not self._overran(after)
            or after.p95_ns <= (1.0 - o.helped_by) * before.p95_ns
            or fewer_missed(before, after, o.significance)
        )
        if helped:
            self._futile = 0
            self._verdict = (f"step {trial.from_index + 1} helped: tick p95 {before.p95_ns / 1e6:.1f} -> "
                             f"{after.p95_ns / 1e6:.1f} ms, missed {before.missed} of {before.ticks} -> "
                             f"{after.missed} of {after.ticks}")  # fmt: skip
            return False
        took_work = (
            before.cpu_rate is None or after.cpu_rate is None or after.cpu_rate <= (1.0 - o.bite) * before.cpu_rate
        )
        what = (f"step {trial.from_index + 1} ({self.ladder[trial.from_index + 1].name}) did not help: tick p95 "
                f"{before.p95_ns / 1e6:.1f} -> {after.p95_ns / 1e6:.1f} ms (medians of {len(trial.before)} -> "
                f"{len(trial.after)} windows), missed {before.missed} of {before.ticks} -> {after.missed} of "
                f"{after.ticks}")  # fmt: skip
        if before.cpu_rate is not None and after.cpu_rate is not None:
            what += f", process CPU {before.cpu_rate:.2f} -> {after.cpu_rate:.2f} s/s"
        cpus = self.cpus or 0
        others = after.others_rate if cpus else None  # the other programs' CPU in the trial (None: not measured)
        if others is not None:
            was = "" if before.others_rate is None else f"{before.others_rate:.2f} -> "
            what += f", others' CPU {was}{others:.2f} s/s of {cpus} cores ({others / cpus * 100:.0f} % of the machine)"
        if not took_work:  # it shed nothing measurable: no evidence either way, the next step may follow
            self.last_reason = self._verdict = f"{what}: it took no CPU away"
            return False
        if others is not None and others < o.others_share * cpus:
            # Nobody else loads the machine: the lateness is ours, and this step did not relieve it; the next may.
            self.last_reason = self._verdict = (f"{what}: the others used under {o.others_share * 100:g} % of the "
                                                f"machine, so the lateness is this process's work; kept, the next "
                                                f"step may follow")  # fmt: skip
            return False
        wait = o.retry_s * min(2**self._futile, 4)
        self._futile += 1
        self.step_index = trial.from_index
        self._no_shed_until = now_ns + round(wait * 1e9)
        why = ("the others' CPU not measured" if others is None
               else f"the others used {o.others_share * 100:g} % of the machine or more")  # fmt: skip
        self._changed(now_ns, f"{what}: {why}, the lateness is not this process's work; taken back, nothing shed "
                      f"for {wait:g} s")  # fmt: skip
        return True

    def _changed(self, now_ns: int, reason: str) -> None:
        self._changed_ns = now_ns
        self._level_windows = []
        self.changes += 1
        self.last_reason = reason
        since = 0.0 if self._first_tick is None else (now_ns - self._first_tick) / 1e9
        self.history = [*self.history[-9:], (round(since, 1), self.step_index, reason)]

    def status(self) -> dict[str, object]:
        """JSON-able: the step, what it sheds, why, the last window's tick p95 and CPU per second (this process's,
        the other programs' and the machine's CPUs), the ladder's steps and the last changes (seconds since the
        first tick, step, reason)."""
        return {
            "step": self.step_index,
            "shed": self.level.name,
            "tracking_rate": round(self.level.tracking_rate, 3),
            "detector_duty": self.level.detector_duty,
            "landmarks": self.level.landmarks,
            "solve_every": self.level.solve_every,
            "detector_pace_s": self.level.pace_s,
            "tile_ratio": self.level.tile_ratio,
            "reason": self.last_reason,
            "changes": self.changes,
            "pinned": self.pinned,
            "tick_p95_ms": self.last_p95_ms,
            # the last window's CPU per second: this process's and the other programs' (None: not measured)
            "process_cpu_s_per_s": None
            if self._last is None or self._last.cpu_rate is None
            else round(self._last.cpu_rate, 3),
            "others_cpu_s_per_s": None
            if self._last is None or self._last.others_rate is None
            else round(self._last.others_rate, 3),
            "machine_cpus": self.cpus,
            "ladder": [lv.name for lv in self.ladder],
            "history": [{"t_s": t, "step": k, "reason": r} for t, k, r in self.history],
        }
