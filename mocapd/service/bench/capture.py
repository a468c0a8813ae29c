"""``mocapd bench capture``: 4 fake GigE Vision cameras (Pose2Sim multi-person demo videos) captured by mocapd.

Runs the fake rig (:mod:`mocapd.sim.fake_rig`, inside ``unshare -rn``) for each configuration and prints one JSON
object (its ``"machine"`` entry names the CPU, :func:`mocapd.service.bench.machine.emit`) and a summary line::

    mocapd bench capture [--duration 10] [--fps 30] [--configs NAME ...] [--read-hz 0]
    mocapd bench capture --fps 60 --configs 544x960_BayerRG8 --read-hz 2 --duration 20   # what mocapd demo serves

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
detector's stand-in): the conversions of a lazy ring run there, ``reader_thread_cpu_pct``. ``--compare-eager``
runs the Bayer configurations with lazy and eager rings alternately (``--repeats`` times each).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from statistics import median
from typing import Any

import numpy as np

from mocapd.errors import DeviceError
from mocapd.io.pose2sim_demo import demo_video

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
    """One run of the fake rig (:mod:`mocapd.sim.fake_rig`, in its own process and network namespace): its JSON."""
    videos = [str(demo_video("Demo_MultiPerson", f"cam0{i}")) for i in range(1, 5)]
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "rig.json"
        cmd = [
            sys.executable,
            "-m",
            "mocapd.sim.fake_rig",
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
        proc = subprocess.run(cmd, capture_output=True, text=True, check=False, timeout=duration + 300)
        if proc.returncode != 0 or not out.exists():
            # The cause in one line: no Aravis, no unshare, a video that does not decode.
            last = (proc.stderr.strip().splitlines() or ["no output"])[-1]
            raise DeviceError(f"fake rig ({fmt}, {size or 'full size'}) failed with status {proc.returncode}: {last}")
        result: dict[str, Any] = json.loads(out.read_text())
    return result


def baseline_copy_ms(width: int, height: int, repeats: int = 50) -> float:
    """Median time of copying one RGB frame of this size with numpy, in ms."""
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
    import cv2

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


def _loadavg() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


def compare_eager(args: argparse.Namespace, configs: dict[str, tuple[str | None, str]]) -> dict[str, Any]:
    """Lazy and eager rings, alternating run by run, per Bayer configuration: capture CPU per camera (mocapd's
    capture thread + Aravis' stream thread), the reader's CPU, frames read and conversions; medians over runs."""
    out: dict[str, Any] = {"machine": {"loadavg_start": _loadavg()}, "fps": args.fps, "duration_s": args.duration,
                           "read_hz": args.read_hz, "repeats": args.repeats, "configs": {}}  # fmt: skip
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
        eager = res["eager"]["capture_cpu_pct_per_camera_median"]
        res["capture_cpu_ratio_lazy_over_eager"] = (
            round(res["lazy"]["capture_cpu_pct_per_camera_median"] / eager, 3) if eager else None
        )
        out["configs"][name] = res
    out["machine"]["loadavg_end"] = _loadavg()
    return out


def run(args: argparse.Namespace) -> dict[str, Any]:
    """``mocapd bench capture``'s report (without its CPU, which :func:`~mocapd.service.bench.machine.emit` adds).

    Raises
    ------
    DeviceError
        A fake rig run failed (no Aravis, no ``unshare``, a video that does not decode): its last line.
    """
    configs = {name: CONFIGS[name] for name in args.configs}
    if args.compare_eager:
        return compare_eager(args, configs)
    result: dict[str, Any] = {
        "machine": {"loadavg_start": _loadavg()},
        "cameras": 4,
        "configs": {
            name: summarise(run_config(size, fmt, args.fps, args.duration, args.max_frames, args.read_hz))
            for name, (size, fmt) in configs.items()
        },
    }
    result["machine"]["loadavg_end"] = _loadavg()
    return result


def summary_line(report: dict[str, Any]) -> str:
    """The human summary: per configuration, the capture CPU per camera, frames and the latency's median."""
    parts = []
    for name, r in report["configs"].items():
        if "lazy" in r:  # --compare-eager
            parts.append(f"{name} capture {r['lazy']['capture_cpu_pct_per_camera_median']} % of a core per camera "
                         f"lazy, {r['eager']['capture_cpu_pct_per_camera_median']} % eager")  # fmt: skip
            continue
        med, expected = r["median_over_cameras"], r["frames_expected_per_camera"]
        parts.append(f"{name} {r['capture_cpu_pct_per_camera']} % of a core per camera, {med['frames']}/{expected} "
                     f"frames, latency p50 {med['latency_ms_median']} ms")  # fmt: skip
    return "bench capture (4 fake GigE cameras): " + "; ".join(parts or ["no Bayer configuration to compare"])


def arguments(ap: argparse.ArgumentParser) -> None:
    """The options of ``mocapd bench capture``."""
    ap.add_argument("--duration", type=float, default=10.0, help="capture time per configuration, s (default 10)")
    ap.add_argument("--fps", type=float, default=30.0, help="camera frame rate, Hz (default 30)")
    ap.add_argument("--max-frames", type=int, default=30, help="video frames served (looped) per camera")
    ap.add_argument("--configs", nargs="+", choices=sorted(CONFIGS), default=list(CONFIGS),
                    help="size and pixel format configurations (default: all)")  # fmt: skip
    ap.add_argument("--read-hz", type=float, default=0.0, help="a reader takes every camera's newest frame (0: none)")
    ap.add_argument("--compare-eager", action="store_true",
                    help="Bayer configurations: run them with lazy and eager rings (demosaic at capture), "
                    "alternating --repeats times")  # fmt: skip
    ap.add_argument("--repeats", type=int, default=1, help="runs per configuration and mode (medians reported)")
