"""Session files for real: the writer thread, a recorder process killed with SIGKILL mid-write, hand-truncated and
corrupted files, a full queue, and the recorder sink's counters."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from mocapd.errors import InputError
from mocapd.io.session import SessionWriter, open_session, read_stream
from mocapd.pipeline.scheduler import PersonPose, PoseFrame
from mocapd.protocols import session_format as sf
from mocapd.service.outputs.recorder import SessionRecorder

MANIFEST = {"format": "mocapd-session", "version": 1}


def frame(i: int, t_ns: int, people: int = 4) -> PoseFrame:
    rng = np.random.default_rng(i)
    return PoseFrame(
        i, t_ns, t_ns + 150_000_000,
        [PersonPose(f"track:{k}", k, None, rng.normal(size=66), rng.normal(size=(21, 3)), 0.9, 4, 0, 5, True)
         for k in range(people)],
        0,
    )  # fmt: skip


# The child: a real recorder (SessionRecorder + SessionWriter) publishing 4-person frames at 200 Hz, each
# stamped with the host clock when it was published, until it is killed.
CHILD = """
import sys, time
sys.path.insert(0, {tests!r})
from test_session import frame, MANIFEST
from mocapd.io.session import SessionWriter
from mocapd.service.outputs.recorder import SessionRecorder
rec = SessionRecorder(SessionWriter({path!r}, MANIFEST, flush_interval_s=0.25))
rec.writer.open()
print("ready", flush=True)
i = 0
while True:
    i += 1
    rec.publish(frame(i, time.monotonic_ns()))
    time.sleep(0.005)
"""


def test_sigkill_mid_write_loses_at_most_the_last_flush_interval(tmp_path: Path) -> None:
    path = tmp_path / "s"
    code = CHILD.format(tests=str(Path(__file__).parent), path=str(path))
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "ready"
        time.sleep(1.5)
        # Freeze the recorder at a moment its file ends inside a record (the buffered writer spilled part of
        # one), then kill it there: a write torn by the crash.
        for _ in range(500):
            proc.send_signal(signal.SIGSTOP)
            stopped_ns = time.monotonic_ns()
            if read_stream(path / "poses.mcs")[1].torn_tail_bytes > 0:
                break
            proc.send_signal(signal.SIGCONT)
            time.sleep(0.002)
        else:
            raise AssertionError("the recorder's file never ended mid-record")
        proc.send_signal(signal.SIGKILL)
        assert proc.wait(timeout=10) == -signal.SIGKILL
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    session = open_session(path)
    frames = session.poses()
    report = session.reports["poses"]
    assert not session.closed_cleanly
    assert report.torn_tail_bytes > 0 and report.corrupt == 0, report
    assert any("torn tail" in line for line in session.recovery_lines())
    assert any("not closed cleanly" in line for line in session.recovery_lines())
    # Every frame up to the last one on disk is there, intact, in order ...
    assert [f.frame for f in frames] == list(range(1, len(frames) + 1))
    assert len(frames) > 100, len(frames)
    expected = frame(len(frames), frames[-1].t_solve_ns)
    assert np.array_equal(frames[-1].people[3].theta, expected.people[3].theta)
    # ... and the last one on disk was published at most one flush interval (0.25 s, plus scheduling slack,
    # well within the promised second) before the recorder stopped.
    lost_s = (stopped_ns - frames[-1].t_solve_ns) / 1e9
    assert 0 <= lost_s < 1.0, lost_s


def _written(path: Path, n: int = 50) -> None:
    w = SessionWriter(path, MANIFEST, flush_interval_s=0.1)
    w.open()
    rec = SessionRecorder(w)
    for i in range(1, n + 1):
        rec.publish(frame(i, 1000 * i, people=2))
    w.close({"note": "test"})


def test_clean_session_reads_back_everything(tmp_path: Path) -> None:
    _written(tmp_path / "s")
    s = open_session(tmp_path / "s")
    assert s.closed_cleanly and s.manifest["note"] == "test" and s.manifest["writer"]["written"] == 50
    assert [f.frame for f in s.poses()] == list(range(1, 51))
    assert s.keypoints() == [] and s.imu() == []
    assert not any(r.damaged for r in s.check().values()) and s.recovery_lines() == []


def test_hand_truncated_and_corrupted_files_recover_everything_before_the_damage(tmp_path: Path) -> None:
    _written(tmp_path / "s")
    stream = tmp_path / "s" / "poses.mcs"
    data = stream.read_bytes()
    size = len(sf.encode_record(sf.T_POSE, sf.encode_pose(_record(1))))
    header = len(data) - 50 * size
    # Cut inside record 31: records 1..30 read back, the partial one is reported.
    stream.write_bytes(data[: header + 30 * size + size // 3])
    s = open_session(tmp_path / "s")
    assert [f.frame for f in s.poses()] == list(range(1, 31))
    assert s.reports["poses"].torn_tail_bytes == size // 3
    assert "torn tail of" in s.recovery_lines()[0]
    # A flipped byte in record 10 and garbage at the end: record 10 lost and counted, the rest recovered.
    bad = bytearray(data)
    bad[header + 9 * size + 100] ^= 0xFF
    stream.write_bytes(bytes(bad) + b"\x13\x37" * 7)
    s = open_session(tmp_path / "s")
    assert [f.frame for f in s.poses()] == [i for i in range(1, 51) if i != 10]
    r = s.reports["poses"]
    # the flipped record and the garbage (no record starts there) are each one corrupt stretch
    assert r.corrupt == 2 and r.skipped_bytes + r.torn_tail_bytes >= size + 14


def _record(i: int) -> sf.PoseRecord:
    from mocapd.service.outputs.recorder import pose_record

    return pose_record(frame(i, 1000 * i, people=2))


def test_a_full_queue_drops_and_counts_instead_of_blocking(tmp_path: Path) -> None:
    w = SessionWriter(tmp_path / "s", MANIFEST, queue_size=100)
    # Not opened: no thread drains the queue, like a disk that stopped keeping up.
    results = [w.put("poses", sf.T_POSE, sf.encode_pose, _record(1)) for _ in range(150)]
    assert results.count(True) == 100 and w.counters.dropped == 50 and w.counters.queued == 100


def test_bad_writer_settings_and_existing_streams_are_refused(tmp_path: Path) -> None:
    with pytest.raises(InputError):
        SessionWriter(tmp_path / "a", MANIFEST, flush_interval_s=1.5)
    _written(tmp_path / "s", 1)
    with pytest.raises(InputError):
        SessionWriter(tmp_path / "s", MANIFEST).open()
    with pytest.raises(InputError):
        open_session(tmp_path / "nothing")
    os.makedirs(tmp_path / "other")
    (tmp_path / "other" / "manifest.json").write_text('{"format": "x"}')
    with pytest.raises(InputError):
        open_session(tmp_path / "other")


def test_the_recorder_notes_knees_bending_the_wrong_way(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 28: a recorded person whose knee bends backwards for more than a moment is in the session's notes (its
    manifest, printed by every command that opens it); the others are not."""
    import asyncio

    from mocapd.core.skeleton import BONE_INDEX
    from mocapd.service.cli.session import _open

    w = SessionWriter(tmp_path / "s", MANIFEST, flush_interval_s=0.1)
    w.open()
    rec = SessionRecorder(w)
    knee = 3 + 3 * BONE_INDEX["LeftLowerLeg"]
    for i in range(1, 61):  # 1 s at 60 Hz
        f = frame(i, i * 1_000_000_000 // 60, people=2)
        for p in f.people:
            p.theta[:] = 0.0  # standing straight ...
        f.people[1].theta[knee] = -0.6  # ... but this one's left knee 34° the wrong way, all along
        rec.publish(f)
    asyncio.run(rec.aclose())
    s = _open(tmp_path / "s")
    people = [p.identity for p in frame(1, 0, people=2).people]
    assert s.manifest["plausibility"][people[0]]["implausible"] is False
    assert s.manifest["plausibility"][people[1]]["events"]["left_knee"]["events"] == 1
    assert f"note: {people[1]}: left knee bent the wrong way 1 time(s)" in capsys.readouterr().err
