"""Latency histogram and percentiles; the delay that follows the detector (``latency_s = "auto"``)."""

from __future__ import annotations

import itertools

import pytest

from mocapd.errors import InputError
from mocapd.pipeline.latency import AutoLatency, AutoLatencyOptions, LatencyStats

MS = 1_000_000


def test_histogram_percentiles_and_prometheus_lines() -> None:
    s = LatencyStats(window=100)
    for v in range(1, 101):
        s.add(v * MS)
    summary = s.summary()
    assert summary["count"] == 100
    assert abs(summary["p50"] - 50.5) < 1e-6
    assert abs(summary["mean_ms"] - 50.5) < 1e-6
    lines = s.prometheus("x_seconds", 'stage="solve"')
    assert 'x_seconds_bucket{stage="solve",le="0.05"} 50' in lines
    assert 'x_seconds_bucket{stage="solve",le="0.1"} 100' in lines
    assert 'x_seconds_bucket{stage="solve",le="+Inf"} 100' in lines
    assert 'x_seconds_count{stage="solve"} 100' in lines
    s.add(5000 * MS)  # beyond the last bucket; the window keeps only the last 100 values
    assert s.bucket_counts[-1] == 1
    assert len(s.recent()) == 100
    assert LatencyStats().summary()["p95"] is None


# ---------------------------------------------------------------------------------------------- auto latency

S = 1_000_000_000


def _feed(auto: AutoLatency, start_ns: int, seconds: float, delay_ns: int, interval_ns: int, n_cams: int = 4) -> int:
    """Detections of ``n_cams`` cameras every ``interval_ns`` (staggered), each in ``delay_ns`` after capture,
    with ``update`` called at 60 Hz; returns the end time."""
    t = start_ns
    end = start_ns + int(seconds * S)
    nxt = [start_ns + k * interval_ns // n_cams for k in range(n_cams)]
    while t < end:
        t += S // 60
        for c in range(n_cams):
            while nxt[c] + delay_ns <= t:
                auto.observe(c, nxt[c], nxt[c] + delay_ns)
                nxt[c] += interval_ns
        auto.update(t)
    return t


def test_auto_latency_settles_on_delay_plus_interval_and_never_runs_solve_time_backwards() -> None:
    opts = AutoLatencyOptions(margin_ns=16_666_667)
    auto = AutoLatency(4, opts)
    assert auto.update(0) == opts.start_ns  # nothing measured: the start value
    t, solve = 0, []
    nxt = [k * 250 * MS // 4 for k in range(4)]
    for _ in range(60 * 30):  # 30 s: detections every 250 ms per camera, 200 ms after capture
        t += S // 60
        for c in range(4):
            while nxt[c] + 200 * MS <= t:
                auto.observe(c, nxt[c], nxt[c] + 200 * MS)
                nxt[c] += 250 * MS
        solve.append(t - auto.update(t))
    need = 450 * MS + opts.margin_ns  # delay 200 + interval 250, + one output period
    assert auto.goal_ns == pytest.approx(need, abs=MS)
    assert auto.latency_ns == auto.goal_ns
    assert all(b >= a for a, b in itertools.pairwise(solve)), "solve time ran backwards"
    st = auto.status()
    assert st["mode"] == "auto" and st["latency_ms"] == pytest.approx(466.7, abs=0.2)
    assert st["detection_delay_p95_ms"] == 200.0 and st["detection_interval_p50_ms"] == 250.0


def test_auto_latency_moves_slowly_and_only_outside_its_band() -> None:
    opts = AutoLatencyOptions(start_ns=1 * S, down_rate=0.05, up_rate=0.25)
    auto = AutoLatency(2, opts)
    t = _feed(auto, 0, 3.0, 100 * MS, 200 * MS, n_cams=2)
    assert auto.goal_ns == pytest.approx(300 * MS, abs=MS)
    # 3 s at most 0.05 s/s down from 1 s (the goal came after the first samples): still well above the goal.
    assert auto.latency_ns >= 1 * S - int(0.05 * 3.0 * S)
    t = _feed(auto, t, 20.0, 100 * MS, 200 * MS, n_cams=2)
    assert auto.latency_ns == auto.goal_ns
    changes = auto.goal_changes
    # A need 5 % higher stays inside the ±10 % band and within hysteresis_min_ns (15 < 20 ms): the goal holds.
    t = _feed(auto, t, 40.0, 115 * MS, 200 * MS, n_cams=2)
    assert auto.goal_changes == changes and auto.latency_ns == pytest.approx(300 * MS, abs=MS)
    # The detector slows down (interval 400 ms): the latency grows, at most 0.25 s/s.
    before = auto.latency_ns
    t2 = _feed(auto, t, 0.5, 115 * MS, 400 * MS, n_cams=2)
    assert auto.latency_ns - before <= int(0.25 * (t2 - t)) + MS
    _feed(auto, t2, 40.0, 115 * MS, 400 * MS, n_cams=2)
    assert auto.latency_ns == pytest.approx(515 * MS, abs=2 * MS)


def test_auto_latency_ignores_a_camera_away_and_stays_in_bounds() -> None:
    opts = AutoLatencyOptions(min_ns=50 * MS, max_ns=800 * MS, start_ns=400 * MS)
    auto = AutoLatency(1, opts)
    auto.observe(0, 0, 10 * MS)
    auto.observe(0, 5 * S, 5 * S + 10 * MS)  # away for 5 s: no detection interval
    assert auto.gaps == 1 and auto.status()["needs"] == 0
    _feed(auto, 6 * S, 10.0, 5 * MS, 10 * MS, n_cams=1)
    assert auto.latency_ns == 50 * MS  # the floor, not the 15 ms measured
    with pytest.raises(InputError):
        AutoLatencyOptions(up_rate=1.0)  # solve time would stand still or run backwards
    with pytest.raises(InputError):
        AutoLatencyOptions(min_ns=2 * S, max_ns=1 * S)


def test_auto_latency_forgets_needs_older_than_a_minute() -> None:
    """A slow start (models warming up: 1.5 s needs) raises the latency; a minute of a fast detector later it
    is forgotten and the latency comes down to what the detector needs now."""
    auto = AutoLatency(2, AutoLatencyOptions(start_ns=500 * MS))
    t = _feed(auto, 0, 10.0, 500 * MS, 1000 * MS, n_cams=2)
    assert auto.goal_ns >= 1500 * MS
    _feed(auto, t, 90.0, 50 * MS, 100 * MS, n_cams=2)
    assert auto.goal_ns == pytest.approx(150 * MS, abs=MS) and auto.latency_ns == auto.goal_ns


def test_auto_latency_follows_a_lasting_change_inside_its_band() -> None:
    # The need falls from 500 to 460 ms: inside the ±10 % band, more than hysteresis_min_ns (20 ms) below.
    opts = AutoLatencyOptions(start_ns=500 * MS, settle_ns=30 * S)
    auto = AutoLatency(2, opts)
    t = _feed(auto, 0, 65.0, 200 * MS, 300 * MS, n_cams=2)
    assert auto.goal_ns == pytest.approx(500 * MS, abs=MS)
    changes = auto.goal_changes
    # The estimate (p95 of the last minute's needs) reaches 460 ms ~57 s later; the goal holds 30 s more.
    t = _feed(auto, t, 70.0, 160 * MS, 300 * MS, n_cams=2)
    assert auto.goal_changes == changes and auto.estimate_ns == pytest.approx(460 * MS, abs=MS)
    t = _feed(auto, t, 20.0, 160 * MS, 300 * MS, n_cams=2)
    assert auto.goal_changes == changes + 1 and auto.goal_ns == pytest.approx(460 * MS, abs=MS)
    _feed(auto, t, 10.0, 160 * MS, 300 * MS, n_cams=2)
    assert auto.latency_ns == auto.goal_ns  # reached at 0.05 s/s


def test_auto_latency_drops_to_its_first_goal_at_once_while_nothing_is_solved_and_never_jumps_up() -> None:
    """At start-up (``idle``: no person solved yet) the placeholder gives way to the first estimate on the tick it
    is made, not at 0.05 s/s; once people are solved the rate limits hold again, and a goal above the latency is
    approached at ``up_rate`` even when idle (solve time never runs backwards)."""
    opts = AutoLatencyOptions(start_ns=500 * MS, min_samples=16)
    auto = AutoLatency(4, opts)
    t = 0
    nxt = [k * 17 * MS // 4 for k in range(4)]
    while auto.estimate_ns is None:  # a tracked stream: keypoints every 17 ms per camera, 30 ms after capture
        t += S // 60
        for c in range(4):
            while nxt[c] + 30 * MS <= t:
                auto.observe(c, nxt[c], nxt[c] + 30 * MS)
                nxt[c] += 17 * MS
        latency = auto.update(t, idle=True)
    assert t < 200 * MS  # the first estimate came with the first keypoints (not at the next 1 s evaluation)
    assert latency == auto.goal_ns == pytest.approx(47 * MS, abs=2 * MS)
    # Once people are solved, a goal far below is approached at 0.05 s/s only.
    slow = AutoLatency(2, opts)
    t = _feed(slow, 0, 2.0, 30 * MS, 17 * MS, n_cams=2)
    assert slow.latency_ns > 400 * MS
    # Idle with a goal above the latency: no jump backwards in solve time.
    up = AutoLatency(2, AutoLatencyOptions(start_ns=100 * MS))
    for _ in range(120):
        t += S // 60
        up.observe(0, t - 400 * MS, t)
        up.observe(1, t - 400 * MS + MS, t)
        before = up.latency_ns
        after = up.update(t, idle=True)
        assert after - before <= int(opts.up_rate * S / 60) + MS
