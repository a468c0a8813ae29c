"""``mocapd bench streams``: serialisation and send cost of the MVN, VMC and Rokoko UDP streams per frame.

Prints one JSON object. The workload is ``--subjects`` solved people (seeded random poses, cycled) per frame at
``--rate`` Hz, as the daemon publishes them:

- ``mvn`` / ``vmc``: ``serialise_us``: the pure encoder per frame (forward kinematics, frame conversion, bytes);
  ``publish_us``: the whole :meth:`publish` of the pose sink (slot assignment, encoding, one ``sendto`` per
  datagram on a non-blocking socket to a loopback receiver that is drained between frames); ``bytes_per_frame``
  and ``datagrams_per_frame`` (all subjects together, one destination); ``sendto_us_per_datagram``.
- ``baseline``: in the same process, the same frame as the JSON-lines pose file writes it (``json.dumps`` of the
  pose vectors rounded to 6 digits) and forward kinematics alone, so that results from different machines can
  be compared as ratios.
- ``budget_fraction``: median publish cost of the MVN and VMC streams over the frame period (1 / rate);
  ``rokoko.budget_fraction``: the Rokoko stream's alone (one LZ4 datagram per frame, every subject an actor).

Median and 95th percentile over ``--frames`` frames, microseconds. Usage:
``mocapd bench streams [--subjects 4] [--rate 60] [--frames 3000]``
"""

from __future__ import annotations

import asyncio
import json
import os
import platform
import socket
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from mocapd.core.kinematics import Kinematics
from mocapd.core.rotations import random_rotvec
from mocapd.core.skeleton import Skeleton
from mocapd.io.udp_stream import MvnUdpSink, RokokoUdpSink, VmcUdpSink
from mocapd.pipeline.scheduler import PersonPose, PoseFrame
from mocapd.protocols.mvn import MvnEncoder
from mocapd.protocols.rokoko import RokokoActor, RokokoEncoder
from mocapd.protocols.vmc import VmcEncoder


def _frames(n_subjects: int, n_frames: int, rate: float, skeleton: Skeleton) -> list[PoseFrame]:
    rng = np.random.default_rng(0)
    kin = Kinematics(skeleton)
    distinct = 120
    thetas = np.zeros((distinct, n_subjects, 66))
    thetas[..., :3] = rng.normal(size=(distinct, n_subjects, 3)) + np.array([0.0, 1.0, 0.0])
    thetas[..., 3:] = random_rotvec(rng, (distinct, n_subjects, 21), max_angle=0.8).reshape(distinct, n_subjects, 63)
    joints = kin.forward(thetas).positions
    period = round(1e9 / rate)
    out = []
    for k in range(n_frames):
        i = k % distinct
        people = [PersonPose(f"suit:s{j}", j, f"s{j}", thetas[i, j], joints[i, j], 0.9, 4, 13, 4, True)
                  for j in range(n_subjects)]  # fmt: skip
        out.append(PoseFrame(k, k * period, k * period, people, 0))
    return out


def _stats(samples_ns: list[int]) -> dict[str, float]:
    a = np.asarray(samples_ns, dtype=np.float64) / 1e3
    return {"median": round(float(np.median(a)), 2), "p95": round(float(np.percentile(a, 95)), 2)}


def _time(
    fn: Callable[[PoseFrame], Any], frames: list[PoseFrame], after: Callable[[], None] | None = None
) -> list[int]:
    out = []
    for f in frames:
        t0 = time.perf_counter_ns()
        fn(f)
        out.append(time.perf_counter_ns() - t0)
        if after is not None:
            after()
    return out


def _drain(sock: socket.socket) -> None:
    while True:
        try:
            sock.recv(65536)
        except BlockingIOError:
            return


def run(subjects: int = 4, rate: float = 60.0, n_frames: int = 3000) -> dict[str, Any]:
    skeleton = Skeleton.from_height(1.75)
    frames = _frames(subjects, n_frames, rate, skeleton)
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.setblocking(False)
    rx.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
    dest = [("127.0.0.1", rx.getsockname()[1])]
    result: dict[str, Any] = {
        "subjects": subjects, "rate_hz": rate, "frames": n_frames,
        "machine": {"python": platform.python_version(), "cpus": os.cpu_count()},
    }  # fmt: skip

    mvn_enc = MvnEncoder(skeleton)
    vmc_enc = VmcEncoder(skeleton)
    sizes: dict[str, tuple[int, int]] = {}

    def mvn_serialise(f: PoseFrame) -> None:
        d = mvn_enc.encode(f.frame, f.t_solve_ns, [(j, p.theta) for j, p in enumerate(f.people)])
        sizes["mvn"] = (sum(map(len, d)), len(d))

    def vmc_serialise(f: PoseFrame) -> None:
        d = vmc_enc.encode_many(f.t_solve_ns, np.stack([p.theta for p in f.people]), [True] * len(f.people))
        sizes["vmc"] = (sum(len(b) for per in d for b in per), sum(len(per) for per in d))

    rok_enc = RokokoEncoder(skeleton, fps=rate)

    def rokoko_serialise(f: PoseFrame) -> None:
        d = rok_enc.encode(f.frame, f.t_solve_ns, [RokokoActor(p.identity, p.theta) for p in f.people])
        sizes["rokoko"] = (len(d.data), 1)

    # VMC drives one avatar per destination: give every subject its own (all to the same receiver port is not
    # allowed by the config, so use one receiver per subject).
    vmc_rx = []
    for _ in range(subjects):
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.bind(("127.0.0.1", 0))
        s.setblocking(False)
        vmc_rx.append(s)
    mvn_sink = MvnUdpSink(skeleton, dest)
    vmc_sink = VmcUdpSink(skeleton, [("127.0.0.1", s.getsockname()[1]) for s in vmc_rx])
    rok_sink = RokokoUdpSink(skeleton, dest, fps=rate)
    for sink in (mvn_sink, vmc_sink, rok_sink):
        asyncio.run(sink.start())

    def drain_all() -> None:
        _drain(rx)
        for s in vmc_rx:
            _drain(s)

    warm = frames[:200]
    for warm_fn in (mvn_serialise, vmc_serialise, rokoko_serialise, mvn_sink.publish, vmc_sink.publish,
                    rok_sink.publish):  # fmt: skip
        _time(warm_fn, warm, drain_all)
    mvn_sink.sender.datagrams_sent = vmc_sink.sender.datagrams_sent = rok_sink.sender.datagrams_sent = 0

    kin = Kinematics(skeleton)

    def baseline_json(f: PoseFrame) -> None:
        people = [{"id": p.identity, "theta": [round(float(v), 6) for v in p.theta]} for p in f.people]
        json.dumps({"v": 1, "frame": f.frame, "t_solve_ns": f.t_solve_ns, "people": people})

    def baseline_fk(f: PoseFrame) -> None:
        kin.forward(np.stack([p.theta for p in f.people]))

    # Interleave the measurements frame by frame so that machine load hits all of them alike.
    names = ["mvn_serialise", "vmc_serialise", "rokoko_serialise", "mvn_publish", "vmc_publish", "rokoko_publish",
             "json", "fk"]  # fmt: skip
    fns: list[Callable[[PoseFrame], Any]] = [
        mvn_serialise, vmc_serialise, rokoko_serialise, mvn_sink.publish, vmc_sink.publish, rok_sink.publish,
        baseline_json, baseline_fk,
    ]  # fmt: skip
    samples: dict[str, list[int]] = {n: [] for n in names}
    for f in frames:
        for label, fn in zip(names, fns, strict=True):
            t0 = time.perf_counter_ns()
            fn(f)
            samples[label].append(time.perf_counter_ns() - t0)
            drain_all()

    # sendto alone: the same datagrams, one call each.
    payloads = mvn_enc.encode(0, 0, [(j, p.theta) for j, p in enumerate(frames[0].people)])
    send_ns = []
    for _ in range(n_frames):
        for d in payloads:
            t0 = time.perf_counter_ns()
            mvn_sink.sender.send(d, dest[0])
            send_ns.append(time.perf_counter_ns() - t0)
        _drain(rx)

    for name, sink in (("mvn", mvn_sink), ("vmc", vmc_sink), ("rokoko", rok_sink)):
        b, n = sizes[name]
        result[name] = {
            "serialise_us": _stats(samples[f"{name}_serialise"]),
            "publish_us": _stats(samples[f"{name}_publish"]),
            "bytes_per_frame": b,
            "datagrams_per_frame": n,
            "dropped": sink.status()["datagrams_dropped"],
        }
    result["mvn"]["sendto_us_per_datagram"] = _stats(send_ns)
    result["baseline"] = {"json_lines_us": _stats(samples["json"]), "forward_kinematics_us": _stats(samples["fk"])}
    both = float(np.median(samples["mvn_publish"])) + float(np.median(samples["vmc_publish"]))
    result["budget_fraction"] = round(both / (1e9 / rate), 4)
    result["rokoko"]["budget_fraction"] = round(float(np.median(samples["rokoko_publish"])) / (1e9 / rate), 4)
    for s in (rx, *vmc_rx):
        s.close()
    for sink in (mvn_sink, vmc_sink, rok_sink):
        asyncio.run(sink.aclose())
    return result
