"""Camera hosts in network namespaces of their own (run by tests/test_camera_hosts_netns.py, never directly on a
shared network).

``main`` runs inside a private network namespace the test made (``unshare -rn``): the solver host. It makes one
more namespace per camera host, joined to its own by a veth pair (solver side ``10.78.<k>.1``, host side
``10.78.<k>.2``), and starts in each (``nsenter``) this module's ``host`` role: Aravis fake GigE Vision cameras on
that namespace's loopback serving the Pose2Sim multi-person videos, and ``mocapd detect-host`` on them with the
real detector, connecting to the solver host over the veth link with user/password authentication (the solver
host listens off loopback, so the config requires it). Then ``mocapd run`` with ``source = "zenoh"`` cameras, a
WebSocket client reading its pose stream, host B's detect-host killed (SIGKILL) and
started again (the ``host`` role kills its detect-host on SIGUSR1 and starts a new one on SIGUSR2; its cameras
stay up). Prints one JSON line; the test asserts on it.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path
from typing import Any

from mocapd.io.lifecycle import guarded_command
from mocapd.io.pose2sim_demo import demo_video
from mocapd.service.demo.cameras import video_fps
from mocapd.sim.camera_hosts import host_config, solver_config
from mocapd.sim.fake_cameras import FakeCameraFleet, FakeCameraSpec
from mocapd.sim.fake_gige import add_loopback_aliases
from mocapd.sim.gige_network import _disable_ipv6, _ip
from tests.netns_rig import _read_stream

DEMO = "Demo_MultiPerson"
HOSTS = {"hostA": ["cam01", "cam02"], "hostB": ["cam03", "cam04"]}
PORT = 7447


# -------------------------------------------------------------------------------------------- camera host role
async def host_role(config: str, cameras: list[str]) -> int:
    addresses = add_loopback_aliases(len(cameras))
    specs = [FakeCameraSpec(c, demo_video(DEMO, c), a, (544, 960), video_fps(demo_video(DEMO, c)))
             for c, a in zip(cameras, addresses, strict=True)]  # fmt: skip
    fleet = FakeCameraFleet(specs, time.monotonic_ns(), replug_after_s=1.0)
    started = asyncio.Event()
    fleet_task = asyncio.create_task(fleet.run(started))
    await started.wait()
    # guarded: a detect-host ends with this process, however it ends (issue 32: no orphans, in tests either)
    cmd = guarded_command([sys.executable, "-m", "mocapd", "detect-host", "--config", config])
    procs = [await asyncio.create_subprocess_exec(*cmd)]
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    loop.add_signal_handler(signal.SIGTERM, stop.set)

    def crash() -> None:  # SIGUSR1: the detect-host dies at once (SIGKILL: no goodbye to the solver host)
        if procs[-1].returncode is None:
            procs[-1].kill()

    async def restart() -> None:  # SIGUSR2: a new detect-host, as after a crash and a restart by systemd
        await procs[-1].wait()
        procs.append(await asyncio.create_subprocess_exec(*cmd))

    loop.add_signal_handler(signal.SIGUSR1, crash)
    restarts: list[asyncio.Task[None]] = []
    loop.add_signal_handler(signal.SIGUSR2, lambda: restarts.append(asyncio.ensure_future(restart())))
    try:
        await stop.wait()
    finally:
        proc = procs[-1]
        if proc.returncode is None:
            proc.send_signal(signal.SIGINT)
            await asyncio.wait_for(proc.wait(), 30)
        await fleet.stop()
        fleet_task.cancel()
        await asyncio.gather(fleet_task, return_exceptions=True)
    return 0


# -------------------------------------------------------------------------------------------- solver host role
def _namespace() -> subprocess.Popen[bytes]:
    holder = subprocess.Popen(guarded_command(["unshare", "-n", "sleep", "infinity"]))
    own = os.readlink("/proc/self/ns/net")
    for _ in range(500):
        with contextlib.suppress(FileNotFoundError, PermissionError):
            if os.readlink(f"/proc/{holder.pid}/ns/net") != own:
                _disable_ipv6(holder.pid)
                return holder
        time.sleep(0.01)
    raise RuntimeError("could not make a network namespace")


def _status(url: str) -> dict[str, Any]:
    with urllib.request.urlopen(f"{url}/status", timeout=5) as r:
        result: dict[str, Any] = json.loads(r.read())
        return result


async def _until(url: str, pred: Any, timeout: float, what: str, log: list[str]) -> dict[str, Any]:
    end = time.monotonic() + timeout
    st: dict[str, Any] = {}
    while time.monotonic() < end:
        with contextlib.suppress(OSError):
            st = _status(url)
            if pred(st):
                return st
        await asyncio.sleep(0.25)
    raise RuntimeError(f"{what} not within {timeout} s; last status {json.dumps(st)[:3000]}\n{''.join(log[-40:])}")


def _people(st: dict[str, Any]) -> int:
    return len((st.get("frame") or {}).get("people", []))


async def _lines(stream: asyncio.StreamReader, out: list[str]) -> None:
    while line := await stream.readline():
        out.append(line.decode(errors="replace"))


async def main(folder: Path) -> dict[str, Any]:
    _disable_ipv6()
    _ip("link", "set", "lo", "up")
    # One user per machine: the solver host admits each camera host's messages from its own user alone
    # ([zenoh] identities, issue 34).
    users = {"mocapd": "correct-horse-battery", **{h: f"{h}-staple-battery" for h in HOSTS}}
    for user, password in users.items():
        (folder / f"password-{user}").write_text(password + "\n", encoding="utf-8")
    (folder / "users").write_text("".join(f"{u}:{p}\n" for u, p in users.items()), encoding="utf-8")
    auth = {"user": "mocapd", "password_file": str(folder / "password-mocapd")}
    holders: dict[str, subprocess.Popen[bytes]] = {}
    listen = []
    for k, host in enumerate(HOSTS, start=1):
        holder = holders[host] = _namespace()
        _ip("link", "add", host, "type", "veth", "peer", "name", f"{host}-peer")
        _ip("link", "set", f"{host}-peer", "netns", str(holder.pid))
        _ip("addr", "add", f"10.78.{k}.1/24", "dev", host)
        _ip("link", "set", host, "up")
        _ip("addr", "add", f"10.78.{k}.2/24", "dev", f"{host}-peer", netns_pid=holder.pid)
        _ip("link", "set", f"{host}-peer", "up", netns_pid=holder.pid)
        listen.append(f"tcp/10.78.{k}.1:{PORT}")
        cams = [{"name": c, "source": "aravis", "address": f"127.0.0.{i}", "pixel_format": "BayerRG8",
                 "region": [0, 0, 544, 960], "frame_rate": 60.0, "packet_size": 8192}
                for i, c in enumerate(HOSTS[host], start=1)]  # fmt: skip
        (folder / f"{host}.toml").write_text(host_config(
            host, cams, [f"tcp/10.78.{k}.1:{PORT}"],
            zenoh={"user": host, "password_file": str(folder / f"password-{host}")},
            extra={"calibration": {"file": str(folder / "calibration.toml")}, "detector": {"intra_op_threads": 1},
                   "detector.packing": {"enabled": False}},
        ), encoding="utf-8")  # fmt: skip
    all_cams = {c: h for h, cs in HOSTS.items() for c in cs}
    (folder / "solver.toml").write_text(solver_config(
        all_cams, folder / "calibration.toml", listen, zenoh={**auth, "users_file": str(folder / "users"),
                                                              "lost_after_s": 3.0,
                                                              "identities": {h: f"user:{h}" for h in HOSTS}},
        extra={"daemon": {"latency_s": 2.0, "keypoint_max_age_s": 1.0, "keypoint_max_gap_s": 5.0}},
    ), encoding="utf-8")  # fmt: skip

    def start_host(host: str) -> subprocess.Popen[bytes]:
        cmd = ["nsenter", f"--net=/proc/{holders[host].pid}/ns/net", sys.executable, "-m", "tests.netns_camera_hosts",
               "host", "--config", str(folder / f"{host}.toml"), "--cameras", ",".join(HOSTS[host])]  # fmt: skip
        out = (folder / f"{host}.log").open("ab")
        return subprocess.Popen(guarded_command(cmd), stdout=out, stderr=subprocess.STDOUT, start_new_session=True)

    log: list[str] = []
    solver = await asyncio.create_subprocess_exec(
        *guarded_command([sys.executable, "-m", "mocapd", "run", "--config", str(folder / "solver.toml"), "--verbose"]),
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.STDOUT,
    )  # fmt: skip
    assert solver.stdout is not None
    pump = asyncio.create_task(_lines(solver.stdout, log))
    hosts = {h: start_host(h) for h in HOSTS}
    result: dict[str, Any] = {}
    try:
        end = time.monotonic() + 300
        url = ws = ""
        while time.monotonic() < end and not (url and ws):
            for line in log:
                if line.startswith("ready: status http://"):
                    url = line.split()[2].rsplit("/status", 1)[0]
                if line.startswith("viewer http://"):
                    ws = line.split()[4]
            if solver.returncode is not None:
                raise RuntimeError("".join(log))
            await asyncio.sleep(0.2)
        st = await _until(url, lambda s: _people(s) == 2 and s["frame"]["missing_cameras"] == 0, 400, "both people",
                          log)  # fmt: skip
        result["before"] = {"remote_hosts": st["remote_hosts"], "people": st["frame"]["people"]}
        result["stream"] = await _read_stream(ws, 60, 10)

        hosts["hostB"].send_signal(signal.SIGUSR1)  # host B's detect-host is killed (its cameras stay up)
        t_kill = time.monotonic()
        st = await _until(url, lambda s: s["remote_hosts"]["hostB"]["lost"], 30, "host B lost", log)
        result["lost_after_s"] = round(time.monotonic() - t_kill, 2)
        st = await _until(url, lambda s: s["frame"]["missing_cameras"] == 2, 30, "host B's cameras out", log)
        result["while_lost"] = {"remote_hosts": st["remote_hosts"], "missing_cameras": st["frame"]["missing_cameras"],
                                "people": len(st["frame"]["people"])}  # fmt: skip

        hosts["hostB"].send_signal(signal.SIGUSR2)  # and started again
        st = await _until(url, lambda s: _people(s) == 2 and s["frame"]["missing_cameras"] == 0
                          and not s["remote_hosts"]["hostB"]["lost"], 400, "host B back", log)  # fmt: skip
        result["after"] = {"remote_hosts": st["remote_hosts"], "people": st["frame"]["people"],
                           "cameras": st["cameras"]}  # fmt: skip
        solver.send_signal(signal.SIGINT)
        result["exit_code"] = await asyncio.wait_for(solver.wait(), 30)
    finally:
        if solver.returncode is None:
            solver.kill()
            await solver.wait()
        await pump
        for proc in hosts.values():
            with contextlib.suppress(ProcessLookupError):
                proc.terminate()  # the host role stops its detect-host and its cameras
        for proc in hosts.values():
            try:
                proc.wait(timeout=40)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        for holder in holders.values():
            holder.terminate()
            holder.wait()
    result["output"] = log[-40:]
    result["host_logs"] = {h: (folder / f"{h}.log").read_text(errors="replace")[-2000:] for h in HOSTS}
    return result


if __name__ == "__main__":
    p = argparse.ArgumentParser()
    p.add_argument("role", choices=["main", "host"])
    p.add_argument("--folder", type=Path)
    p.add_argument("--config")
    p.add_argument("--cameras")
    args = p.parse_args()
    if args.role == "host":
        sys.exit(asyncio.run(host_role(args.config, args.cameras.split(","))))
    print(json.dumps(asyncio.run(main(args.folder))), flush=True)
