"""How long a stop takes in each phase, and what a SIGKILL loses (issue 32): the numbers of the lifecycle table in
docs/reliability.md.

Developer benchmark, not a ``mocapd bench`` verb (those are the benchmarks a user runs).

For ``mocapd run`` on the synthetic rig, ``mocapd run`` on four fake GigE cameras is in the test suite (a
private network namespace), and ``mocapd demo``: each phase × each stop signal, ``--repeats`` times, landed in the
phase as :mod:`tools.stop_cases` does (the announcing process frozen at its phase's sd_notify message, the signal
sent, the process thawed): the seconds from the signal to the exit, the exit status and the phase the process
named. Then SIGKILL while recording, ``--kills`` times: the seconds of published output missing from the
session (the kill's time minus the tick time of the last frame on disk), and SIGKILL of ``mocapd demo``: how long
until its namespace child and camera servers are gone. Prints JSON, with the load average.

    .venv/bin/python tools/bench_lifecycle.py --repeats 3 --kills 5
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import tempfile
import time
from pathlib import Path
from statistics import median
from typing import Any

from mocapd.io.session import open_session
from tools.stop_cases import Launched, silent_pty, stop_in_phase, tagged_processes

SIGNALS = [signal.SIGINT, signal.SIGTERM, signal.SIGHUP]
PHASES = ["starting", "loading models", "loading the solver kernel", "opening devices", "running", "stopping"]
SYNTHETIC = "".join(f'[[cameras]]\nname = "cam{i}"\nsource = "synthetic"\n\n' for i in range(4))
PORTS = "[daemon]\nhttp_port = 0\n\n[websocket]\nport = 0\n\n"


def _case(folder: Path, command: list[str], base: str, phase: str, sig: int) -> dict[str, Any]:
    folder.mkdir(parents=True)
    env, extra, held = {}, "", None
    if phase == "loading the solver kernel":
        env["NUMBA_CACHE_DIR"] = str(folder / "numba")  # a real compile
    if phase == "opening devices":
        port, held = silent_pty(folder)  # a serial port that never answers
        extra = f'[imu]\nports = ["{port}"]\nresponse_timeout_s = 5.0\nattempts = 20\n'
    config = folder / "rig.toml"
    config.write_text(base + extra)
    first, then = (signal.SIGTERM, sig) if phase == "stopping" else (sig, None)
    try:
        o = stop_in_phase([*command, "--config", str(config)], folder / "run",
                          "running" if phase == "stopping" else phase, first, then=then, env=env)  # fmt: skip
    finally:
        if held is not None:
            os.close(held)
    said = o.stop_lines[0]["phase"] if o.stop_lines else None
    return {"stop_s": round(o.stop_s, 3), "rc": o.rc, "said": said, "left": len(o.left)}


def stops(work: Path, name: str, command: list[str], base: str, phases: list[str], repeats: int) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for phase in phases:
        for sig in SIGNALS:
            runs = [_case(work / f"{name}-{phase}-{sig.name}-{k}".replace(" ", "_"), command, base, phase, sig)
                    for k in range(repeats)]  # fmt: skip
            out[f"{phase} / {sig.name}"] = {
                "stop_s_median": round(median(r["stop_s"] for r in runs), 3),
                "stop_s_max": max(r["stop_s"] for r in runs),
                "exit": sorted({r["rc"] for r in runs}),
                "said": sorted({str(r["said"]) for r in runs}),
                "left": sum(r["left"] for r in runs),
            }
    return out


def kill_while_recording(work: Path, kills: int) -> dict[str, Any]:
    lost = []
    for k in range(kills):
        folder = work / f"kill-{k}"
        folder.mkdir()
        config = folder / "rig.toml"
        config.write_text(SYNTHETIC + PORTS)
        session = folder / "session"
        run = Launched([sys.executable, "-m", "mocapd", "run", "--config", str(config), "--record", str(session)],
                       folder / "run")  # fmt: skip
        try:
            run.notes.wait_for("READY=1", 300, run.alive)
            time.sleep(3.0 + 0.137 * k)  # a different moment of the flush cycle each time
            killed = time.monotonic_ns()
            run.proc.send_signal(signal.SIGKILL)
            run.proc.wait(timeout=10)
        finally:
            if run.alive():
                run.kill()
        run.finish()
        frames = open_session(session).poses()
        lost.append(round((killed - frames[-1].tick_ns) / 1e9, 3))
    return {"lost_s": lost, "lost_s_median": median(lost), "lost_s_max": max(lost),
            "flush_interval_s": 0.25}  # fmt: skip


def kill_demo(work: Path) -> dict[str, Any]:
    folder = work / "kill-demo"
    folder.mkdir()
    config = folder / "demo.toml"
    config.write_text("[websocket]\nport = 0\n")
    run = Launched([sys.executable, "-m", "mocapd", "demo", "--config", str(config), "--http-port", "0",
                    "--scale", "0.25"], folder / "run")  # fmt: skip
    try:
        run.notes.wait_for("READY=1", 300, run.alive)
        before = len(tagged_processes(run.tag))
        t0 = time.monotonic()
        run.proc.send_signal(signal.SIGKILL)
        run.proc.wait(timeout=10)
        while tagged_processes(run.tag) and time.monotonic() - t0 < 10:
            time.sleep(0.01)
        gone_s = time.monotonic() - t0
    finally:
        if run.alive() or tagged_processes(run.tag):
            run.kill()
    run.finish()
    return {"processes": before, "all_gone_s": round(gone_s, 3)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--repeats", type=int, default=1, help="stops per phase and signal (default 1)")
    p.add_argument("--kills", type=int, default=5, help="SIGKILLs while recording (default 5)")
    p.add_argument("--no-demo", action="store_true", help="leave out the camera demo (fake GigE, detector)")
    args = p.parse_args()
    load0 = os.getloadavg()
    run = [sys.executable, "-m", "mocapd", "run"]
    demo = [sys.executable, "-m", "mocapd", "demo", "--http-port", "0", "--scale", "0.25"]
    with tempfile.TemporaryDirectory(prefix="mocapd-bench-lifecycle-") as tmp:
        work = Path(tmp)
        report: dict[str, Any] = {"run_synthetic": stops(work, "run", run, SYNTHETIC + PORTS, PHASES, args.repeats)}
        if not args.no_demo:
            phases = ["starting", "starting the fake cameras", *PHASES[1:]]
            report["demo"] = stops(work, "demo", demo, "[websocket]\nport = 0\n\n", phases, args.repeats)
            report["sigkill_demo"] = kill_demo(work)
        report["sigkill_while_recording"] = kill_while_recording(work, args.kills)
    report["loadavg"] = {"start": [round(x, 2) for x in load0], "end": [round(x, 2) for x in os.getloadavg()]}
    report["cpus"] = os.cpu_count()
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
