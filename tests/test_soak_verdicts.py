"""tools/soak.py's verdict lines (issue 45): what the run measured against what it needs, the output rate first."""

from __future__ import annotations

import asyncio
import sys
from typing import Any

import pytest

from tools.soak import first_good_frame, verdicts


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
