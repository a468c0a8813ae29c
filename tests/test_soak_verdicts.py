"""tools/soak.py's verdict lines (issue 45): what the run measured against what it needs, the output rate first."""

from __future__ import annotations

from typing import Any

from tools.soak import verdicts


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
