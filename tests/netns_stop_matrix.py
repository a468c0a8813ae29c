"""Runs inside a private network namespace the test made (``unshare -rn python -m tests.netns_stop_matrix OUT``):
four Aravis fake GigE Vision cameras serving the Pose2Sim multi-person videos on 127.0.0.1-4 (started once),
then ``mocapd run`` on them, the way a user runs it, again and again:

- the stop matrix on this rig (issue 32): one case per phase, the signal taking turns (the synthetic rig, in
  tests/test_stop_matrix.py, gets every signal in every phase), each checked by :func:`tools.stop_cases.problems`
  here, where its ports are;
- faults: the whole daemon paused (SIGSTOP) for twice a camera's ``lost_after_s`` and resumed: no camera may be
  declared lost for it; then one camera stops sending but keeps its socket (its server frozen): it must be
  declared lost after its time-out and come back once it sends again.

Prints one JSON object of what happened; the test asserts on it.
"""

from __future__ import annotations

import asyncio
import json
import os
import signal
import sys
import time
import urllib.request
from pathlib import Path
from typing import Any

from mocapd.io.calibration_files import read_qca, scale_calibration, write_mocapd_toml
from mocapd.io.pose2sim_demo import CAMERAS, demo_calibration, demo_video
from mocapd.sim.fake_cameras import FakeCameraFleet, FakeCameraSpec
from mocapd.sim.fake_gige import add_loopback_aliases
from tools.stop_cases import Launched, problems, silent_pty, stop_in_phase

DEMO = "Demo_MultiPerson"
SCALE = 0.25  # 272 x 480 frames: four cameras and a detector on a loaded 2-core machine
SIZE = (272, 480)
FPS = 10.0
LOST_AFTER_S = 1.0
PAUSE_S = 1.3
"""Longer than ``lost_after_s`` (a naive silence count would declare every camera lost) and than the silence clock's
pause threshold (2 pop time-outs + half of ``lost_after_s``: 0.9 s), and well inside the cameras' GigE Vision
heartbeat time-out (3 s): a camera left without heartbeats longer than that releases its control channel, as a real
one does, and must be reopened. Aravis heartbeats once a second (``ARV_GV_DEVICE_HEARTBEAT_PERIOD_US``), so the last
one may come a second before the pause, and on a loaded machine the first one after it comes late: a 1.6 s pause
left 0.4 s, and in 3 runs of 11 on a busy 2-core machine one camera then sent no frame for a second after the pause
and was reopened (the likeliest cause; 16 runs on a calmer machine saw none)."""
SIGNALS = [signal.SIGINT, signal.SIGTERM, signal.SIGHUP]
PHASES = ["starting", "loading models", "loading the solver kernel", "opening devices", "running", "recording"]


def rig_toml(addresses: list[str], calibration: Path, extra: str = "") -> str:
    cams = "".join(
        f'[[cameras]]\nname = "{name}"\nsource = "aravis"\naddress = "{a}"\npixel_format = "BayerRG8"\n'
        f"region = [0, 0, {SIZE[0]}, {SIZE[1]}]\nframe_rate = {FPS}\npacket_size = 8192\n"
        f"lost_after_s = {LOST_AFTER_S}\n\n"
        for name, a in zip(CAMERAS, addresses, strict=True)
    )
    return (cams + f'[calibration]\nfile = "{calibration}"\n\n[detector]\nintra_op_threads = 2\n\n'
            "[detector.packing]\nenabled = false\n\n[daemon]\nhttp_port = 0\nlatency_s = 2.0\n"
            "keypoint_max_age_s = 1.0\nkeypoint_max_gap_s = 5.0\n\n[websocket]\nport = 0\n\n" + extra)  # fmt: skip


def _status(port: int) -> dict[str, Any]:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/status", timeout=30) as r:  # a loaded machine answers late
        st: dict[str, Any] = json.loads(r.read())
        return st


def _captures(port: int) -> list[dict[str, Any]]:
    return [c["capture"] for c in _status(port)["cameras"]]


def _until(cond: Any, timeout: float) -> float:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        if cond():
            return time.monotonic() - t0
        time.sleep(0.1)
    raise AssertionError("condition not reached in time")


def matrix(out: Path, addresses: list[str], calibration: Path) -> list[dict[str, Any]]:
    results = []
    for i, phase in enumerate(PHASES):
        sig = SIGNALS[i % len(SIGNALS)]
        folder = out / f"case{i}"
        folder.mkdir()
        env: dict[str, str] = {}
        extra, held = "", None
        if phase == "loading the solver kernel":
            env["NUMBA_CACHE_DIR"] = str(folder / "numba")
        if phase == "opening devices":
            port, held = silent_pty(folder)
            extra = f'[imu]\nports = ["{port}"]\nresponse_timeout_s = 5.0\nattempts = 20\n'
        config = folder / "rig.toml"
        config.write_text(rig_toml(addresses, calibration, extra))
        cmd = [sys.executable, "-m", "mocapd", "run", "--config", str(config)]
        session = folder / "session" if phase == "recording" else None
        if session is not None:
            cmd += ["--record", str(session)]
        then = SIGNALS[(i + 1) % len(SIGNALS)] if phase in ("running", "recording") else None
        try:
            outcome = stop_in_phase(cmd, folder / "run", "running" if phase == "recording" else phase, sig,
                                    then=then, env=env, settle_s=1.0 if phase == "recording" else 0.0)  # fmt: skip
        finally:
            if held is not None:
                os.close(held)
        said = "running" if phase == "recording" else phase
        results.append({"phase": phase, "signal": sig.name, "then": then.name if then else None,
                        "stop_s": round(outcome.stop_s, 3),
                        "problems": problems(outcome, sig, said, "mocapd run", session)})  # fmt: skip
    return results


def faults(out: Path, addresses: list[str], calibration: Path, fleet: FakeCameraFleet) -> dict[str, Any]:
    folder = out / "faults"
    folder.mkdir()
    config = folder / "rig.toml"
    config.write_text(rig_toml(addresses, calibration))
    run = Launched([sys.executable, "-m", "mocapd", "run", "--config", str(config)], folder)
    result: dict[str, Any] = {}
    try:
        run.notes.wait_for("READY=1", 300, run.alive)
        _until(lambda: any(line.startswith("ready: status") for line in run.out), 10)
        port = int(next(line for line in run.out if line.startswith("ready: status")).split(":")[3].split("/")[0])
        _until(lambda: all(c["frames"] > 10 for c in _captures(port)), 60)
        # The whole daemon paused for longer than lost_after_s: its cameras' frames wait in the kernel meanwhile.
        run.proc.send_signal(signal.SIGSTOP)
        time.sleep(PAUSE_S)
        run.proc.send_signal(signal.SIGCONT)
        before = [c["frames"] for c in _captures(port)]
        _until(lambda: all(c["frames"] > b + 5 for c, b in zip(_captures(port), before, strict=True)), 30)
        result["after_pause"] = [{k: c[k] for k in ("failures", "reopens", "last_error")} for c in _captures(port)]
        # One camera stops sending but keeps its socket: its server frozen.
        server = fleet.cameras[1].pid
        assert server is not None
        failed = _captures(port)[1]["failures"]
        os.kill(server, signal.SIGSTOP)
        t0 = time.monotonic()
        try:
            result["declared_lost_after_s"] = round(_until(lambda: _captures(port)[1]["failures"] > failed, 30), 2)
            result["lost_error"] = _captures(port)[1]["last_error"]
        finally:
            os.kill(server, signal.SIGCONT)
        frames = _captures(port)[1]["frames"]
        result["back_after_s"] = round(_until(lambda: _captures(port)[1]["frames"] > frames + 5, 60), 2)
        result["frozen_s"] = round(time.monotonic() - t0, 2)
        now = _captures(port)
        result["others_failures"] = [now[i]["failures"] - result["after_pause"][i]["failures"] for i in (0, 2, 3)]
        result["stop_s"] = round(run.stop(signal.SIGTERM), 3)
        outcome = run.finish()
        result["rc"] = outcome.rc
        result["traceback"] = "Traceback" in outcome.out + outcome.err
    finally:
        if run.alive():
            run.kill()
    return result


async def main(out: Path) -> dict[str, Any]:
    addresses = add_loopback_aliases(len(CAMERAS))
    calibration = out / "calibration.toml"
    write_mocapd_toml(scale_calibration(read_qca(demo_calibration(DEMO)), SCALE), calibration)
    specs = [FakeCameraSpec(name, demo_video(DEMO, name), a, SIZE, 60.0, "BayerRG8", 20)
             for name, a in zip(CAMERAS, addresses, strict=True)]  # fmt: skip
    fleet = FakeCameraFleet(specs, time.monotonic_ns(), replug_after_s=1.0)
    started = asyncio.Event()
    fleet_task = asyncio.create_task(fleet.run(started))
    await asyncio.wait({asyncio.create_task(started.wait()), fleet_task}, return_when=asyncio.FIRST_COMPLETED)
    if fleet_task.done():
        fleet_task.result()
    try:
        cases = await asyncio.to_thread(matrix, out, addresses, calibration)
        fault = await asyncio.to_thread(faults, out, addresses, calibration, fleet)
    finally:
        await fleet.stop()
        fleet_task.cancel()
        await asyncio.gather(fleet_task, return_exceptions=True)
    return {"cases": cases, "faults": fault}


if __name__ == "__main__":
    signal.signal(signal.SIGHUP, signal.SIG_DFL)  # the cases run on threads: see tools.stop_cases (nohup)
    print(json.dumps(asyncio.run(main(Path(sys.argv[1])))), flush=True)
