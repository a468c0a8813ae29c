"""``mocapd bench latency --rig cameras``: the camera demo (``mocapd demo``) run for a while, measured from inside.

Runs in a private network namespace like the demo (the parent re-executes this module under ``unshare -rn``) and
prints one JSON object: end-to-end latency (the capture instant a frame is solved for -> frame published; it
includes the configured fixed latency) and per-stage latency, the detection delay (camera capture stamp ->
detections received), the output rate achieved against the configured one, detector camera-frames per second,
frames captured / skipped per camera, CPU per stage (the scheduler's own stage clocks) and per thread kind
(event loop, detector workers with their onnxruntime threads, capture threads, Aravis stream threads), the fake
camera servers' CPU, and resident memory over the run (growth after the warm-up).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import platform
import sys
import threading
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

from mocapd.service.assembly import RunOptions
from mocapd.service.config import load_config
from mocapd.service.daemon import Daemon
from mocapd.service.demo.cameras import CameraDemoOptions, in_private_netns, run_camera_demo

CLOCK_TICKS = os.sysconf("SC_CLK_TCK")
WARM_UP_S = 20.0  # model sessions, numba kernel and every ring / buffer pool touched once


def _rss_mb() -> float:
    with open("/proc/self/statm") as fh:
        pages = int(fh.read().split()[1])
    return pages * os.sysconf("SC_PAGE_SIZE") / 2**20


def _cpu_s(stat_path: str) -> float:
    try:
        fields = Path(stat_path).read_text().rsplit(")", 1)[1].split()
    except (FileNotFoundError, ProcessLookupError):
        return 0.0
    return (int(fields[11]) + int(fields[12])) / CLOCK_TICKS


def thread_cpu_by_kind(capture_tids: set[int]) -> dict[str, float]:
    """CPU seconds of this process's threads so far, by kind.

    ``detector``: the ``mocapd-detect`` workers and the onnxruntime threads they started (Linux threads inherit
    their creator's name); ``capture``: mocapd's capture threads; ``aravis``: Aravis stream threads; ``event_loop``:
    the main thread (scheduler ticks, HTTP, asyncio callbacks); ``other``.
    """
    out: dict[str, float] = {}
    main = threading.main_thread().native_id
    for task in Path(f"/proc/{os.getpid()}/task").iterdir():
        tid = int(task.name)
        try:
            name = (task / "comm").read_text().strip()
        except FileNotFoundError:
            continue
        if tid in capture_tids:
            kind = "capture"
        elif tid == main:
            kind = "event_loop"
        elif name.startswith("mocapd-detect"):
            kind = "detector"
        elif name.startswith("arv"):
            kind = "aravis"
        else:
            kind = "other"
        out[kind] = out.get(kind, 0.0) + _cpu_s(str(task / "stat"))
    return out


class Measure:
    """Samples the running demo daemon: memory each second, counters at the warm-up's end and at the end."""

    def __init__(self, seconds: float) -> None:
        self.seconds = seconds
        self.result: dict[str, Any] = {}

    def _snapshot(self, daemon: Daemon) -> dict[str, Any]:
        st = daemon.status()
        frames = [getattr(s, "frames", None) for s in daemon.rig.sources]  # DetectorKeypointSource's capture
        tids = {t for f in frames if isinstance(t := getattr(f, "thread_id", None), int)}
        servers = {f["name"]: _cpu_s(f"/proc/{f['pid']}/stat") for f in st["fake_cameras"] if f["pid"]}
        return {"t": time.monotonic(), "status": st, "threads": thread_cpu_by_kind(tids),
                "process_cpu": time.process_time(), "servers": servers}  # fmt: skip

    async def __call__(self, daemon: Daemon) -> None:
        rss: list[tuple[float, float]] = []
        t0 = time.monotonic()
        percentiles: list[dict[str, Any]] = []
        a: dict[str, Any] | None = None
        while (now := time.monotonic()) - t0 < WARM_UP_S + self.seconds:
            await asyncio.sleep(1.0)
            rss.append((round(now - t0, 1), round(_rss_mb(), 1)))
            if a is None and now - t0 >= WARM_UP_S:
                a = self._snapshot(daemon)
            if a is not None and len(rss) % 30 == 0:
                e2e = daemon.status()["latency_ms"]["end_to_end"]
                percentiles.append({"t_s": round(now - t0, 1), "p50": e2e["p50"], "p95": e2e["p95"]})
        assert a is not None
        b = self._snapshot(daemon)
        self.result = summarize(a, b, rss, percentiles)


def summarize(
    a: dict[str, Any], b: dict[str, Any], rss: list[tuple[float, float]], percentiles: list[dict[str, Any]]
) -> dict[str, Any]:
    """The JSON report from two snapshots (end of warm-up, end of run)."""
    wall = b["t"] - a["t"]
    sa, sb = a["status"], b["status"]
    frames = sb["output"]["frames"] - sa["output"]["frames"]
    cams = {}
    for ca, cb in zip(sa["cameras"], sb["cameras"], strict=True):
        cams[cb["name"]] = {
            "captured_fps": round((cb["captured"] - ca["captured"]) / wall, 2),
            "detected_fps": round((cb["detected"] - ca["detected"]) / wall, 2),
            "skipped": cb["skipped"] - ca["skipped"],
            "transfer_ms_mean": cb["transfer_ms_mean"],
            "missing_frames": cb["capture"]["missing_frames"], "bad_buffers": cb["capture"]["bad_buffers"],
            "failures": cb["capture"]["failures"],
        }  # fmt: skip
    detected = sum((cb["detected"] - ca["detected"]) for ca, cb in zip(sa["cameras"], sb["cameras"], strict=True))
    stage_cpu = {k: round(v - sa["cpu_s"].get(k, 0.0), 2) for k, v in sb["cpu_s"].items()}
    after = [m for t, m in rss if t >= WARM_UP_S]
    return {
        "duration_s": round(wall, 1),
        "configured": {"output_rate_hz": sb["output"]["configured_hz"], "latency_ms": 1e3 * sb["output"]["latency_s"]},
        "output": {"frames": frames, "achieved_hz": round(frames / wall, 2),
                   "missed_ticks": sb["output"]["missed_ticks"] - sa["output"]["missed_ticks"]},
        "end_to_end_ms_last_window": sb["latency_ms"]["end_to_end"],
        "end_to_end_ms_every_30s": percentiles,
        "detection_delay_ms_last_window": sb["latency_ms"]["detect"],
        "stage_latency_ms_last_window": {k: v for k, v in sb["latency_ms"].items() if k not in ("end_to_end",)},
        "detector_camera_frames_per_s": round(detected / wall, 2),
        "latency_at_end": sb["output"].get("latency"),
        "detection_group_at_end": sb["cameras"][0].get("packing"),
        "cameras": cams,
        "people": {"person_solves": sb["counters"]["person_solves"] - sa["counters"]["person_solves"],
                   "person_solves_per_frame": round((sb["counters"]["person_solves"] - sa["counters"]["person_solves"])
                                                    / max(frames, 1), 3),
                   "subjects_at_end": len(sb["subjects"]["subjects"])},
        "cpu_fraction_of_one_core": {
            "scheduler_stages": {k: round(v / wall, 3) for k, v in stage_cpu.items()},
            "threads": {k: round((v - a["threads"].get(k, 0.0)) / wall, 3) for k, v in b["threads"].items()},
            "daemon_process": round((b["process_cpu"] - a["process_cpu"]) / wall, 3),
            "fake_camera_servers": {k: round((v - a["servers"].get(k, 0.0)) / wall, 3)
                                    for k, v in b["servers"].items()},
        },
        "stage_cpu_ms_per_frame": {k: round(1e3 * v / max(frames, 1), 3) for k, v in stage_cpu.items()},
        "memory_mb": {"rss_samples": rss[:: max(1, len(rss) // 12)], "after_warm_up_first": after[0] if after else None,
                      "after_warm_up_last": after[-1] if after else None,
                      "growth_after_warm_up": round(after[-1] - after[0], 1) if len(after) > 1 else None,
                      "warm_up_s": WARM_UP_S},
        "task_failures": {k: v["failures"] for k, v in sb["tasks"].items()},
    }  # fmt: skip


def child_main(argv: list[str] | None = None) -> int:
    """Inside the private network namespace: run the demo, measure, print the JSON report."""
    p = argparse.ArgumentParser()
    p.add_argument("--seconds", type=float, default=120.0)
    p.add_argument("--options", default="{}")
    args = p.parse_args(argv)
    opts = CameraDemoOptions(**json.loads(args.options))
    config = load_config()
    # Inside the namespace: any free port (nothing outside it reads them).
    config = config.model_copy(update={"daemon": config.daemon.model_copy(update={"http_port": 0}),
                                       "websocket": config.websocket.model_copy(update={"port": 0})})  # fmt: skip
    m = config.detector.model
    load0 = os.getloadavg()
    measure = Measure(args.seconds)
    code = asyncio.run(run_camera_demo(config, opts, RunOptions(), monitor=measure))
    report = {
        "rig": {"cameras": 4, "source": f"Pose2Sim {opts.demo} videos, fake GigE Vision cameras in a private netns",
                "image": [round(1088 * opts.scale), round(1920 * opts.scale)], "pixel_format": opts.pixel_format,
                "camera_fps": 60, "detector": f"{m.input_width}x{m.input_height} yolo11n-pose, "
                f"{config.detector.workers} worker(s), providers {list(config.detector.providers)}"},
        **measure.result,
        "machine": {"cpus": os.cpu_count(), "loadavg_at_start": [round(x, 2) for x in load0],
                    "loadavg_at_end": [round(x, 2) for x in os.getloadavg()], "python": platform.python_version()},
    }  # fmt: skip
    print(json.dumps(report, indent=2), flush=True)
    return code


def run(seconds: float, opts: CameraDemoOptions) -> int:
    """``mocapd bench latency --rig cameras``: re-run this module in a private network namespace."""
    return in_private_netns(
        "mocapd.service.bench.cameras", ["--seconds", str(seconds), "--options", json.dumps(asdict(opts))]
    )


if __name__ == "__main__":
    sys.exit(child_main())
