"""``mocapd devices`` as a user runs it, with a simulated Xsens device on a real pseudo-terminal given by --serial.

Each run is under ``unshare -rn`` (a private, empty network namespace), so that nothing the command does can reach
a real network even if it tried. GigE Vision discovery and the Aravis Fake interface are covered by
tests/test_gige_discovery.py, the snippet for every kind of device by tests/test_inventory.py.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tomllib
import tty
from collections.abc import Iterator
from pathlib import Path

import pytest

from mocapd.service.cli import main
from mocapd.service.config import parse_config
from mocapd.sim import xsens as xsens_sim

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def sim(tmp_path: Path) -> Iterator[xsens_sim.XsensSimulator]:
    device = xsens_sim.SimDevice(xsens_sim.synthetic_motion(device_id=0x00B40042))
    started = xsens_sim.XsensSimulator(tmp_path / "imu0", device).start()
    yield started
    started.stop()


def _devices(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        ["unshare", "-rn", sys.executable, "-m", "mocapd", "devices", *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


def test_an_xsens_device_on_a_named_port_is_identified(sim: xsens_sim.XsensSimulator) -> None:
    proc = _devices("--serial", str(sim.link), "--json")
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = json.loads(proc.stdout)
    (entry,) = [s for s in out["serial"] if s["device"] == str(sim.link)]
    assert (entry["device_id"], entry["product_code"], entry["firmware"], entry["error"]) == (
        "00B40042", "MTw2-3A7G6", "4.6.0", None
    )  # fmt: skip
    assert out["gige"] == [] and out["gige_counters"] == {}
    imu = tomllib.loads(out["snippet"])["imu"]
    assert list(parse_config({"imu": imu}).imu.ports) == [str(sim.link)]
    assert '# "00B40042" = "<bone>"' in out["snippet"]


def test_table_and_snippet_and_a_port_that_does_not_answer(sim: xsens_sim.XsensSimulator) -> None:
    master, slave = os.openpty()
    tty.setraw(slave)
    try:
        silent = os.ttyname(slave)
        proc = _devices("--serial", str(sim.link), "--serial", silent)
    finally:
        os.close(master)
        os.close(slave)
    assert proc.returncode == 1, proc.stderr[-2000:]  # a port named on the command line gave nothing
    lines = proc.stdout.splitlines()
    row = next(line for line in lines if line.strip().startswith(str(sim.link)))
    assert row.split()[1:4] == ["00B40042", "MTw2-3A7G6", "4.6.0"]
    assert any(line.strip().startswith(silent) and "no answer" in line for line in lines)
    assert "Xsens serial devices:" in proc.stdout and "GigE Vision is listed only with --gige-interface" in proc.stdout
    assert f"warning: serial {silent}: " in proc.stderr
    # A SlimeVR tracker owner is told where trackers show up (on Wi-Fi, nothing here can list them).
    assert "SlimeVR trackers (Wi-Fi, not listed here: they connect to a running server):" in proc.stdout
    assert "[imu.slimevr] enabled = true" in proc.stdout and "/status imu.slimevr.trackers" in proc.stdout
    snippet = proc.stdout[proc.stdout.index("# From `mocapd devices`") :]
    assert list(parse_config({"imu": tomllib.loads(snippet)["imu"]}).imu.ports) == [str(sim.link)]


def test_bad_timeout_is_refused_before_looking(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["devices", "--timeout", "0"]) == 2
    assert "--timeout must be > 0" in capsys.readouterr().err
