"""Camera hosts over Zenoh: what the hop adds, and what a remote camera costs the solver host.

Developer benchmark, not a ``mocapd bench`` verb (those are the benchmarks a user runs). Prints one JSON object::

    python -m tools.bench_zenoh [--seconds 20] [--warmup 8] [--people 2] [--rate 30]

Two runs of the same 8 cameras of a simulated ring rig (detector output computed from recorded motion, so no
detector competes for the 2 cores; ``[synthetic] detection_delay_s`` = 50 ms stands for the detector):

* ``local``: ``mocapd run`` with the 8 cameras as ``source = "synthetic"`` in its own process;
* ``remote``: the same 8 cameras on 2 camera hosts (this module's ``host`` role: the simulated rig's cameras 0-3 and
  4-7, one world, one epoch, published by :func:`mocapd.service.detect_host.serve`, the code of
  ``mocapd detect-host``), and ``mocapd run`` with 8 ``source = "zenoh"`` cameras; Zenoh over TCP on loopback.

Per run, over ``--seconds`` after ``--warmup``: the solver host's CPU (process user+system time / wall time, in
cores, and per camera), the camera hosts' CPU, detections delivered per second (throughput), the solver's
``detect`` latency (capture -> detections in the timeline on the solver host's clock, p50/p95 from /status) and,
remote, the hop alone (sent by the camera host -> received, through the estimated clock offset) and the clock
offset estimate. ``added_latency_ms`` = remote - local ``detect`` latency (same machine, same process layout).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path
from typing import Any

import numpy as np
import psutil

N_CAMERAS = 8
HOSTS = {"hostA": [0, 1, 2, 3], "hostB": [4, 5, 6, 7]}
NAMES = [f"cam{i}" for i in range(N_CAMERAS)]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


# ------------------------------------------------------------------------------------------------ camera host role
async def host_role(config: str, cameras: list[int], epoch_ns: int, people: int, rate: float) -> None:
    from mocapd.service.config import load_config
    from mocapd.service.detect_host import serve
    from mocapd.sim.world import SyntheticKeypointSource, SyntheticWorld

    cfg = load_config(config)
    world = SyntheticWorld(N_CAMERAS, people, 0, seed=0, camera_names=NAMES)
    sources = [SyntheticKeypointSource(world, c, epoch_ns=epoch_ns, rate_hz=rate, delay_s=0.05, noise_px=1.0)
               for c in cameras]  # fmt: skip
    sizes = [(world.cameras[c].width, world.cameras[c].height) for c in cameras]
    stop = asyncio.Event()
    asyncio.get_running_loop().add_signal_handler(signal.SIGTERM, stop.set)
    await serve(cfg, list(sources), sizes, stop=stop)


# ------------------------------------------------------------------------------------------------ measurement
def _status(url: str) -> dict[str, Any]:
    with urllib.request.urlopen(f"{url}/status", timeout=60) as r:  # a starved loaded daemon answers late
        out: dict[str, Any] = json.loads(r.read())
        return out


class Solver:
    def __init__(self, config: Path) -> None:
        self.proc = subprocess.Popen([sys.executable, "-m", "mocapd", "run", "--config", str(config)],
                                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)  # fmt: skip
        assert self.proc.stdout is not None
        self.url = ""
        end = time.monotonic() + 300
        while time.monotonic() < end:
            line = self.proc.stdout.readline()
            if not line and self.proc.poll() is not None:
                raise RuntimeError("solver exited")
            if line.startswith("ready: status http://"):
                self.url = line.split()[2].rsplit("/status", 1)[0]
                break
        if not self.url:
            raise RuntimeError("solver not ready")

    def stop(self) -> None:
        self.proc.send_signal(signal.SIGINT)
        try:
            self.proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


def _cpu(pids: list[int]) -> float:
    total = 0.0
    for pid in pids:
        p = psutil.Process(pid)
        for proc in [p, *p.children(recursive=True)]:
            t = proc.cpu_times()
            total += t.user + t.system
    return total


def _measure(
    solver: Solver, hosts: list[int], seconds: float, warmup: float, n_cameras: int = N_CAMERAS
) -> dict[str, Any]:
    time.sleep(warmup)
    s0 = _status(solver.url)
    c0, h0, t0 = _cpu([solver.proc.pid]), _cpu(hosts), time.monotonic()
    time.sleep(seconds)
    s1 = _status(solver.url)
    c1, h1, t1 = _cpu([solver.proc.pid]), _cpu(hosts), time.monotonic()
    wall = t1 - t0

    def delivered(s: dict[str, Any]) -> int:  # a remote camera's delivered; a local camera's timeline frames
        return sum(int(c.get("delivered", c.get("frames", 0))) for c in s["cameras"])

    frames = s1["output"]["frames"] - s0["output"]["frames"]
    dets = delivered(s1) - delivered(s0)
    out: dict[str, Any] = {
        "solver_cpu_cores": round((c1 - c0) / wall, 3),
        # The two runs need not reach the same output rate on a loaded machine: CPU per unit of work compares them.
        "solver_cpu_ms_per_output_frame": round(1e3 * (c1 - c0) / max(frames, 1), 3),
        "solver_cpu_ms_per_detection": round(1e3 * (c1 - c0) / max(dets, 1), 3),
        "solver_cpu_per_camera_cores": round((c1 - c0) / wall / n_cameras, 4),
        "detections_per_s": round(dets / wall, 1),
        "stage_cpu_ms_per_output_frame": {
            k: round(1e3 * (s1["cpu_s"][k] - s0["cpu_s"][k]) / max(frames, 1), 3) for k in ("sample", "sort", "solve")
        },
        "detect_latency_ms": {k: s1["latency_ms"]["detect"][k] for k in ("p50", "p95")},
        "solve_ms": {k: s1["latency_ms"]["solve"][k] for k in ("p50", "p95")},
        "output_hz": s1["output"]["achieved_hz"],
        "people": len((s1.get("frame") or {}).get("people", [])),
        "missed_ticks": s1["output"]["missed_ticks"] - s0["output"]["missed_ticks"],
    }
    if hosts:
        out["hosts_cpu_cores"] = round((h1 - h0) / wall, 3)
        hops = [c["hop_ms"] for c in s1["cameras"]]
        out["hop_ms"] = {k: round(float(np.median([h[k] for h in hops])), 3) for k in ("p50", "p95")}
        out["dropped"] = {c["name"]: c["dropped"] for c in s1["cameras"] if c["dropped"]}
        out["clock"] = {h: {k: v[k] for k in ("clock_offset_ms", "clock_uncertainty_ms", "clock_rtt_ms")}
                        for h, v in s1["remote_hosts"].items()}  # fmt: skip
    return out


def codec_cost(people: int, repeats: int = 2000) -> dict[str, Any]:
    """Median encode and decode time of one camera frame's ``det`` message (COCO-17, ``people`` people)."""
    from mocapd.core.sorting import Detections2D
    from mocapd.protocols.remote import Decoder, encode_detections

    rng = np.random.default_rng(0)
    dets = Detections2D(rng.uniform(0, 500, (people, 17, 2)), rng.uniform(0, 1, (people, 17)))
    data = encode_detections("hostA", "cam0", 1, 1, 1, 1, 640, 480, dets)
    decoder = Decoder()
    enc, dec = [], []
    for _ in range(repeats):
        t0 = time.perf_counter_ns()
        encode_detections("hostA", "cam0", 1, 1, 1, 1, 640, 480, dets)
        t1 = time.perf_counter_ns()
        decoder.decode(data)
        dec.append(time.perf_counter_ns() - t1)
        enc.append(t1 - t0)
    return {"message_bytes": len(data), "encode_us_median": round(float(np.median(enc)) / 1e3, 1),
            "decode_us_median": round(float(np.median(dec)) / 1e3, 1)}  # fmt: skip


def run(seconds: float, warmup: float, people: int, rate: float) -> dict[str, Any]:
    from mocapd.sim.camera_hosts import host_config, solver_config, toml_tables, write_ring_calibration

    daemon = {"http_port": 0, "latency_s": 0.3, "keypoint_max_age_s": 0.2}
    result: dict[str, Any] = {"cameras": N_CAMERAS, "hosts": len(HOSTS), "people": people, "camera_rate_hz": rate,
                              "cpu_count": psutil.cpu_count(), "seconds": seconds,
                              "codec": codec_cost(people)}  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        local = folder / "local.toml"
        local.write_text(toml_tables(
            {"daemon": daemon, "websocket": {"port": 0},
             "synthetic": {"people": people, "suits": 0, "camera_rate_hz": rate, "detection_delay_s": 0.05}},
            [{"name": n, "source": "synthetic"} for n in NAMES],
        ), encoding="utf-8")  # fmt: skip
        solver = Solver(local)
        try:
            result["local"] = _measure(solver, [], seconds, warmup)
        finally:
            solver.stop()

        endpoint = f"tcp/127.0.0.1:{_free_port()}"
        write_ring_calibration(NAMES, folder / "calibration.toml")
        remote = folder / "remote.toml"
        cameras = {NAMES[c]: h for h, cs in HOSTS.items() for c in cs}
        remote.write_text(solver_config(cameras, folder / "calibration.toml", [endpoint], extra={"daemon": daemon}),
                          encoding="utf-8")  # fmt: skip
        solver = Solver(remote)
        epoch = time.monotonic_ns()
        hosts = []
        try:
            for h, cams in HOSTS.items():
                cfg = folder / f"{h}.toml"
                cfg.write_text(host_config(h, [], [endpoint]), encoding="utf-8")
                hosts.append(subprocess.Popen([sys.executable, "-m", "tools.bench_zenoh", "--role", "host", "--config",
                                               str(cfg), "--host-cameras", ",".join(map(str, cams)), "--epoch-ns",
                                               str(epoch), "--people", str(people), "--rate", str(rate)]))  # fmt: skip
            result["remote"] = _measure(solver, [p.pid for p in hosts], seconds, warmup)
        finally:
            solver.stop()
            for p in hosts:
                p.terminate()
            for p in hosts:
                p.wait(timeout=30)
    lo, re_ = result["local"], result["remote"]
    result["added_latency_ms"] = {k: round(re_["detect_latency_ms"][k] - lo["detect_latency_ms"][k], 3)
                                  for k in ("p50", "p95")}  # fmt: skip
    result["solver_cpu_per_camera_remote_minus_local_cores"] = round(
        re_["solver_cpu_per_camera_cores"] - lo["solver_cpu_per_camera_cores"], 4
    )
    result["load_average_1_5_15"] = [round(v, 2) for v in psutil.getloadavg()]
    return result


def run_detector(seconds: float, warmup: float, cameras: int) -> dict[str, Any]:
    """The same ``cameras`` Pose2Sim multi-person videos with the real detector: as ``video`` cameras of
    ``mocapd run`` (local), and on one ``mocapd detect-host`` feeding ``mocapd run`` with ``zenoh`` cameras."""
    from mocapd.io.pose2sim_demo import CAMERAS, demo_video
    from mocapd.service.cli import main as cli
    from mocapd.sim.camera_hosts import host_config, solver_config, toml_tables
    from tests.test_run_rig import _calib

    names = list(CAMERAS[:cameras])
    daemon = {"http_port": 0, "latency_s": 2.0, "keypoint_max_age_s": 1.0, "keypoint_max_gap_s": 5.0}
    detector = {"intra_op_threads": 1}
    result: dict[str, Any] = {"cameras": cameras, "seconds": seconds, "video": "Pose2Sim Demo_MultiPerson 1088x1920"}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        calibration = folder / "calibration.toml"
        assert cli(["calibrate", "convert", str(_calib()), str(calibration)]) == 0
        cams = [{"name": n, "source": "video", "path": str(demo_video("Demo_MultiPerson", n))} for n in names]
        local = folder / "local.toml"
        tables: dict[str, dict[str, Any]] = {
            "daemon": daemon, "websocket": {"port": 0}, "calibration": {"file": str(calibration)},
            "detector": detector, "detector.packing": {"enabled": False},
        }  # fmt: skip
        local.write_text(toml_tables(tables, cams), encoding="utf-8")
        solver = Solver(local)
        try:
            result["local"] = _measure(solver, [], seconds, warmup, n_cameras=cameras)
        finally:
            solver.stop()
        endpoint = f"tcp/127.0.0.1:{_free_port()}"
        remote = folder / "remote.toml"
        remote.write_text(solver_config(dict.fromkeys(names, "hostA"), calibration, [endpoint],
                                        extra={"daemon": daemon}), encoding="utf-8")  # fmt: skip
        host_cfg = folder / "hostA.toml"
        host_cfg.write_text(host_config("hostA", cams, [endpoint], extra={
            "calibration": {"file": str(calibration)}, "detector": detector, "detector.packing": {"enabled": False}}),
            encoding="utf-8")  # fmt: skip
        solver = Solver(remote)
        host = subprocess.Popen([sys.executable, "-m", "mocapd", "detect-host", "--config", str(host_cfg)],
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
        try:
            result["remote"] = _measure(solver, [host.pid], seconds, warmup, n_cameras=cameras)
        finally:
            solver.stop()
            host.send_signal(signal.SIGINT)
            host.wait(timeout=30)
    return result


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=20.0)
    p.add_argument("--warmup", type=float, default=8.0)
    p.add_argument("--people", type=int, default=2)
    p.add_argument("--rate", type=float, default=30.0, help="camera frame rate, Hz")
    p.add_argument("--role", choices=["bench", "host"], default="bench")
    p.add_argument("--detector", type=int, default=0, metavar="N",
                   help="instead: N Pose2Sim videos with the real detector, local vs on one detect-host")  # fmt: skip
    p.add_argument("--config")
    p.add_argument("--host-cameras")
    p.add_argument("--epoch-ns", type=int)
    args = p.parse_args()
    if args.role == "host":
        cams = [int(c) for c in args.host_cameras.split(",")]
        asyncio.run(host_role(args.config, cams, args.epoch_ns, args.people, args.rate))
        return
    if args.detector:
        print(json.dumps(run_detector(args.seconds, args.warmup, args.detector), indent=2))
        return
    print(json.dumps(run(args.seconds, args.warmup, args.people, args.rate), indent=2))


if __name__ == "__main__":
    main()
