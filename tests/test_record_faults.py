"""Faults while recording, on the real daemon (issue 32): the disk fills up, and the daemon is killed with SIGKILL.

Disk full: a 1 MiB tmpfs mounted in a mount namespace of the test's own (tests/enospc_rig.py). The live output
must keep streaming, recording stop with one log line and a ``/status`` flag, the session read back to its last
complete record with a manifest closed properly (no ``.tmp`` left) that says it was cut by ENOSPC, and
``mocapd session`` must say so. SIGKILL: the session recovers, with at most 1 s lost.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from mocapd.io.lifecycle import guarded_command
from mocapd.io.session import open_session
from tests.load import load_factor
from tests.rigs import synthetic_toml, write
from tools.stop_cases import Launched

REPO = Path(__file__).resolve().parents[1]


def test_a_full_disk_stops_the_recording_cleanly_while_the_output_goes_on(tmp_path: Path) -> None:
    cmd = guarded_command(["unshare", "-rm", sys.executable, "-m", "tests.enospc_rig", str(tmp_path)])
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=600, check=False)
    assert proc.returncode == 0, proc.stderr[-5000:]
    r = json.loads(proc.stdout.strip().splitlines()[-1])
    err = r["stderr"]
    # /status says recording stopped, and why; the live output goes on (3 s of frames after the cut, waited for:
    # a loaded machine publishes them late, and the rate is not what this test is about).
    assert r["recorder"]["recording"] is False and r["recorder"]["stopped"].startswith("ENOSPC"), r["recorder"]
    assert r["frames_after_cut"] >= 180, r
    # The recorder that stopped does not keep trying (or logging): nothing more is written after the cut.
    assert r["recorder_later"]["written"] == r["recorder"]["written"], r
    assert r["recorder_later"]["write_errors"] == 1, r
    # One log line, no traceback; a clean exit, nothing left.
    assert err.count("recording stopped") == 1 and err.count(" ERROR ") == 1, err
    assert "Traceback" not in err and r["rc"] == 0 and r["stop_s"] < 2.0 * load_factor() and r["left"] == [], r
    # The session: closed properly, cut by ENOSPC, every frame up to the last complete record, no .tmp.
    s = r["session"]
    assert s["closed_cleanly"] and s["cut"]["errno"] == "ENOSPC", s
    # Frames, IMU samples and keypoint sets share the 1 MiB: a loaded machine publishes fewer frames before it
    # fills (49 at load 9 under a profiler, against > 50 asked before), so half a second of frames is asked.
    assert s["frames"] > 30 and s["frames_consecutive"] and s["imu"] > 500 and s["keypoints"] > 50, s
    assert all(rep["corrupt"] == 0 for rep in s["reports"].values()), s
    assert not [f for f in s["files"] if f.endswith(".tmp")], s
    assert set(s["files"]) >= {"manifest.json", "imu.mcs", "keypoints.mcs", "poses.mcs"}, s
    cli = r["session_cli"]
    assert cli["rc"] == 0 and cli["json"]["cut"]["errno"] == "ENOSPC", cli
    assert "cut by ENOSPC" in cli["stderr"] and "the disk was full" in cli["stderr"], cli


@pytest.mark.quiet_machine  # "at most 1 s lost" is a wall-clock promise: the writer thread must get the CPU
def test_sigkill_while_recording_loses_at_most_one_second(tmp_path: Path) -> None:
    """``kill -9`` of the recording daemon: no clean close, but the session recovers, and what was published up
    to at most 1 s before the kill is on disk ([record] flush_interval_s = 0.25 s)."""
    config = write(tmp_path / "rig.toml", synthetic_toml())
    session = tmp_path / "session"
    run = Launched([sys.executable, "-m", "mocapd", "run", "--config", str(config), "--record", str(session)],
                   tmp_path / "run")  # fmt: skip
    try:
        run.notes.wait_for("READY=1", 300, run.alive)
        time.sleep(3.0)
        killed_ns = time.monotonic_ns()
        run.proc.send_signal(signal.SIGKILL)
        assert run.proc.wait(timeout=10) == -signal.SIGKILL
    finally:
        if run.alive():
            run.kill()
    outcome = run.finish()
    assert outcome.left == []
    s = open_session(session)
    frames = s.poses()
    assert not s.closed_cleanly
    assert frames and [f.frame for f in frames] == list(range(1, len(frames) + 1))
    lost_s = (killed_ns - frames[-1].tick_ns) / 1e9  # the last frame on disk was published at its tick
    assert 0.0 <= lost_s <= 1.0, lost_s
    imu = s.imu()
    assert imu and 0.0 <= (killed_ns - max(x.host_ns for x in imu)) / 1e9 <= 1.0
    assert any("not closed cleanly" in line for line in s.recovery_lines())
