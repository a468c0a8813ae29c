"""tools/soak.py's verdict lines (issue 45): what the run measured against what it needs, the output rate first."""

from __future__ import annotations

import asyncio
import sys
from pathlib import Path
from typing import Any

import pytest

from tools.soak import first_good_frame, trace_beside, verdicts
from tools.soak_trace import Sample, minute_findings, minute_table, trace_second


def _summary(**over: Any) -> dict[str, Any]:
    base: dict[str, Any] = {
        "output_rate_hz": 60.0, "output_hz_client_min": 59.2, "output_hz_client_median": 59.8,
        "missed_ticks_total": 12, "daemon_cpu_s_per_s_median": 0.9, "slimevr_good_hz_min": 98.0,
        "slimevr_good_connected_end": True, "slimevr_good_in_table_end": True,
        "slimevr_good_connected_minutes": 2, "slimevr_evicted_trackers": 3, "web_breaches": 0,
    }  # fmt: skip
    return {**base, **over}


def test_the_output_rate_verdict_says_the_measured_rate_against_the_needed_one() -> None:
    """The lead's quiet-machine run saw 53.9-56.0 Hz of 60 configured and had to read it out of the JSON: the
    verdict says it (NOT HELD), with the rate needed."""
    held = verdicts(_summary(), 0.05)[0]
    assert (
        held.startswith("verdict: output rate HELD") and "needed >= 57.0 Hz" in held and "59.2 Hz at the lowest" in held
    )
    low = verdicts(_summary(output_hz_client_min=53.9, output_hz_client_median=55.1, missed_ticks_total=498), 0.05)
    assert low[0].startswith("verdict: output rate NOT HELD") and "53.9 Hz at the lowest" in low[0]
    assert "498 missed ticks" in low[0] and "60 Hz configured" in low[0]
    assert verdicts(_summary(output_hz_client_min=None, output_hz_client_median=None), 0.05)[0].startswith(
        "verdict: output rate NOT HELD"
    )


def test_the_slimevr_verdict_says_whether_the_well_behaved_tracker_was_locked_out() -> None:
    out = _summary(slimevr_good_connected_end=False, slimevr_good_in_table_end=False, slimevr_good_connected_minutes=0)
    lines = verdicts(out, 0.05)
    assert lines[1].startswith("verdict: SlimeVR tracker LOCKED OUT") and "in 0 of the report intervals" in lines[1]
    silent = verdicts(_summary(slimevr_good_connected_end=False), 0.05)[1]  # let in, then its sender fell silent
    assert silent.startswith("verdict: SlimeVR tracker TIMED OUT") and "(in the table: True)" in silent
    assert verdicts(_summary(), 0.05)[1].startswith("verdict: SlimeVR tracker CONNECTED")
    assert verdicts(_summary(web_breaches=2), 0.05)[2].startswith("verdict: web surface BREACHED")


@pytest.mark.asyncio
async def test_the_intervals_start_at_the_good_client_s_first_frame() -> None:
    """The first interval counted from `ready`, seconds before the attacker process (which hosts the well-behaved
    client) was up: 56.3 Hz in a first minute in which the daemon published 58.3. The soak now waits for the
    client's first frame, and refuses to measure when the process ended first or no frame came."""
    loop = asyncio.get_running_loop()
    proc = await asyncio.create_subprocess_exec(sys.executable, "-c", "import time; time.sleep(30)")
    try:
        latest: dict[str, int] = {"good_connects": 1}
        loop.call_later(0.3, latest.update, {"good_frames": 4})
        t0 = loop.time()
        await first_good_frame(latest, proc, 10.0)
        assert loop.time() - t0 >= 0.25 and latest["good_frames"] == 4
        with pytest.raises(RuntimeError, match=r"no frame in 0\.2 s"):
            await first_good_frame({}, proc, 0.2)
    finally:
        proc.kill()
        await proc.wait()
    ended = await asyncio.create_subprocess_exec(sys.executable, "-c", "raise SystemExit(3)")
    await ended.wait()
    with pytest.raises(RuntimeError, match=r"ended \(exit 3\) before its client got a frame"):
        await first_good_frame({}, ended, 10.0)


def _sample(t: float, **over: Any) -> Sample:
    base: dict[str, Any] = {
        "t": t, "missed": 0, "late": 0, "published": round(60 * t), "good_frames": 60 * t, "report_t": t,
        "daemon_cpu_s": 0.9 * t, "machine_busy_s": 1.2 * t, "machine_steal_s": 0.0, "attacker_cpu_s": 0.1 * t,
        "rss_mib": 350.0, "gc_collections": [int(10 * t), int(t), 0], "gc_pause_ms": [0.1 * t, 0.05 * t, 0.0],
        "attacker": {"good_frames": 60 * t, "churn_connects": 7 * t, "reset_text_403": 3 * t},
        "log_lines": {"io.ws_server": int(t)}, "evictions": 0, "offset_estimates": 0, "offset_estimate_ms": 0.0,
        "unplugs": 0, "replugs": 0, "cli_started": 0, "cli_running": None, "governor_step": 6,
        "governor_changes": 0, "loop_late_ms": 1.0,
    }  # fmt: skip
    return Sample(**{**base, **over})


def _minute_of_seconds(dip: dict[int, dict[str, Any]]) -> list[dict[str, Any]]:
    """60 trace lines of a minute; the seconds in ``dip`` get their own (cumulative) readings added."""
    out: list[dict[str, Any]] = []
    prev = _sample(0.0)
    extra: dict[str, float] = {"missed": 0, "good_frames": 0.0, "machine_busy_s": 0.0, "gc2": 0, "gc2_ms": 0.0}
    for k in range(1, 61):
        t = float(k)
        d = dip.get(k, {})
        extra["missed"] += d.get("missed", 0)
        extra["good_frames"] -= d.get("frames_lost", 0)
        extra["machine_busy_s"] += d.get("other_cpu", 0.0)
        extra["gc2"] += d.get("gc2", 0)
        extra["gc2_ms"] += d.get("gc2_ms", 0.0)
        cur = _sample(t, missed=int(extra["missed"]), good_frames=60 * t + extra["good_frames"],
                      machine_busy_s=1.2 * t + extra["machine_busy_s"],
                      gc_collections=[int(10 * t), int(t), int(extra["gc2"])],
                      gc_pause_ms=[0.1 * t, 0.05 * t, extra["gc2_ms"]], cli_running=d.get("cli"),
                      loop_late_ms=d.get("late_ms", 1.0))  # fmt: skip
        out.append(trace_second(prev, cur, 0.0, 60.0))
        prev = cur
    return out


def test_the_trace_names_a_slow_minute_s_worst_seconds_and_what_co_occurred() -> None:
    """A quiet 10-minute soak gave 56.6 Hz in its last minute (220 missed ticks, the others 38-122) and nothing in
    its counters said why. The per-second trace (tools/soak_trace.py) records each second's missed ticks, the
    client's rate, the CPU of the daemon and of the other processes, the collections and their pauses, what ran;
    for a minute below the rate the minute line and the verdict table name its worst seconds and what was unusual
    in them."""
    seconds = _minute_of_seconds({
        41: {"missed": 9, "frames_lost": 9, "gc2": 1, "gc2_ms": 180.0, "late_ms": 190.0},
        42: {"missed": 30, "frames_lost": 30, "other_cpu": 0.9},
        43: {"missed": 4, "frames_lost": 4, "cli": "import mvnx FIFO"},
    })  # fmt: skip
    assert len(seconds) == 60 and all(s["minute"] == 1 for s in seconds)
    s42 = seconds[41]
    assert s42["missed"] == 30 and s42["client_hz"] == 30.0 and s42["other_cpu"] == pytest.approx(1.1)
    assert seconds[0]["attacks"] == {"ws_churn": 7, "reset_flood": 3}  # the well-behaved client is no attack
    minute: dict[str, Any] = {"minute": 10, "output_hz_client": 56.6, "missed_ticks": 43, "late_ticks": 0}
    minute.update(minute_findings(minute, seconds, 57.0))
    worst = minute["worst_seconds"]
    assert [w["t_s"] for w in worst] == [42.0, 41.0, 43.0]
    assert any(w.startswith("other processes 1.10 cores (minute median 0.20)") for w in worst[0]["with"])
    assert "gc generation 2 x1 (180 ms)" in worst[1]["with"] and "event loop 190 ms late (median 1)" in worst[1]["with"]
    assert worst[2]["with"] == ["CLI attack import mvnx FIFO"]
    assert minute["longest_missing_run_s"] == 3 and minute["longest_missing_run_from_t_s"] == 41.0
    held = {"minute": 9, "output_hz_client": 58.7, "missed_ticks": 80, "late_ticks": 2}
    assert minute_findings(held, seconds, 57.0) == {}  # only a minute below the rate is explained
    table = minute_table([held, minute], 57.0)
    assert table[1].split() == ["9", "58.70", "80", "2", "held"]
    assert table[2].split() == ["10", "56.60", "43", "0", "BELOW", "57.0"]
    assert table[3] == (
        "        its median second: other processes 0.20 cores, daemon 0.90, attacker 0.10, steal 0.00, event loop 1 "
        "ms late; 1 generation-2 collections"
    )
    assert "longest run of seconds with missed ticks: 3 s from t = 41 s" in table[4]
    assert "other_cpu 0.20 / 0.20" in table[5] and "missed 9.00 / 0.00" in table[5]  # the run against the rest
    assert table[6].startswith("        t = 42 s: 30 missed, client 30.0 Hz; with: other processes 1.10 cores")
    all_missed = [{**x, "missed": 1} for x in seconds]  # a minute missing ticks in every second: no rest to compare
    assert "(every second of the minute missed ticks)" in minute_table([{**minute, **minute_findings(minute,
                                                                      all_missed, 57.0)}], 57.0)[4]  # fmt: skip
    unexplained = minute_table([{**minute, "worst_seconds": []}], 57.0)
    assert "no second of it in the trace missed a tick" in unexplained[2]


def test_the_trace_goes_beside_the_soak_s_output() -> None:
    assert trace_beside(Path("/tmp/x/s2")) == Path("/tmp/x/s2.trace.jsonl")
