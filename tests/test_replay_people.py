"""``tools/replay_people.py`` on a session whose detections carry both hands' keypoints after the body's (a rig with
``[detector] hands`` on: the manifest's ``keypoint_columns``): the replay samples and sorts every recorded column
as the live daemon did, and finds the person it solved. It used to build its timelines with the targets' columns
only, and the first tick with one camera's keypoints and another's empty (stale) sample stopped it with a
ValueError (17 columns against 59, in the sorter)."""

from __future__ import annotations

import asyncio
from pathlib import Path

from mocapd.io.session import open_session
from mocapd.service.outputs.recorder import attach_recorder
from tools.replay_people import replay

from .test_hands_live import HAND_COLUMNS, _daemon
from .test_scheduler_hands import LATENCY, RATE, S, _frames


async def _record(path: Path) -> int:
    """One person with fingers, seen by six cameras for a second (camera 0 silent for a while), through a daemon
    whose rig's detections carry the hands' columns, recorded as the daemon records: its recorder on the
    detection taps and publishing the frames the scheduler made. Returns the frames with a person solved."""
    daemon = _daemon(HAND_COLUMNS)
    # The replay sorts people, it solves no pose: the finger solve's cost buys nothing here (its columns are
    # sampled, sorted and recorded all the same).
    daemon.scheduler.hands = None
    rec = attach_recorder(daemon.config, daemon, path)
    assert rec is not None
    await rec.start()
    solved = 0
    for i, row in enumerate(_frames(1.0)[0]):
        t = S + i * S // RATE
        for c, det in enumerate(row):
            if c == 0 and 20 <= i < 45:
                continue
            daemon.scheduler.add_detections(c, t, det, t + LATENCY // 2)
            for tap in daemon.detection_taps:
                tap(c, t, det, t + LATENCY // 2)
        frame = daemon.scheduler.tick(t + LATENCY)
        solved += bool(frame.people)
        rec.publish(frame)
    await rec.aclose()
    return solved


def test_a_session_with_hand_columns_replays_to_its_live_people(tmp_path: Path) -> None:
    solved = asyncio.run(_record(tmp_path / "s"))
    session = open_session(tmp_path / "s")
    assert len(session.manifest["keypoint_columns"]) == 59 and len(session.manifest["targets"]["names"]) == 17
    assert {k.keypoints.shape[1] for k in session.keypoints()} == {59}  # the hands' columns were recorded
    assert solved > 30
    r = replay(str(tmp_path / "s"), [])
    assert r["ticks"] == 60 and r["identities_recorded"] == ["track:1"]
    assert abs(r["person_solves_per_tick"] - r["recorded_person_solves_per_tick"]) <= 0.05, r
    assert [e[1] for e in r["tracking_events"]] == ["enrolled"]
    # camera 0's silence: stale samples (no keypoints) beside the other cameras' 59 columns, in the same ticks
    assert r["sample_statuses"]["stale"] > 0 and r["sample_statuses"]["exact"] > 300, r
