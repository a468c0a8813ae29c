"""Capture benchmark: 4 fake GigE Vision cameras (Pose2Sim multi-person demo videos) captured by mocapd.

Runs :mod:`tools.fake_rig` (inside ``unshare -rn``) for each configuration and prints one JSON object::

    python -m tools.bench_capture [--duration 10] [--fps 30] [--repeats 1]

Configurations: 640x480 and the videos' own 1088x1920, RGB8, ``--fps`` each. Per camera and configuration:
capture-thread CPU (% of one core), frames, missing frames / resent packets / bad buffers, and latencies (ms,
median and p95):

* ``latency``: Aravis' host timestamp of the frame (wall clock when its GVSP leader packet arrived) to the frame's
  publication in the ring buffer: the transfer of the frame's packets plus mocapd's capture path;
* ``convert``: pop from the Aravis pool to publication (zero-copy view + one conversion/copy into the slot).

The fake servers run on the same cores, so the numbers include their load. ``baseline_copy_ms`` is the median
time of a plain ``np.copyto`` of one frame of that size, measured in this process just before: the floor that
``convert`` is compared with on a noisy machine.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path
from statistics import median
from typing import Any

from mocapd.io.pose2sim_demo import demo_root

ROOT = Path(__file__).resolve().parents[1]
VIDEOS = demo_root() / "Demo_MultiPerson" / "videos"


def run_config(size: str | None, fmt: str, fps: float, duration: float, max_frames: int) -> dict[str, Any]:
    videos = [str(VIDEOS / f"cam0{i}.mp4") for i in range(1, 5)]
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "rig.json"
        cmd = [
            sys.executable,
            "-m",
            "tools.fake_rig",
            "--videos",
            *videos,
            "--max-frames",
            str(max_frames),
            "--duration",
            str(duration),
            "--fps",
            str(fps),
            "--format",
            fmt,
            "--no-verify",
            "--json",
            str(out),
        ]
        if size:
            cmd += ["--size", size]
        proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, check=False, timeout=duration + 300)
        if proc.returncode != 0 or not out.exists():
            raise RuntimeError(f"fake rig failed: {proc.stderr[-2000:]}")
        result: dict[str, Any] = json.loads(out.read_text())
    return result


def baseline_copy_ms(width: int, height: int, repeats: int = 50) -> float:
    """Median time of copying one RGB frame of this size with numpy, in ms."""
    import time

    import numpy as np

    src = np.random.default_rng(0).integers(0, 256, (height, width, 3), dtype=np.uint8)
    dst = np.empty_like(src)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter_ns()
        np.copyto(dst, src)
        times.append(time.perf_counter_ns() - t0)
    return round(median(times) / 1e6, 3)


def summarise(rig: dict[str, Any]) -> dict[str, Any]:
    cams = rig["cameras"]
    keys = (
        "frames",
        "missing_frames",
        "resent_packets",
        "bad_buffers",
        "capture_thread_cpu_pct",
        "latency_ms_median",
        "latency_ms_p95",
        "convert_ms_median",
        "convert_ms_p95",
    )
    return {
        "format": rig["format"],
        "size": rig["size"],
        "fps": rig["fps"],
        "duration_s": rig["duration_s"],
        "per_camera": [{k: c[k] for k in ("name", *keys)} for c in cams],
        "median_over_cameras": {k: median(c[k] for c in cams if c[k] is not None) for k in keys},
        "frames_expected_per_camera": round(rig["fps"] * rig["duration_s"]),
        "baseline_copy_ms": baseline_copy_ms(*rig["size"]),
        "capture_process_cpu_pct": rig["capture_process_cpu_pct"],
        "capture_process_cpu_pct_by_thread_name": rig["capture_process_cpu_pct_by_thread_name"],
        "fake_server_cpu_pct": rig["fake_server_cpu_pct"],
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--duration", type=float, default=10.0, help="capture time per configuration, s")
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--max-frames", type=int, default=30, help="video frames served (looped) per camera")
    args = parser.parse_args(argv)
    # RGB8 at the demo size is 6.3 MB a frame (1.5 Gbit/s per camera at 30 fps, more than GigE carries); a colour
    # machine-vision camera sends Bayer (2.1 MB), demosaiced on the host.
    configs = {
        "640x480_RGB8": ("640x480", "RGB8"),
        "1088x1920_RGB8": (None, "RGB8"),
        "1088x1920_BayerRG8": (None, "BayerRG8"),
    }
    result: dict[str, Any] = {
        "machine": {
            "cpus": len(__import__("os").sched_getaffinity(0)),
            "loadavg_start": Path("/proc/loadavg").read_text().split()[:3],
        },
        "configs": {
            name: summarise(run_config(size, fmt, args.fps, args.duration, args.max_frames))
            for name, (size, fmt) in configs.items()
        },
    }
    result["machine"]["loadavg_end"] = Path("/proc/loadavg").read_text().split()[:3]
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
