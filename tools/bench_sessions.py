"""The detector's throughput against cores, sessions in flight and threads per session: the curve of issue 31.

Developer benchmark, not a ``mocapd bench`` verb (those are the benchmarks a user runs).

The daemon's packed group (:class:`~mocapd.pipeline.packed_source.PackedDetectionGroup`, the shipped ``[detector]``
with ``enabled = "auto"``: packed or whole-frame passes by cost) runs its real worker loops, one per inference
session, on the four ``Demo_MultiPerson`` cameras at the demo's 544x960, cameras that always have a new frame (60
fps cameras, a detector far slower). For each number of cores (``--cores``; each in a child process pinned with
``taskset -c 0-(n-1)``, so that onnxruntime and ``[detector] workers = "auto"`` see n cores) and each (sessions,
intra-op threads per session), it measures camera frames detected per second of wall time, the process's CPU in
cores, and frames per CPU-second. Configurations alternate in blocks inside each child, so that a shared
machine's load weighs on all of them alike. Prints one JSON object; the rows marked ``auto`` are what
``workers = "auto"`` and ``intra_op_threads = 0`` pick on that many cores.

    .venv/bin/python tools/bench_sessions.py --cores 1 2 --seconds 8 --blocks 3
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from mocapd.io.pose2sim_demo import CAMERAS, demo_video
from mocapd.pipeline.detection_mode import ModeChooser
from mocapd.pipeline.detector_config import DetectorConfig
from mocapd.pipeline.detector_pool import detector_executor, process_cores
from mocapd.pipeline.frame_ring import FrameRef
from mocapd.pipeline.packed_source import PackedDetectionGroup, Session
from mocapd.pipeline.packing import PackedDetector, detectors_from_config

SIZE = (544, 960)


class LoopingCamera:
    """A camera that always has a new frame: the demo video's frames in turn (RGB, as rings hold them)."""

    def __init__(self, camera: int, frames: list[NDArray[np.uint8]]) -> None:
        self.camera = camera
        self.frames = frames
        self.seq = 0

    def has_new_frame(self) -> bool:
        return True

    def take_newest(self) -> tuple[FrameRef, NDArray[np.uint8]]:
        now = time.perf_counter_ns()
        self.seq += 1
        return FrameRef(f"cam{self.camera}", self.seq, now, now, self.seq), self.frames[self.seq % len(self.frames)]


def demo_frames(n: int) -> list[list[NDArray[np.uint8]]]:
    out: list[list[NDArray[np.uint8]]] = []
    for name in CAMERAS:
        cap = cv2.VideoCapture(str(demo_video("Demo_MultiPerson", name)))
        frames: list[NDArray[np.uint8]] = []
        for _ in range(n):
            ok, img = cap.read()
            if not ok:
                break
            frames.append(np.asarray(cv2.cvtColor(cv2.resize(img, SIZE), cv2.COLOR_BGR2RGB), np.uint8))
        cap.release()
        out.append(frames)
    return out


class Rig:
    """One configuration's sessions and ROI state, kept across its blocks."""

    def __init__(self, sessions: int, threads: int, frames: list[list[NDArray[np.uint8]]], precision: str) -> None:
        self.sessions, self.threads = sessions, threads
        cfg = DetectorConfig(intra_op_threads=threads, workers=sessions, precision=precision)
        sizes = [SIZE] * len(frames)
        with detector_executor(sessions) as named:  # onnxruntime's threads named like the daemon's
            pairs = [named.submit(detectors_from_config, cfg, sizes).result() for _ in range(sessions)]
        self.packer = PackedDetector(pairs[0][0], sizes, cfg.packing, canvas_detector=pairs[0][1])
        self.session_list = [Session(w, c) for w, c in pairs]
        self.chooser = ModeChooser(first="whole")
        self.frames = frames
        self.totals = {"frames": 0, "wall_s": 0.0, "cpu_s": 0.0, "passes": 0, "whole_passes": 0, "in_flight_max": 0}

    def block(self, seconds: float, measure: bool) -> None:
        """Run the group's workers for ``seconds`` of wall time (counted when ``measure``)."""
        group = PackedDetectionGroup(self.packer, detector_executor(self.sessions), chooser=self.chooser,
                                     sessions=self.session_list)  # fmt: skip
        for cam, f in enumerate(self.frames):
            group.add(LoopingCamera(cam, f))  # type: ignore[arg-type]  # has_new_frame / take_newest only
        frames0 = self.packer.stats.camera_frames
        t0, c0 = time.perf_counter(), time.process_time()
        group._workers = [group.executor.submit(group._work, i) for i in range(self.sessions)]  # no event loop
        time.sleep(seconds)
        with group._cond:  # stop after the passes in flight (close() would also abort the sessions for good)
            group._stop = True
            group._cond.notify_all()
        for w in group._workers:
            w.result()
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        group.executor.shutdown()
        if measure:
            t = self.totals
            t["frames"] += self.packer.stats.camera_frames - frames0 + group.whole_passes
            t["wall_s"] += wall
            t["cpu_s"] += cpu
            t["passes"] += group.passes
            t["whole_passes"] += group.whole_passes
            t["in_flight_max"] = max(t["in_flight_max"], group.in_flight_max)

    def row(self, cores: int) -> dict[str, Any]:
        t = self.totals
        auto = DetectorConfig().sessions(cores, len(self.frames))
        return {
            "cores": cores, "sessions": self.sessions, "threads_per_session": self.threads,
            "auto": (self.sessions, self.threads) == auto,
            "camera_frames_per_s": round(t["frames"] / t["wall_s"], 2) if t["wall_s"] else None,
            "cpu_cores": round(t["cpu_s"] / t["wall_s"], 2) if t["wall_s"] else None,
            "camera_frames_per_cpu_s": round(t["frames"] / t["cpu_s"], 2) if t["cpu_s"] else None,
            "passes": t["passes"], "whole_passes": t["whole_passes"], "passes_in_flight_max": t["in_flight_max"],
            "wall_s": round(t["wall_s"], 1),
        }  # fmt: skip


def configs(cores: int, sessions: list[int], threads: list[int]) -> list[tuple[int, int]]:
    """(sessions, threads) pairs worth running on ``cores`` (no more threads than 2x the cores), with auto's."""
    out = [(s, t) for s in sessions for t in threads if s * t <= 2 * cores]
    auto = DetectorConfig().sessions(cores, len(CAMERAS))
    return out if auto in out else [*out, auto]


def child(args: argparse.Namespace) -> None:
    cores = process_cores()
    cv2.setNumThreads(1)
    frames = demo_frames(12)
    rigs = [Rig(s, t, frames, args.precision) for s, t in configs(cores, args.sessions, args.threads)]
    for rig in rigs:
        rig.block(2.0, measure=False)  # sessions warm, ROIs on the people
    for b in range(args.blocks):
        for rig in rigs if b % 2 == 0 else reversed(rigs):
            rig.block(args.seconds, measure=True)
    print(json.dumps({"cores": cores, "rows": [r.row(cores) for r in rigs]}), flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cores", type=int, nargs="+", default=[1, 2], help="core counts to pin the runs to")
    ap.add_argument("--sessions", type=int, nargs="+", default=[1, 2, 4])
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="intra-op threads per session")
    ap.add_argument("--seconds", type=float, default=8.0, help="wall time of one block")
    ap.add_argument("--blocks", type=int, default=3, help="blocks of each configuration (alternating)")
    ap.add_argument("--precision", default="auto", choices=["auto", "fp32", "int8"])
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(args)
        return
    available = process_cores()
    load0 = os.getloadavg()
    results = []
    for n in args.cores:
        if n > available:
            results.append({"cores": n, "skipped": f"this machine lets the process use {available} cores"})
            continue
        cmd = [sys.executable, __file__, "--child", "--seconds", str(args.seconds), "--blocks", str(args.blocks),
               "--precision", args.precision, "--sessions", *map(str, args.sessions),
               "--threads", *map(str, args.threads)]  # fmt: skip
        if shutil.which("taskset"):
            cmd = ["taskset", "-c", f"0-{n - 1}", *cmd]
        else:  # the child pins itself through the same affinity call
            cmd = [sys.executable, "-c", f"import os, runpy, sys; os.sched_setaffinity(0, range({n})); "
                   f"sys.argv = {cmd[1:]!r}; runpy.run_path({__file__!r}, run_name='__main__')"]  # fmt: skip
        out = subprocess.run(cmd, capture_output=True, text=True, check=True)
        results.append(json.loads(out.stdout.strip().splitlines()[-1]))
    report = {
        "rig": f"4 x Demo_MultiPerson {SIZE[0]}x{SIZE[1]}, cameras always with a new frame, yolo11n-pose, "
               f"[detector.packing] enabled = auto, precision {args.precision}",
        "seconds_per_block": args.seconds, "blocks": args.blocks,
        "curve": [row for r in results for row in r.get("rows", [r])],
        "machine": {"cpus": os.cpu_count(), "process_cores": available,
                    "loadavg_start": [round(x, 2) for x in load0],
                    "loadavg_end": [round(x, 2) for x in os.getloadavg()]},
    }  # fmt: skip
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
