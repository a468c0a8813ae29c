"""The governor (mocapd.pipeline.governor): sheds work one step at a time when the tick does not fit its period,
restores it only after a calm hold, never before the settling time."""

from __future__ import annotations

import itertools

from mocapd.pipeline.governor import LADDER, Governor, GovernorOptions

PERIOD = 16_666_667
S = 1_000_000_000


def _window(g: Governor, t0: int, tick_ms: float, missed_every: int = 0) -> int:
    """Two seconds of 60 Hz ticks taking ``tick_ms`` each (one missed every ``missed_every``); the next t."""
    t = t0
    for k in range(120):
        g.observe(round(tick_ms * 1e6), 1 if missed_every and k % missed_every == 0 else 0)
        t += PERIOD
    g.step(t)
    return t


def test_a_tick_that_fits_sheds_nothing() -> None:
    g = Governor(PERIOD)
    t = 0
    for _ in range(20):
        t = _window(g, t, 3.0)
    assert g.step_index == 0 and g.level is LADDER[0] and g.changes == 0


def test_an_overrun_sheds_one_step_per_window_in_the_ladders_order_and_never_the_tick() -> None:
    g = Governor(PERIOD)
    t = _window(g, 0, 3.0)
    t = _window(g, t, 3.0)
    t = _window(g, t, 3.0)  # past the settling time: 6 s
    seen = []
    for _ in range(len(LADDER) + 2):
        t = _window(g, t, 50.0)  # p95 three periods
        seen.append(g.step_index)
    assert seen == [min(k + 1, len(LADDER) - 1) for k in range(len(seen))]
    assert g.level.tracking_rate == 0.5 and g.level.detector_duty == 0.35 and not g.level.landmarks
    # The landmark model first (the detector's costliest part, issue 40), then the tracking's rate, then the
    # detector; tracking itself never (detections alone came too far apart: people lost and re-enrolled), the tick
    # never; each step sheds more than the one before.
    assert [lv.name for lv in LADDER[1:4]] == ["landmark model off", "keypoint tracking at half rate",
                                              "keypoint tracking at half rate, detector at 75 % duty"]  # fmt: skip
    for a, b in itertools.pairwise(LADDER):
        assert b.tracking_rate <= a.tracking_rate and b.detector_duty <= a.detector_duty and a != b
    assert all(lv.tracking_rate > 0 for lv in LADDER)
    assert "of a 16.7 ms period" in str(g.status()["reason"])


def test_missed_ticks_shed_even_when_the_ticks_that_ran_were_quick() -> None:
    g = Governor(PERIOD, GovernorOptions(settle_s=0.0))
    _window(g, 0, 2.0, missed_every=20)  # 5 % missed
    assert g.step_index == 1


def test_nothing_is_shed_while_settling() -> None:
    g = Governor(PERIOD, GovernorOptions(settle_s=5.0))
    t = _window(g, 0, 60.0)
    t = _window(g, t, 60.0)
    assert g.step_index == 0
    _window(g, t, 60.0)
    assert g.step_index == 1


def test_work_comes_back_only_after_a_calm_hold() -> None:
    o = GovernorOptions(settle_s=0.0, hold_s=6.0)
    g = Governor(PERIOD, o)
    t = _window(g, 0, 50.0)
    t = _window(g, t, 50.0)
    assert g.step_index == 2
    steps = []
    for _ in range(8):  # calm: p95 18 % of the period (below 60 %)
        t = _window(g, t, 3.0)
        steps.append(g.step_index)
    # 6 s of calm (three windows) before each step back, not one step per window.
    assert steps == [2, 2, 1, 1, 1, 0, 0, 0]
    # In between (neither calm nor overrun): held where it is.
    g2 = Governor(PERIOD, o)
    t = _window(g2, 0, 50.0)
    for _ in range(6):
        t = _window(g2, t, 20.0)  # 1.2 periods: below shedding, above restoring
    assert g2.step_index == 1
