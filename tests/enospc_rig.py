"""Runs inside a private mount namespace the test made (``unshare -rm python -m tests.enospc_rig OUT``): a 1 MiB
tmpfs mounted there, ``mocapd run`` on the synthetic rig recording onto it until the disk is full, then what a
user sees: ``/status``, the log, the exit, the session and ``mocapd session``. The tmpfs is gone when the
namespace ends, so everything is read here; prints one JSON object for tests/test_record_faults.py.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path
from typing import Any

from mocapd.io.session import open_session
from tests.load import load_factor
from tests.rigs import synthetic_toml
from tools.stop_cases import Launched


def _status(port: int) -> dict[str, Any]:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/status", timeout=30) as r:  # a loaded machine answers late
        st: dict[str, Any] = json.loads(r.read())
        return st


def main(out: Path) -> dict[str, Any]:
    mnt = out / "mnt"
    mnt.mkdir()
    subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(mnt)], check=True)
    config = out / "rig.toml"
    config.write_text(synthetic_toml())
    session = mnt / "session"
    run = Launched([sys.executable, "-m", "mocapd", "run", "--config", str(config), "--record", str(session)],
                   out / "run")  # fmt: skip
    result: dict[str, Any] = {}
    try:
        run.notes.wait_for("READY=1", 300, run.alive)
        end = time.monotonic() + 10 * load_factor()
        while not any(line.startswith("ready: status") for line in run.out) and time.monotonic() < end:
            time.sleep(0.05)
        port = int(next(line for line in run.out if line.startswith("ready: status")).split(":")[3].split("/")[0])
        end = time.monotonic() + 120 * load_factor()
        while _status(port)["sinks"]["recorder"]["recording"] and time.monotonic() < end:
            time.sleep(0.2)
        st = _status(port)
        result["recorder"] = st["sinks"]["recorder"]
        frames_at_cut = st["output"]["frames"]
        # The live output goes on: 3 s of frames at 60 Hz are published, however long a loaded machine takes to
        # publish them (waited for, bounded; the frame count, not the rate, is what the test checks).
        t_cut = time.monotonic()
        end = t_cut + 60 * load_factor()
        while (st := _status(port))["output"]["frames"] < frames_at_cut + 180 and time.monotonic() < end:
            time.sleep(0.2)
        result["frames_after_cut"] = st["output"]["frames"] - frames_at_cut
        result["seconds_for_them"] = round(time.monotonic() - t_cut, 1)
        result["recorder_later"] = st["sinks"]["recorder"]
        result["stop_s"] = round(run.stop(signal.SIGTERM), 3)
        outcome = run.finish()
        result["rc"] = outcome.rc
        result["stderr"] = outcome.err
        result["left"] = outcome.left
    finally:
        if run.alive():
            run.kill()
    s = open_session(session)
    frames = s.poses()
    result["session"] = {
        "closed_cleanly": s.closed_cleanly,
        "cut": s.cut,
        "frames": len(frames),
        "frames_consecutive": [f.frame for f in frames] == list(range(1, len(frames) + 1)),
        "imu": len(s.imu()),
        "keypoints": len(s.keypoints()),
        "reports": {k: {"corrupt": v.corrupt, "torn_tail_bytes": v.torn_tail_bytes} for k, v in s.reports.items()},
        "files": sorted(p.name for p in session.iterdir()),
    }
    info = subprocess.run([sys.executable, "-m", "mocapd", "session", str(session)], capture_output=True,
                          text=True, check=False)  # fmt: skip
    result["session_cli"] = {"rc": info.returncode, "stderr": info.stderr, "json": json.loads(info.stdout)}
    return result


if __name__ == "__main__":
    print(json.dumps(main(Path(sys.argv[1]))), flush=True)
