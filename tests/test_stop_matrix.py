"""Every phase × every stop signal (issue 32): ``mocapd run`` on the synthetic rig and on fake GigE cameras, and
``mocapd demo``, stopped by SIGINT (Ctrl-C), SIGTERM (systemd, kill) and SIGHUP (the terminal closed) while
starting, loading models, compiling the solver kernel, opening devices, running, recording and stopping.

Each case asserts what a technician relies on: exit status 0 (a requested stop), gone within 2 s of the signal,
one line naming the signal and the phase (no traceback), no process of the run left (``/proc`` scan for the
run's tag), its ports free again, nothing left in its TMPDIR, and a recording's session complete and closed.

How a signal is landed in a phase, and the other helpers: :mod:`tools.stop_cases`. Start-ups are shared where
the phase allows: a daemon stopped while running or recording is also sent a second signal while it stops (the
"stopping" phase), so those two phases cost one start-up per signal. The kernel phase is a real compile (an
empty ``NUMBA_CACHE_DIR``); the devices phase waits on a serial port that never answers.
"""

from __future__ import annotations

import json
import os
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
from tools.stop_cases import Launched, port_free, problems, ready_ports, silent_pty, stop_in_phase, tagged_processes

REPO = Path(__file__).resolve().parents[1]
SIGNALS = [signal.SIGINT, signal.SIGTERM, signal.SIGHUP]
PHASES = ["starting", "loading models", "loading the solver kernel", "opening devices", "running", "recording"]


def _next(sig: signal.Signals) -> signal.Signals:
    return SIGNALS[(SIGNALS.index(sig) + 1) % len(SIGNALS)]


def _settle(phase: str) -> float:
    """A recording is stopped once it has recorded something (1 s after READY), other phases as they begin."""
    return 1.0 if phase == "recording" else 0.0


def case_setup(tmp_path: Path, phase: str, base: str) -> tuple[Path, dict[str, str], int | None]:
    """The config file, environment and held pty of a case: a fresh numba cache for the kernel phase (a real
    compile), a serial port that never answers for the devices phase."""
    env: dict[str, str] = {}
    held = None
    extra = ""
    if phase == "loading the solver kernel":
        env["NUMBA_CACHE_DIR"] = str(tmp_path / "numba")
    if phase == "opening devices":
        port, held = silent_pty(tmp_path)
        extra = f'[imu]\nports = ["{port}"]\nresponse_timeout_s = 5.0\nattempts = 20\n'
    return write(tmp_path / "rig.toml", base + extra), env, held


@pytest.mark.parametrize("phase", PHASES)
@pytest.mark.parametrize("sig", SIGNALS, ids=lambda s: s.name)
def test_run_on_the_synthetic_rig_stops_in_every_phase(tmp_path: Path, phase: str, sig: signal.Signals) -> None:
    config, env, held = case_setup(tmp_path, phase, synthetic_toml())
    session = tmp_path / "session" if phase == "recording" else None
    cmd = [sys.executable, "-m", "mocapd", "run", "--config", str(config)]
    if session is not None:
        cmd += ["--record", str(session)]
    wait_for = "running" if phase == "recording" else phase
    then = _next(sig) if phase in ("running", "recording") else None  # and the stopping phase
    try:
        outcome = stop_in_phase(cmd, tmp_path / "run", wait_for, sig, then=then, env=env, settle_s=_settle(phase))
    finally:
        if held is not None:
            os.close(held)
    assert not problems(outcome, sig, "running" if phase == "recording" else phase, "mocapd run", session)


def test_run_on_fake_gige_cameras_stops_in_every_phase_and_tells_a_pause_from_a_lost_camera(tmp_path: Path) -> None:
    """The same on four fake GigE Vision cameras in a private network namespace (one case per phase, the signal
    taking turns), and the camera faults: a pause of the whole daemon is not a lost camera; a camera that stops
    sending but keeps its socket is (tests/netns_stop_matrix.py)."""
    cmd = guarded_command(["unshare", "-rn", sys.executable, "-m", "tests.netns_stop_matrix", str(tmp_path)])
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=1200, check=False)
    assert proc.returncode == 0, proc.stderr[-5000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert [c["phase"] for c in result["cases"]] == PHASES
    for case in result["cases"]:
        assert not case["problems"], case
    f = result["faults"]
    # Paused for longer than lost_after_s: no camera declared lost, none reopened.
    assert all(c["failures"] == 0 and c["reopens"] == 0 for c in f["after_pause"]), f
    # A camera that stops sending is declared lost after its time-out (1 s; plus a pop time-out and a status
    # poll), the others untouched, and it comes back once it sends again.
    # Bounds in seconds scaled by the machine's load (tests/load.py): a starved daemon notices and stops later.
    assert f["declared_lost_after_s"] < (1.0 + 3.0) * load_factor(), f
    assert "sent no frame" in f["lost_error"] or "control connection" in f["lost_error"], f
    assert f["others_failures"] == [0, 0, 0], f
    assert f["rc"] == 0 and f["stop_s"] < 2.0 * load_factor() and not f["traceback"], f


DEMO_PHASES = ["starting", "starting the fake cameras", *PHASES[1:]]
DEMO_CHILD = "mocapd demo (in its network namespace)"


def _demo_cmd(config: Path, session: Path | None = None) -> list[str]:
    cmd = [sys.executable, "-m", "mocapd", "demo", "--config", str(config), "--http-port", "0", "--scale", "0.25"]
    return cmd + (["--record", str(session)] if session is not None else [])


@pytest.mark.parametrize("phase", DEMO_PHASES)
def test_demo_stops_in_every_phase(tmp_path: Path, phase: str) -> None:
    """``mocapd demo`` (a parent in the host's network namespace, the daemon and four fake camera servers in a
    private one): the signal taking turns over the phases; the parent forwards it, the child names the phase."""
    i = DEMO_PHASES.index(phase)
    sig = SIGNALS[i % len(SIGNALS)]
    config, env, held = case_setup(tmp_path, phase, "[websocket]\nport = 0\n\n")
    session = tmp_path / "session" if phase == "recording" else None
    then = _next(sig) if phase in ("running", "recording") else None
    try:
        outcome = stop_in_phase(_demo_cmd(config, session), tmp_path / "run", "running" if phase == "recording"
                                else phase, sig, then=then, env=env, settle_s=_settle(phase))  # fmt: skip
    finally:
        if held is not None:
            os.close(held)
    who = "mocapd demo" if phase == "starting" else DEMO_CHILD
    assert not problems(outcome, sig, "running" if phase == "recording" else phase, who, session)


def test_kill_9_of_the_demo_leaves_no_process_and_frees_its_ports(tmp_path: Path) -> None:
    """SIGKILL of ``mocapd demo`` (a crashed terminal, the OOM killer): its namespace child and the four fake
    camera servers end too (the kernel's SIGTERM: PR_SET_PDEATHSIG), within 2 s; the ports are free again; and
    the child, stopped by that SIGTERM as by a Ctrl-C, closed its recording."""
    config = write(tmp_path / "demo.toml", "[websocket]\nport = 0\n")
    session = tmp_path / "session"
    run = Launched(_demo_cmd(config, session), tmp_path / "run")
    try:
        run.notes.wait_for("READY=1", 300, run.alive)
        time.sleep(2.0)  # recording
        assert len(tagged_processes(run.tag)) >= 6  # the demo, its namespace child, four camera servers
        t0 = time.monotonic()
        run.proc.send_signal(signal.SIGKILL)
        run.proc.wait(timeout=10)
        while tagged_processes(run.tag) and time.monotonic() - t0 < 10:
            time.sleep(0.02)
        gone_s = time.monotonic() - t0
    finally:
        if run.alive() or tagged_processes(run.tag):
            run.kill()
    outcome = run.finish()
    assert gone_s < 2.0 and outcome.left == [], outcome.describe()
    ports = ready_ports(outcome.out)
    assert len(ports) == 2 and all(port_free(p) for p in ports), outcome.describe()
    assert [(x["who"], x["signal"], x["phase"]) for x in outcome.stop_lines] == [(DEMO_CHILD, "SIGTERM", "running")]
    s = open_session(session)
    assert s.closed_cleanly and s.poses() and s.cut is None, s.recovery_lines()
    assert outcome.tmp_left == []
