"""Two camera hosts and a solver host in three network namespaces joined by veth pairs (tests/netns_camera_hosts.py):
fake GigE Vision cameras and the real detector on each camera host, user/password-authenticated Zenoh over the
links, both people solved and streamed; a camera host killed mid-run is shown lost, its cameras leave the solve,
and it rejoins when started again, without a restart of the solver host."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

from mocapd.io.lifecycle import guarded_command
from mocapd.service.cli import main
from tests.test_run_rig import _calib

REPO = Path(__file__).resolve().parents[1]


def test_camera_hosts_in_namespaces_solve_lose_and_rejoin(tmp_path: Path) -> None:
    assert main(["calibrate", "convert", str(_calib()), str(tmp_path / "calibration.toml"), "--scale", "0.5"]) == 0
    proc = subprocess.run(
        guarded_command(["unshare", "-rn", sys.executable, "-m", "tests.netns_camera_hosts", "main", "--folder",
                         str(tmp_path)]),
        cwd=REPO, capture_output=True, text=True, timeout=1500, check=False,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-5000:]
    r: dict[str, Any] = json.loads(proc.stdout.strip().splitlines()[-1])
    (tmp_path / "result.json").write_text(json.dumps(r, indent=1), encoding="utf-8")  # for a look after the run
    out = "".join(r["output"])
    before = r["before"]["remote_hosts"]
    for host in ("hostA", "hostB"):
        assert before[host]["lost"] is False and before[host]["round_trips"] > 0
        # One machine, one CLOCK_MONOTONIC: the true offset is 0 and must lie within the reported bound.
        assert abs(before[host]["clock_offset_ms"]) <= before[host]["clock_uncertainty_ms"]
    for p in r["before"]["people"]:
        x, y, z = p["root_m"]
        assert 0.5 < y < 1.3 and abs(x) < 3.0 and abs(z) < 3.0 and p["views"] >= 2, p
    assert r["stream"]["max_subjects"] == 2 and r["stream"]["frames_with_two"] >= 10
    lost = r["while_lost"]
    assert lost["remote_hosts"]["hostB"]["last_seen_s"] > 3.0  # lost once silent for zenoh.lost_after_s
    assert lost["remote_hosts"]["hostB"]["lost"] and not lost["remote_hosts"]["hostA"]["lost"]
    assert lost["missing_cameras"] == 2
    after = r["after"]["remote_hosts"]["hostB"]
    assert after["joins"] == 2 and after["losses"] == 1 and after["restarts"] == 1
    assert len(r["after"]["people"]) == 2
    cams = {c["name"]: c for c in r["after"]["cameras"]}
    assert all(cams[c]["delivered"] > 0 for c in ("cam01", "cam02", "cam03", "cam04"))
    assert r["exit_code"] == 0, out
    assert "Traceback" not in out, out
