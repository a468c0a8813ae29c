"""Capture benchmark: 4 fake GigE Vision cameras (Pose2Sim multi-person demo videos) captured by mocapd.

Developer benchmark, not a ``mocapd bench`` verb (those are the benchmarks a user runs).

Runs :mod:`tools.fake_rig` (inside ``unshare -rn``) for each configuration and prints one JSON object::

    python -m tools.bench_capture [--duration 10] [--fps 30] [--configs NAME ...] [--read-hz 0]
    python -m tools.bench_capture --fps 60 --configs 544x960_BayerRG8 --read-hz 2 --duration 20   # mocapd demo's

Configurations: 640x480 and the videos' own 1088x1920 in RGB8, 1088x1920 and the demo's 544x960 in BayerRG8,
``--fps`` each. Per camera and configuration: capture-thread CPU (% of one core), frames, missing frames / resent
packets / bad buffers, and latencies (ms, median and p95):

* ``latency``: Aravis' host timestamp of the frame (wall clock when its GVSP leader packet arrived) to the frame's
  publication in the ring buffer: the transfer of the frame's packets plus mocapd's capture path;
* ``convert``: pop from the Aravis pool to publication (zero-copy view + one conversion/copy into the slot).

The fake servers run on the same cores, so the numbers include their load. ``baseline_copy_ms`` is the median
time of a plain ``np.copyto`` of one RGB frame of that size, measured in this process just before: the floor that
``convert`` is compared with on a noisy machine. For a Bayer format, ``per_frame_ms`` gives, measured the same
way, what capture did per frame before its ring turned lazy (demosaic into the slot) and what it does now (copy the
mosaic).

``capture_cpu_pct_per_camera`` is what capturing one camera costs: mocapd's capture threads plus Aravis' stream
threads, over the cameras. With ``--read-hz`` a reader thread takes every camera's newest frame that often (the
detector's stand-in): the conversions of a lazy ring run there, ``reader_thread_cpu_pct``.
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


# RGB8 at the videos' size is 6.3 MB a frame (1.5 Gbit/s per camera at 30 fps, more than GigE carries); a colour
# machine-vision camera sends Bayer (2.1 MB), demosaiced on the host. 544x960 BayerRG8 is what `mocapd demo` serves.
CONFIGS: dict[str, tuple[str | None, str]] = {
    "640x480_RGB8": ("640x480", "RGB8"),
    "1088x1920_RGB8": (None, "RGB8"),
    "1088x1920_BayerRG8": (None, "BayerRG8"),
    "544x960_BayerRG8": ("544x960", "BayerRG8"),
}


def run_config(
    size: str | None, fmt: str, fps: float, duration: float, max_frames: int, read_hz: float = 0.0, eager: bool = False
) -> dict[str, Any]:
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
            "--read-hz",
            str(read_hz),
            "--json",
            str(out),
        ]
        if size:
            cmd += ["--size", size]
        if eager:
            cmd.append("--eager")
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


def per_frame_ms(width: int, height: int, fmt_name: str, repeats: int = 50) -> dict[str, float] | None:
    """Median time per frame of a Bayer format's eager conversion (demosaic into a slot) and of its lazy capture
    (copy the mosaic into a raw slot), in ms; None for other formats."""
    import time

    import cv2
    import numpy as np

    from mocapd.io.pixels import convert_into, from_rgb, pixel_format

    fmt = pixel_format(fmt_name)
    if fmt.cv_code is None:
        return None
    rgb = np.random.default_rng(0).integers(0, 256, (height, width, 3), dtype=np.uint8)
    raw = from_rgb(rgb, fmt)
    image, slot = np.empty((height, width, 3), np.uint8), np.empty_like(raw)
    demosaic, copy = [], []
    for _ in range(repeats):  # interleaved, so that other load hits both alike
        t0 = time.perf_counter_ns()
        convert_into(fmt, raw, height, width, image)
        t1 = time.perf_counter_ns()
        np.copyto(slot, raw)
        t2 = time.perf_counter_ns()
        demosaic.append(t1 - t0)
        copy.append(t2 - t1)
    return {"eager_demosaic_ms": round(median(demosaic) / 1e6, 4), "lazy_raw_copy_ms": round(median(copy) / 1e6, 4),
            "opencv_threads": cv2.getNumThreads()}  # fmt: skip


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
    by_thread = rig["capture_process_cpu_pct_by_thread_name"]
    capture_pct = by_thread.get("mocapd_capture", 0.0) + by_thread.get("arv_gv_stream", 0.0)
    return {
        "format": rig["format"],
        "size": rig["size"],
        "fps": rig["fps"],
        "duration_s": rig["duration_s"],
        "per_camera": [{k: c.get(k) for k in ("name", *keys, "lazy_ring", "frames_read", "conversions")} for c in cams],
        "median_over_cameras": {k: median(c[k] for c in cams if c[k] is not None) for k in keys},
        "frames_expected_per_camera": round(rig["fps"] * rig["duration_s"]),
        "capture_cpu_pct_per_camera": round(capture_pct / len(cams), 2),
        "baseline_copy_ms": baseline_copy_ms(*rig["size"]),
        "per_frame_ms": per_frame_ms(rig["size"][0], rig["size"][1], rig["format"]),
        "capture_process_cpu_pct": rig["capture_process_cpu_pct"],
        "capture_process_cpu_pct_by_thread_name": by_thread,
        "read_hz": rig.get("read_hz"),
        "reader_thread_cpu_pct": rig.get("reader_thread_cpu_pct"),
        "fake_server_cpu_pct": rig["fake_server_cpu_pct"],
    }


def compare_eager(args: argparse.Namespace, configs: dict[str, tuple[str | None, str]]) -> int:
    """Lazy and eager rings, alternating run by run, per Bayer configuration: capture CPU per camera (mocapd's
    capture thread + Aravis' stream thread), the reader's CPU, frames read and conversions; medians over runs."""
    out: dict[str, Any] = {"machine": {"cpus": len(__import__("os").sched_getaffinity(0)),
                                       "loadavg_start": Path("/proc/loadavg").read_text().split()[:3]},
                           "fps": args.fps, "duration_s": args.duration, "read_hz": args.read_hz,
                           "repeats": args.repeats, "configs": {}}  # fmt: skip
    for name, (size, fmt) in configs.items():
        if not fmt.startswith("Bayer"):
            continue
        runs: dict[str, list[dict[str, Any]]] = {"lazy": [], "eager": []}
        for k in range(args.repeats):
            for mode in ("lazy", "eager") if k % 2 == 0 else ("eager", "lazy"):
                rig = run_config(size, fmt, args.fps, args.duration, args.max_frames, args.read_hz, mode == "eager")
                runs[mode].append(summarise(rig))
        res: dict[str, Any] = {}
        for mode, rs in runs.items():
            res[mode] = {
                "capture_cpu_pct_per_camera_median": median(r["capture_cpu_pct_per_camera"] for r in rs),
                "capture_cpu_pct_per_camera_runs": [r["capture_cpu_pct_per_camera"] for r in rs],
                "mocapd_capture_thread_pct_per_camera_median": median(
                    r["median_over_cameras"]["capture_thread_cpu_pct"] for r in rs
                ),
                "convert_ms_median": median(r["median_over_cameras"]["convert_ms_median"] for r in rs),
                "reader_thread_cpu_pct_median": median(r["reader_thread_cpu_pct"] or 0.0 for r in rs),
                "frames_per_camera_median": median(r["median_over_cameras"]["frames"] for r in rs),
                "frames_read_per_camera": [c["frames_read"] for c in rs[-1]["per_camera"]],
                "conversions_per_camera": [c["conversions"] for c in rs[-1]["per_camera"]],
                "missing_frames_median": median(r["median_over_cameras"]["missing_frames"] for r in rs),
            }
        res["per_frame_ms"] = runs["lazy"][-1]["per_frame_ms"]
        res["capture_cpu_ratio_lazy_over_eager"] = round(
            res["lazy"]["capture_cpu_pct_per_camera_median"] / res["eager"]["capture_cpu_pct_per_camera_median"], 3
        )
        out["configs"][name] = res
    out["machine"]["loadavg_end"] = Path("/proc/loadavg").read_text().split()[:3]
    print(json.dumps(out, indent=1))
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--duration", type=float, default=10.0, help="capture time per configuration, s")
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--max-frames", type=int, default=30, help="video frames served (looped) per camera")
    parser.add_argument("--configs", nargs="+", choices=sorted(CONFIGS), default=list(CONFIGS))
    parser.add_argument("--read-hz", type=float, default=0.0, help="a reader takes every camera's newest frame")
    parser.add_argument("--compare-eager", action="store_true",
                        help="Bayer configurations: also run them with eager rings (demosaic at capture), alternating "
                        "lazy / eager --repeats times")  # fmt: skip
    parser.add_argument("--repeats", type=int, default=1, help="runs per configuration and mode (medians reported)")
    args = parser.parse_args(argv)
    configs = {name: CONFIGS[name] for name in args.configs}
    if args.compare_eager:
        return compare_eager(args, configs)
    result: dict[str, Any] = {
        "machine": {
            "cpus": len(__import__("os").sched_getaffinity(0)),
            "loadavg_start": Path("/proc/loadavg").read_text().split()[:3],
        },
        "configs": {
            name: summarise(run_config(size, fmt, args.fps, args.duration, args.max_frames, args.read_hz))
            for name, (size, fmt) in configs.items()
        },
    }
    result["machine"]["loadavg_end"] = Path("/proc/loadavg").read_text().split()[:3]
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
