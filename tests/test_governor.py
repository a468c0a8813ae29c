"""The governor (mocapd.pipeline.governor): sheds work one step at a time when the tick does not fit its period,
restores it only after a calm hold, never before the settling time; judges each step on the medians of several
windows before taking it back."""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import numpy as np
import pytest

from mocapd.io.machine_cpu import MachineCpu
from mocapd.pipeline.governor import LADDER, Governor, GovernorOptions, Level, ladder

PERIOD = 16_666_667
S = 1_000_000_000


class _Process:
    """Injected measurements: 60 Hz ticks of a given p95 and the daemon's process CPU at a given rate, two seconds
    (one governor window) at a time, the governor stepped after each tick as the daemon does. With ``cpus``, the
    machine's CPU counters too, read where the governor is due as the daemon reads them: this process's CPU and
    the other programs' (``others`` s/s), in the kernel's 10 ms clock ticks (None: not Linux, nothing read)."""

    def __init__(self, g: Governor, t0: int = 0, cpus: int | None = None) -> None:
        self.g, self.t, self.cpu, self.cpus, self.busy = g, t0, 0, cpus, 0
        g.observe(0)
        g.step(t0, 0, self._machine())  # the first tick: the governor's time starts here

    def _machine(self) -> MachineCpu | None:
        tick = 10_000_000  # /proc/stat counts in 1/100 s
        return None if self.cpus is None else MachineCpu(self.busy // tick * tick, self.cpus)

    def window(self, tick_ms: float, cpu_s_per_s: float = 1.0, missed_every: int = 0, missed: int = -1,
               others: float = 0.0) -> int:  # fmt: skip
        """``missed``: this many of the window's 120 ticks missed (``missed_every``: one every so many)."""
        for k in range(120):
            skip = int(k < missed) if missed >= 0 else int(bool(missed_every) and k % missed_every == 0)
            self.g.observe(round(tick_ms * 1e6), skip)
            self.t += PERIOD
            self.cpu += round(cpu_s_per_s * PERIOD)
            self.busy += round((cpu_s_per_s + others) * PERIOD)
            self.g.step(self.t, self.cpu, self._machine() if self.g.due(self.t) else None)
        return self.g.step_index


@pytest.mark.parametrize("cpus", [None, 2])
def test_a_tick_that_fits_sheds_nothing(cpus: int | None) -> None:
    """A fast machine: with the machine's CPU measured and nobody else loading it (the case in which a late window
    sheds at once) a tick that fits still sheds nothing, in the settling time or after it."""
    g = Governor(PERIOD)
    p = _Process(g, cpus=cpus)
    assert {p.window(3.0, others=0.1) for _ in range(20)} == {0} and g.level is LADDER[0] and g.changes == 0
    assert {p.window(20.0, missed=1, others=0.1) for _ in range(10)} == {0}  # 1.2 periods, 1 of 121: not late


def test_an_overrun_sheds_in_the_ladders_order_one_step_per_judgement_and_never_the_tick() -> None:
    g = Governor(PERIOD)
    p = _Process(g)
    for _ in range(3):
        p.window(3.0)  # past the settling time: 6 s
    seen = [p.window(300.0 * 0.85**g.step_index) for _ in range(3 * len(LADDER) + 3)]  # each step 15 % better
    # Two late windows shed the first step; each step is then on trial for three windows (nothing else changes),
    # helped (its windows' median p95 fell), and the next follows; the last step stays. A late p95 alone, no tick
    # missed, never paces the detector (the last step: its own test).
    assert seen == [0, *(k for k in range(1, 10) for _ in range(3)), *[9] * 8], seen
    assert g.level is LADDER[9] and g.level.pace_s == 0.0
    assert g.level.tracking_rate == pytest.approx(1 / 3) and g.level.detector_duty == 0.35 and not g.level.landmarks
    assert g.level.solve_every == 3 and [lv.solve_every for lv in LADDER] == [1] * 7 + [2, 3, 3, 3]
    assert LADDER[-1].pace_s == 1.0 and LADDER[-1].tile_ratio == 0.5
    # The landmark model first (the detector's costliest part, issue 40), then the detector's duty, then the
    # tracking's rate last (alone it saved least, and below 55 % it costs the 30 Hz keypoints, docs/daemon.md);
    # tracking itself never (detections alone came too far apart: people lost and re-enrolled), the tick never;
    # each step sheds more than the one before.
    assert [lv.name for lv in LADDER[1:]] == ["landmark model off", "detector at 75 % duty", "detector at 50 % duty",
                                              "detector at 35 % duty",
                                              "detector at 35 % duty, keypoint tracking at 60 % rate",
                                              "detector at 35 % duty, keypoint tracking at 55 % rate",
                                              "detector at 35 % duty, keypoint tracking at 55 % rate, people solved "
                                              "at half rate",
                                              # the deeper rungs (docs/daemon.md): the solves before the keypoints'
                                              # 30 Hz
                                              "detector at 35 % duty, keypoint tracking at 55 % rate, people solved "
                                              "on every third tick",
                                              "detector at 35 % duty, keypoint tracking at a third of its rate, "
                                              "people solved on every third tick",
                                              # the paced detector on half-scale tiles (docs/daemon.md)
                                              "detector paced (each camera every 1 s, packed tiles at 0.5 scale), "
                                              "keypoint tracking at a third of its rate, people solved on every "
                                              "third tick"]  # fmt: skip
    for a, b in itertools.pairwise(LADDER):
        assert b.tracking_rate <= a.tracking_rate and b.detector_duty <= a.detector_duty and a != b
    assert all(lv.tracking_rate > 0 for lv in LADDER)
    assert [h[1] for h in g.history] == list(range(1, 10)) and "of a 16.7 ms period" in str(g.status()["reason"])


def test_missed_ticks_shed_even_when_the_ticks_that_ran_were_quick() -> None:
    g = Governor(PERIOD, GovernorOptions(settle_s=0.0))
    p = _Process(g)
    assert [p.window(2.0, missed_every=20) for _ in range(2)] == [0, 1]  # 5 % missed, two windows in a row


def test_nothing_is_shed_while_settling_which_counts_from_the_first_tick() -> None:
    """The daemon builds its governor before the cameras open and the models load (which took longer than the
    settling time): the start-up ticks (people enrolling, first solves: 95 of 142 ticks missed in the camera
    demo's first window) are not the machine's speed. On the old code the settling time ran from construction and
    the first window shed a step."""
    g = Governor(PERIOD, GovernorOptions(settle_s=5.0), start_ns=0)
    p = _Process(g, t0=60 * S)  # the first tick a minute after the governor was made
    assert [p.window(60.0, missed_every=5), p.window(60.0)] == [0, 0]  # a fifth of the ticks missed: a burst
    assert [p.window(60.0), p.window(60.0)] == [0, 1]  # 6 and 8 s after the first tick


def test_a_window_that_lost_a_quarter_of_its_ticks_sheds_while_settling() -> None:
    """Settling waits out start-up bursts, not a machine too slow for the work: on the quiet 2-core `mocapd demo`
    the settling time's windows lost 25-60 % of their ticks and the walk down the ladder started only after it. On
    the old code nothing was shed before 5 s whatever was lost."""
    g = Governor(PERIOD, GovernorOptions(settle_s=5.0), start_ns=0)
    p = _Process(g)
    assert p.window(60.0, missed_every=2) == 1  # 2 s after the first tick, half the ticks lost: shed at once
    assert "60 of 180 ticks missed" in str(g.status()["reason"])  # 120 ran, 60 skipped


def test_one_slow_window_sheds_nothing() -> None:
    """A burst (a window's p95 at 4 periods, 30 of its ticks missed) between windows that fit is no reason to shed:
    two late windows in a row are. On the old code the one window shed a step."""
    g = Governor(PERIOD, GovernorOptions(settle_s=0.0))
    p = _Process(g)
    steps = [p.window(t, missed=m) for t, m in [(8.0, 0), (70.0, 30), (8.0, 0), (8.0, 0), (70.0, 0), (70.0, 0)]]
    assert steps == [0, 0, 0, 0, 0, 1], steps


def test_work_comes_back_only_after_a_calm_hold() -> None:
    o = GovernorOptions(settle_s=0.0, hold_s=6.0)
    g = Governor(PERIOD, o)
    p = _Process(g)
    assert [p.window(60.0), p.window(60.0), p.window(50.0), p.window(50.0), p.window(50.0)] == [0, 1, 1, 1, 2]
    steps = [p.window(3.0) for _ in range(8)]  # calm: p95 18 % of the period (below 60 %)
    # 6 s of calm (three windows) before each step back, not one step per window.
    assert steps == [2, 2, 1, 1, 1, 0, 0, 0], steps
    # In between (neither calm nor overrun): held where it is.
    g2 = Governor(PERIOD, o)
    p2 = _Process(g2)
    p2.window(50.0)
    p2.window(50.0)
    assert {p2.window(20.0) for _ in range(6)} == {1}  # 1.2 periods: below shedding, above restoring


def test_lateness_that_is_not_ours_sheds_one_step_takes_it_back_and_waits() -> None:
    """Issue 39's cause test: on a machine loaded by other programs the tick's p95 stays at 50 ms whatever is
    shed. The first step takes CPU away (1.6 -> 1.2 s/s) and the p95 does not move over its three windows: it is
    taken back, nothing is shed for 30 s, then one retry, taken back again, and 60 s of waiting. Before the cause
    test: the whole ladder in 10 s."""
    g = Governor(PERIOD, GovernorOptions(settle_s=0.0))
    p = _Process(g)
    steps = [p.window(50.0, 1.6 if g.step_index == 0 else 1.2) for _ in range(60)]  # two minutes
    assert max(steps) == 1, steps
    reason = str(g.status()["reason"])
    assert "step 1 (landmark model off) did not help: tick p95 50.0 -> 50.0 ms (medians of 3 -> 3 windows)" in reason
    assert "process CPU 1.60 -> 1.20 s/s" in reason and "not this process's work" in reason, reason
    # shed at 4 s, taken back at 10 s; again at 40 s (30 s on), back at 46; again at 106 s (60 s on), back at 112
    assert [(t, k) for t, k, _ in g.history] == [(4.0, 1), (10.0, 0), (40.0, 1), (46.0, 0), (106.0, 1), (112.0, 0)]
    assert "nothing shed for 120 s" in reason and g.changes == 6
    assert "the others' CPU not measured" in reason  # no machine counters (not Linux): the rule before them


def test_a_machine_other_programs_load_still_takes_the_step_back_and_waits() -> None:
    """The same lateness with the machine's CPU measured: the other programs used 1.1 of the 2 cores (55 %, a VR
    game's share) while the step took CPU from this process and the p95 stayed: not ours, taken back, waits."""
    g = Governor(PERIOD, GovernorOptions(settle_s=0.0))
    p = _Process(g, cpus=2)
    steps = [p.window(50.0, 1.6 if g.step_index == 0 else 1.2, others=1.1 if g.step_index == 0 else 1.5)
             for _ in range(60)]  # fmt: skip
    assert max(steps) == 1, steps
    assert [(t, k) for t, k, _ in g.history] == [(4.0, 1), (10.0, 0), (40.0, 1), (46.0, 0), (106.0, 1), (112.0, 0)]
    reason = str(g.status()["reason"])
    assert "process CPU 1.60 -> 1.20 s/s, others' CPU 1.10 -> 1.50 s/s of 2 cores (75 % of the machine)" in reason
    assert "the others used 25 % of the machine or more, the lateness is not this process's work" in reason, reason
    st = g.status()
    assert st["machine_cpus"] == 2 and st["others_cpu_s_per_s"] == pytest.approx(1.1, abs=0.01), st
    assert st["process_cpu_s_per_s"] == pytest.approx(1.6, abs=0.001)


def test_on_a_machine_only_we_load_a_step_that_did_not_help_is_kept_and_the_next_follows() -> None:
    """The quiet 2-core `mocapd demo` (the daemon ~1.6 cores, its fake cameras ~0.24 together, nothing else): step
    2 (detector at 50 % duty) took CPU away (1.61 -> 1.51 s/s) and the p95 stayed (70.8 -> 71.0 ms), the missed
    ticks fell but not significantly (60 of 360 -> 51 of 366). The old rule called that "not this process's work",
    took the step back and shed nothing for 30 s (the run lost 300-700 ticks); nobody else loaded the machine, so
    the lateness is ours: the step stays and the next follows, down the ladder. (Each trial runs its three windows
    here: ``hurry_missed`` at a whole window, so that no late window ends a trial; the next test has it.)"""
    steps = ladder(False, True, True)  # the demo's: no landmark step
    g = Governor(PERIOD, GovernorOptions(settle_s=0.0, hurry_missed=1.0), steps=steps)
    p = _Process(g, cpus=2)
    p95 = {0: 70.8, 1: 70.8, 2: 71.0}
    seen = [p.window(p95.get(g.step_index, 71.0), 1.71 - 0.1 * g.step_index, missed=20 if g.step_index < 2 else 17,
                     others=0.24) for _ in range(2 + 3 * (len(steps) - 1))]  # fmt: skip
    assert seen == [0, *(k for k in range(1, len(steps)) for _ in range(3)), len(steps) - 1], seen
    kept = g.history[2][2]  # step 3, shed with the verdict on step 2
    assert "step 2 (detector at 50 % duty) did not help: tick p95 70.8 -> 71.0 ms (medians of 3 -> 3 windows), " \
           "missed 60 of 420 -> 51 of 411, process CPU 1.61 -> 1.51 s/s, others' CPU 0.24 -> 0.24 s/s of 2 cores " \
           "(12 % of the machine): the others used under 25 % of the machine, so the lateness is this process's " \
           "work; kept, the next step may follow" in kept, kept  # fmt: skip
    assert "others' CPU 0.24 s/s of 2 cores" in kept  # the window that shed step 3, as /status and the console say
    assert not any("taken back" in r for _, _, r in g.history) and g.history[-1][1] == len(steps) - 1


@pytest.mark.parametrize("others", [0.2, 0.24, 0.8, 1.1, None])
def test_late_windows_on_a_machine_only_we_load_walk_one_step_a_window(others: float | None) -> None:
    """`mocapd demo` on the quiet 2-core machine (eighth session): after the first steps each trial's windows
    missed 5-9 of ~120 ticks (4-7.5 %) with the process at 1.24-1.66 s/s and the fake cameras at 0.20-0.22 s/s of
    2 cores, and every step waited for its three-window verdict, which could only keep it (helped, or took CPU and
    the lateness is ours, or took no CPU): most of a run's missed ticks fell in those ~24 s. With the others under a
    quarter of the machine (0.2 or 0.24 of 2 cores) a window still late ends the trial at once: one step a window,
    each kept unjudged, to the last step before the paced detector (which waits for a window that missed 6 %: its
    own test). With the others at 0.8 or 1.1 of 2 cores (40 %, 55 %), or not
    measured, each step waits for its three-window trial, and a step that took CPU without helping is taken back.
    On the old code (a tenth of the window missed to end a trial) the 5 % trace waited for every trial."""
    steps = ladder(False, True, True)
    g = Governor(PERIOD, GovernorOptions(settle_s=0.0), steps=steps)
    p = _Process(g, cpus=None if others is None else 2)
    seen = [p.window(60.0, 1.71 - 0.1 * g.step_index, missed=6, others=others or 0.0) for _ in range(12)]
    if others is not None and others < 0.5:
        last = len(steps) - 2
        assert seen == [*range(last + 1), *[last] * (11 - last)], seen
        assert "step 1 kept unjudged: the window after it was still late while the others used under 25 % of the " \
               "machine (the lateness is ours)" in g.history[1][2], g.history  # fmt: skip
        assert "6 of 126 ticks missed, process CPU 1.61 s/s, others' CPU" in g.history[1][2]  # the window said
    else:
        assert seen[:5] == [0, 1, 1, 1, 0], seen  # judged over its trial: took CPU, did not help, taken back
        assert "taken back" in g.history[1][2] and max(seen) == 1


def test_a_step_kept_at_once_is_still_given_back_after_a_calm_hold() -> None:
    """Restoring is unchanged by the fast walk: a machine shed too far (the ladder walked in a late start-up on a
    machine only we load) gets a step back after each ``hold_s`` of calm."""
    g = Governor(PERIOD, GovernorOptions(settle_s=0.0, hold_s=6.0))
    p = _Process(g, cpus=2)
    assert [p.window(60.0, missed=6, others=0.2) for _ in range(4)] == [0, 1, 2, 3]
    assert [p.window(3.0, others=0.2) for _ in range(7)] == [3, 3, 2, 2, 2, 1, 1]


@pytest.mark.parametrize(("others", "back"), [(0.45, False), (0.55, True)])
def test_the_others_share_decides_at_a_quarter_of_the_machine(others: float, back: bool) -> None:
    """``others_share``: 0.45 of 2 cores (22 %) is not a load that makes the lateness someone else's (each late
    window after a step sheds the next at once); 0.55 (28 %) is (the step is judged over its trial, taken back)."""
    g = Governor(PERIOD, GovernorOptions(settle_s=0.0))
    p = _Process(g, cpus=2)
    seen = [p.window(50.0, 1.6 if g.step_index == 0 else 1.2, others=others) for _ in range(5)]
    assert seen == ([0, 1, 1, 1, 0] if back else [0, 1, 2, 3, 4]), seen


def test_a_step_that_helps_lets_the_next_follow_and_resets_the_wait() -> None:
    """Our own lateness: each step takes CPU away and the p95 falls with it (here by 17 %, or the missed ticks
    significantly while the p95 wobbles up), so the ladder is walked; a step that did not help is taken back to the
    last one that did, and a step that helps again ends the doubling of the wait."""
    g = Governor(PERIOD, GovernorOptions(settle_s=0.0))
    p = _Process(g)
    assert [p.window(120.0, 1.9), p.window(120.0, 1.9)] == [0, 1]
    assert [p.window(100.0, 1.7) for _ in range(3)] == [1, 1, 2]  # p95 -17 %: helped, still late: the next
    assert [p.window(105.0, 1.5, missed_every=20) for _ in range(3)] == [2, 2, 1]  # up, 5 % missed, CPU less: back
    assert {p.window(105.0, 1.7, missed_every=20) for _ in range(14)} == {1}  # for 30 s nothing is shed
    assert p.window(105.0, 1.7, missed_every=20) == 2  # the retry
    assert [p.window(80.0, 1.5) for _ in range(3)] == [2, 2, 3] and g._futile == 0  # it helped: the wait is reset
    g2 = Governor(PERIOD, GovernorOptions(settle_s=0.0))
    p2 = _Process(g2)
    assert [p2.window(60.0, 1.9, missed_every=10) for _ in range(2)] == [0, 1]  # 10 % missed
    # the p95 wobbled up, the missed ticks fell from 24 of 240 to 9 of 360 (one-sided p < 0.001): it helped
    assert [p2.window(65.0, 1.7, missed_every=40) for _ in range(3)] == [1, 1, 2]


def test_a_step_that_took_no_cpu_away_proves_nothing_and_the_next_follows() -> None:
    """A step that sheds nothing here (the landmark model of "auto" that was not running): the process's CPU did
    not fall, so the unchanged p95 says nothing about whose the lateness is; the next step follows, and that one,
    which takes CPU away to no effect, is taken back to it."""
    g = Governor(PERIOD, GovernorOptions(settle_s=0.0))
    p = _Process(g)
    assert [p.window(50.0, 1.6) for _ in range(5)] == [0, 1, 1, 1, 2]
    assert "step 1 (landmark model off) did not help" in str(g.status()["reason"])
    assert "it took no CPU away" in str(g.status()["reason"])
    assert [p.window(50.0, 1.2) for _ in range(3)] == [2, 2, 1] and "step 2" in str(g.status()["reason"])


def _noisy_run(g: Governor, before: Sequence[tuple[float, int]], after: Sequence[tuple[float, int]],
               windows: int, others: float | None = None) -> list[int]:  # fmt: skip
    """``windows`` windows of ticks whose p95 and missed ticks come from ``before`` while nothing is shed and from
    ``after`` once a step is (both in turn); the process's CPU falls by a fifth with the step. ``others``: the
    other programs' CPU on a 2-core machine (None: the machine's CPU not measured)."""
    p = _Process(g, cpus=None if others is None else 2)
    seen, k = [], {0: 0, 1: 0}
    for _ in range(windows):
        shed = min(g.step_index, 1)
        tick_ms, missed = (before, after)[shed][k[shed] % len((before, after)[shed])]
        k[shed] += 1
        seen.append(p.window(tick_ms, 1.6 - 0.3 * shed, missed=missed, others=others or 0.0))
    return seen


def test_a_step_that_helps_on_average_is_kept_through_a_noisy_window() -> None:
    """The quiet camera demo of the third session: the first window after a step (p95 60.9 -> 79.9 ms, missed 9
    -> 26 of ~120, process CPU 1.66 -> 1.53 s/s) took a step back that helped on average: the windows after it
    were ~20 % better. Judged on the medians of three windows, the step is kept; on the old code, which judged the
    one window after the step, it was taken back at once."""
    g = Governor(PERIOD, GovernorOptions(settle_s=0.0))
    before = [(60.9, 9), (58.0, 7), (63.0, 11)]
    after = [(79.9, 26), (44.0, 2), (49.0, 4), (47.0, 3), (55.0, 6), (46.0, 3)]  # mean 53.6 ms, median 48 ms
    seen = _noisy_run(g, before, after, 30)
    first = seen.index(1)
    assert min(seen[first:]) >= 1, (seen, g.last_reason)  # never taken back to nothing shed
    assert not any("not this process's work" in r and k == 0 for _, k, r in g.history), g.history


def _bursty(rng: np.random.Generator, p95_ms: float, missed: float) -> list[tuple[float, int]]:
    """Six windows' (p95 ms, missed ticks): the p95 varying by 10 % (one standard deviation), one window in five a
    burst 35 % slower, the missed ticks Poisson."""
    return [(p95_ms * (1 + 0.1 * rng.standard_normal() + (0.35 if rng.random() < 0.2 else 0.0)),
             int(rng.poisson(missed))) for _ in range(6)]  # fmt: skip


@pytest.mark.parametrize(
    ("effect", "others", "kept"),
    [(0.2, None, (0.9, 1.0)), (0.0, None, (0.0, 0.6)), (0.0, 1.1, (0.0, 0.6)), (0.2, 0.24, (1.0, 1.0)),
     (0.0, 0.24, (1.0, 1.0))],
)  # fmt: skip
def test_the_judgement_over_many_noisy_runs(effect: float, others: float | None, kept: tuple[float, float]) -> None:
    """Windows as the quiet 2-core camera demo's: the p95 varies by 10 % (one standard deviation) and one window in
    five is a burst 35 % slower (the 79.9 ms among ~60 ms windows), missed ticks Poisson. A step that brings the
    p95 and the missed ticks down by 20 % is kept in at least 90 % of 200 seeded runs (the old code's one-window
    test kept it in 75 %: a burst in the one window after the step took it back); a step that brings nothing (the
    lateness is other programs') is taken back in at least 40 % (the rest go on to the next step, judged in turn;
    the old code: 65 %). The same with the machine's CPU measured and other programs using 1.1 of its 2 cores;
    with them at 0.24 (the demo's fake cameras alone), the lateness is ours and the step is kept in every run,
    whether or not it helped. Seeded: the same numbers every run."""
    n_kept = 0
    for seed in range(200):
        rng = np.random.default_rng(seed)
        before, after = _bursty(rng, 60.0, 8.0), _bursty(rng, 60.0 * (1 - effect), 8.0 * (1 - effect))
        g = Governor(PERIOD, GovernorOptions(settle_s=0.0))
        seen = _noisy_run(g, before, after, 8, others)  # shed at the 2nd window, judged at the 5th
        n_kept += min(seen[seen.index(1) :]) >= 1
    assert kept[0] * 200 <= n_kept <= kept[1] * 200, n_kept


def test_a_pinned_governor_holds_its_step_and_still_measures() -> None:
    """``[daemon] governor_pin_step``: the level stays (a developer measures what the step saves) while the windows
    are still measured; a step the rig's ladder does not have is refused."""
    steps = ladder(False, True, True)
    g = Governor(PERIOD, GovernorOptions(settle_s=0.0), steps=steps, pin=2)
    p = _Process(g)
    assert {p.window(80.0, missed_every=5) for _ in range(5)} | {p.window(2.0) for _ in range(8)} == {2}
    st = g.status()
    assert st["pinned"] is True and st["shed"] == "detector at 50 % duty" and st["tick_p95_ms"] == 2.0
    assert g.changes == 0 and "governor_pin_step" in str(st["reason"])
    with pytest.raises(ValueError, match="step 10 is not on this rig's ladder"):
        Governor(PERIOD, steps=steps, pin=10)


def test_the_ladder_has_only_steps_that_shed_something_the_daemon_runs() -> None:
    names = [
        [lv.name for lv in ladder(*run)] for run in ((True, True, True), (False, True, True), (False, False, True))
    ]
    assert names[0] == [lv.name for lv in LADDER]
    assert names[1] == [lv.name for lv in LADDER if lv.name != "landmark model off"]
    assert names[2] == ["nothing shed", "detector at 75 % duty", "detector at 50 % duty", "detector at 35 % duty",
                        "detector at 35 % duty, people solved at half rate",
                        "detector at 35 % duty, people solved on every third tick"]  # fmt: skip
    assert [lv.tracking_rate for lv in ladder(False, False, True)] == [1.0] * 6
    # the synthetic rig: nothing else to shed, the solve at half rate and a third alone (it solves like every rig)
    assert ladder(False, False, False) == (LADDER[0], Level("people solved at half rate", 1.0, 1.0, True, 2),
                                           Level("people solved on every third tick", 1.0, 1.0, True, 3))  # fmt: skip
    assert [lv.name for lv in ladder(False, True, False)] == ["nothing shed", "keypoint tracking at 60 % rate",
                                                              "keypoint tracking at 55 % rate",
                                                              "keypoint tracking at 55 % rate, people solved at half "
                                                              "rate",
                                                              "keypoint tracking at 55 % rate, people solved on "
                                                              "every third tick",
                                                              "keypoint tracking at a third of its rate, people "
                                                              "solved on every third tick"]  # fmt: skip
    assert [lv.solve_every for lv in ladder(False, True, False)] == [1, 1, 1, 2, 3, 3]
    # The keypoints stay at 30 Hz or more a camera and person until the tracking at a third (33 Hz nominal at 55 %:
    # at half rate 27.6-29.8 Hz were measured); only it and the paced detector's step after it go below.
    assert all(lv.tracking_rate * 60.0 >= 33.0 for lv in LADDER[:-2])
    assert {lv.tracking_rate * 60.0 for lv in LADDER[-2:]} == {20.0}
    # Every rig's ladder: each step sheds at least what the one before did, and the people on every third tick last.
    for run in itertools.product((True, False), repeat=3):
        steps = ladder(*run)
        assert steps[-1].solve_every == 3 and len({lv.name for lv in steps}) == len(steps)
        for a, b in itertools.pairwise(steps):
            assert b.tracking_rate <= a.tracking_rate and b.detector_duty <= a.detector_duty
            assert b.solve_every >= a.solve_every and b.tracking_rate > 0


#: the camera demo's ladder before the paced detector (main at 40317a9): its steps and their order stay
DEMO_LADDER_BEFORE = [
    "nothing shed", "detector at 75 % duty", "detector at 50 % duty", "detector at 35 % duty",
    "detector at 35 % duty, keypoint tracking at 60 % rate", "detector at 35 % duty, keypoint tracking at 55 % rate",
    "detector at 35 % duty, keypoint tracking at 55 % rate, people solved at half rate",
    "detector at 35 % duty, keypoint tracking at 55 % rate, people solved on every third tick",
    "detector at 35 % duty, keypoint tracking at a third of its rate, people solved on every third tick",
]  # fmt: skip


def test_the_deepest_step_paces_the_detector_on_half_scale_tiles_after_the_steps_of_before() -> None:
    """Issue 39 at a CPU budget of 0.4 of a core on the 2-core EPYC (0.8 of a core on the issue's slower CPU): at
    the last step before, the detector still took 0.09-0.13 s/s (its duty's rest, a multiple of a throttled pass's
    wall time, took no CPU away) and 9-15 % of the ticks were missed. One step follows it where a packed detector and
    keypoint tracking run: the detector paced, each camera detected every 1 s (the tracking's 2 s age limit bounds
    it), on packed tiles at half scale. Every step before is as it was; a rig without the packed detector or the
    tracking has no such step."""
    demo = ladder(False, True, True)
    assert [lv.name for lv in demo[:9]] == DEMO_LADDER_BEFORE
    assert all(lv.pace_s == 0.0 and lv.tile_ratio == 1.0 for lv in demo[:9])
    assert [(lv.pace_s, lv.tile_ratio, lv.solve_every) for lv in demo[9:]] == [(1.0, 0.5, 3)]
    assert all(lv.tracking_rate == pytest.approx(1 / 3) for lv in demo[8:])
    assert [lv.name for lv in ladder(True, True, True)] == [
        *DEMO_LADDER_BEFORE[:1],
        "landmark model off",
        *DEMO_LADDER_BEFORE[1:],
        *(lv.name for lv in demo[9:]),
    ]
    for run in ((False, True, False), (False, False, True), (False, False, False), (True, False, True)):
        assert all(lv.pace_s == 0.0 and lv.tile_ratio == 1.0 for lv in ladder(*run)), run
    # Far behind at step 8 (at 0.4 of a core its windows missed 7-18 %) with nobody else loading the machine: on to
    # the paced step, said in /status.
    g = Governor(PERIOD, GovernorOptions(settle_s=0.0), steps=demo)
    p = _Process(g, cpus=2)
    seen = [p.window(60.0, 0.4, missed=12, others=0.2) for _ in range(12)]
    assert seen == [*range(10), 9, 9], seen
    st = g.status()
    assert st["detector_pace_s"] == 1.0 and st["tile_ratio"] == 0.5 and str(st["shed"]).startswith("detector paced")


def test_a_machine_whose_ticks_fit_at_step_8_never_paces_the_detector() -> None:
    """The steps above are as they were on a machine that does not need the new one: ticks that fit again at step
    8 keep it there, and windows that miss under ``pace_missed`` (6 %) of their ticks there, as the quiet 2-core
    demo's did at its last step (2-6 of ~120, eighth session), do not pace the detector either: it costs coarser
    detections, for a machine far behind."""
    for late in (0, 2, 6):
        g = Governor(PERIOD, GovernorOptions(settle_s=0.0), steps=ladder(False, True, True))
        p = _Process(g, cpus=2)
        seen = [p.window(60.0 if g.step_index < 8 else 30.0, 1.4, missed=12 if g.step_index < 8 else late,
                         others=0.2) for _ in range(20)]  # fmt: skip
        assert max(seen) == 8 and seen[-1] == 8, (late, seen)
        assert g.level.pace_s == 0.0 and g.level.tile_ratio == 1.0
    seen.append(p.window(30.0, 1.4, missed=8, others=0.2))  # 8 of 128: far enough behind
    assert seen[-1] == 9 and g.level.pace_s == 1.0


def test_a_window_that_loses_most_of_its_ticks_sheds_at_once_without_waiting_for_a_trial() -> None:
    """`mocapd demo` on the 2-core machine lost a third of its ticks for 31 s while each of seven steps waited for two
    late windows and a three-window trial: a window missing at least ``severe_missed`` of its ticks sheds the next
    step at once (one step a window, each kept unjudged); below that share a late window waits as before."""
    g = Governor(PERIOD, GovernorOptions(settle_s=0.0))
    p = _Process(g)
    seen = [p.window(60.0, missed=60) for _ in range(len(LADDER) + 1)]  # a third of every window's ticks missed
    assert seen == [*range(1, len(LADDER)), 10, 10], seen
    assert "kept unjudged: 60 of 180 ticks missed" in g.history[-1][2]
    # 10 % missed: late, not severe: two windows before the first step, then a trial of three windows.
    g = Governor(PERIOD, GovernorOptions(settle_s=0.0))
    p = _Process(g)
    assert [p.window(60.0, missed=12) for _ in range(5)] == [0, 1, 1, 1, 2]
