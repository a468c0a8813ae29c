"""``mocapd bench latency --rig cameras``: the camera demo (``mocapd demo``) run for a while, measured from inside.

Runs in a private network namespace like the demo (the parent re-executes this module under ``unshare -rn``) and
prints one JSON object: end-to-end latency (the capture instant a frame is solved for -> frame published; it
includes the configured fixed latency) and per-stage latency, the detection delay (camera capture stamp ->
detections received), the output rate achieved against the configured one, detector camera-frames per second,
frames captured / skipped per camera, CPU per stage (the scheduler's own stage clocks) and per thread kind
(event loop, detector workers with their onnxruntime threads, capture threads, Aravis stream threads), the fake
camera servers' CPU, and resident memory over the run (growth after the warm-up).

Before and after the live run, in the same process and on the same frames (the demo videos at the served size,
mosaicked and demosaicked as the cameras and the ring do), the detector alone: whole-frame and packed throughput in
camera-frames per second (:func:`detector_alone`; the report gives both runs and their mean). The report's
``summary`` puts the live pipeline against it: live detected camera-frames per second over the detector-alone
packed throughput (the issue-15 target: >= 0.8), end-to-end latency p50/p95, ticks missed after the warm-up, and
CPU per stage in cores (capture threads, Aravis stream threads, detector threads, the event loop with its 60 Hz
tick, the keypoint tracking).

Keypoints between detections (issue 31, ``[detector.tracking]``): per camera, keypoint sets delivered per second,
and per person in view (person-keypoint-sets per second over the people per detection), the tracking's CPU per
tracked frame and per tracked person, and the tracked keypoints' error against each new detection of the same
frame (px, median and p90, per joint group and by age), pooled over the cameras for the measured window;
``summary.targets_issue_31`` sets them against the issue's targets.
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import json
import math
import os
import sys
import threading
import time
from dataclasses import asdict
from pathlib import Path
from statistics import median
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from mocapd.errors import MocapdError
from mocapd.io import cpu_budget, lifecycle
from mocapd.io.aravis_camera import load_aravis
from mocapd.io.pixels import convert_into, from_rgb, pixel_format
from mocapd.io.pose2sim_demo import CAMERAS, demo_video
from mocapd.pipeline.detector import OnnxPoseDetector
from mocapd.pipeline.detector_config import DetectorConfig
from mocapd.pipeline.detector_pool import detector_executor
from mocapd.pipeline.keypoint_tracker import JOINT_GROUPS, error_summary
from mocapd.pipeline.packing import packed_detector_from_config
from mocapd.service.assembly import RunOptions
from mocapd.service.bench.machine import machine
from mocapd.service.config import Config, load_config
from mocapd.service.daemon import Daemon
from mocapd.service.demo.cameras import CameraDemoOptions, in_private_netns, run_camera_demo
from mocapd.sim.fake_gige import load_video_rgb
from mocapd.sim.fake_rig import cpu_seconds

WARM_UP_S = 20.0  # model sessions, numba kernel and every ring / buffer pool touched once
ALONE_PASSES = 20  # detector-alone passes (each: one frame of every camera), after ALONE_WARM_UP untimed ones
ALONE_WARM_UP = 2


def _rss_mb() -> float:
    with open("/proc/self/statm") as fh:
        pages = int(fh.read().split()[1])
    return pages * os.sysconf("SC_PAGE_SIZE") / 2**20


def _cpu_s(pid: int, tid: int | None = None) -> float:
    """:func:`~mocapd.sim.fake_rig.cpu_seconds`, 0 for a thread or process that is gone."""
    seconds = cpu_seconds(pid, tid)
    return 0.0 if math.isnan(seconds) else seconds


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
        elif name.startswith("mocapd-track"):
            kind = "tracking"
        elif name.startswith("arv"):
            kind = "aravis"
        else:
            kind = "other"
        out[kind] = out.get(kind, 0.0) + _cpu_s(os.getpid(), tid)
    return out


def served_frames(opts: CameraDemoOptions, n_frames: int) -> list[list[NDArray[np.uint8]]]:
    """The first ``n_frames`` frames of every demo camera as the detector gets them live, BGR (h, w, 3): the video
    resized to the served size, sent in the cameras' pixel format and converted as the ring converts it.

    Returns
    -------
    list over frames of list over cameras of ndarray, shape (h, w, 3), uint8
    """
    fmt = pixel_format(opts.pixel_format)
    w, h = opts.size
    per_camera = []
    for cam in CAMERAS:
        out = []
        for rgb in load_video_rgb(demo_video(opts.demo, cam), min(n_frames, opts.max_frames), opts.size):
            image = np.empty((h, w, fmt.channels), np.uint8)
            convert_into(fmt, from_rgb(rgb, fmt), h, w, image)
            rgb3 = image if fmt.channels == 3 else np.repeat(image, 3, axis=2)
            out.append(np.asarray(cv2.cvtColor(rgb3, cv2.COLOR_RGB2BGR), np.uint8))
        per_camera.append(out)
    n = min(len(f) for f in per_camera)
    return [[per_camera[c][k % n] for c in range(len(CAMERAS))] for k in range(n_frames)]


def detector_alone(cfg: DetectorConfig, frames: list[list[NDArray[np.uint8]]], warm_up: int) -> dict[str, Any]:
    """Throughput of the detector alone, in camera-frames per second: whole-frame (one inference per camera frame)
    and packed (every camera's frame per pass, ROIs on shared canvases), over the same consecutive frames, the two
    interleaved pass by pass (their order alternating) so that other load on the machine hits both alike.

    Parameters
    ----------
    cfg : DetectorConfig
        The live run's detector section (providers, threads, model, packing options).
    frames : list over passes of list over cameras of ndarray, shape (h, w, 3), uint8, BGR
    warm_up : int
        Leading passes not timed (sessions allocate on their first runs; the packer finds the people).
    """
    sizes = [(im.shape[1], im.shape[0]) for im in frames[0]]
    whole = OnnxPoseDetector.from_config(cfg)
    packing = dataclasses.replace(cfg.packing, enabled=True)
    packer = packed_detector_from_config(dataclasses.replace(cfg, packing=packing), sizes)
    t_whole: list[float] = []
    t_packed: list[float] = []
    cpu: dict[str, float] = {"whole": 0.0, "packed": 0.0}  # process CPU seconds in the timed passes
    canvases: list[int] = []
    for k, cams in enumerate(frames):
        for name in ("whole", "packed") if k % 2 == 0 else ("packed", "whole"):
            t0, c0 = time.perf_counter(), time.process_time()
            if name == "whole":
                for im in cams:
                    whole.detect(im)
            else:
                packer.detect([cams])
            dt = time.perf_counter() - t0
            if k >= warm_up:
                (t_whole if name == "whole" else t_packed).append(dt)
                cpu[name] += time.process_time() - c0
        if k >= warm_up:
            canvases.append(len(packer.last_packings))
    n_cams = len(frames[0])

    def rate(times: list[float]) -> float:
        # Total frames over total time: the packer's periodic whole-frame refresh passes count at their cost.
        return round(n_cams * len(times) / sum(times), 2) if times else 0.0

    def cores(name: str, times: list[float]) -> float | None:
        # The process's CPU over the passes' wall time: nothing else of the process runs then, so this is the
        # detector's (onnxruntime's and OpenVINO's threads included).
        return round(cpu[name] / sum(times), 3) if times else None

    return {"passes": len(t_whole), "camera_frames_per_pass": n_cams, "image_size": list(sizes[0]),
            "whole_camera_frames_per_s": rate(t_whole), "packed_camera_frames_per_s": rate(t_packed),
            "whole_pass_ms_median": round(1e3 * median(t_whole), 1) if t_whole else None,
            "packed_pass_ms_median": round(1e3 * median(t_packed), 1) if t_packed else None,
            "packed_canvases_per_pass_mean": round(float(np.mean(canvases)), 2) if canvases else None,
            "whole_cpu_cores": cores("whole", t_whole), "packed_cpu_cores": cores("packed", t_packed),
            "providers": whole.providers, "precision": whole.precision,  # what runs ("auto" resolved)
            "intra_op_threads": cfg.intra_op_threads}  # fmt: skip


class Measure:
    """Samples the running demo daemon: memory each second, counters at the warm-up's end and at the end."""

    def __init__(self, seconds: float, warm_up_s: float = WARM_UP_S) -> None:
        self.seconds = seconds
        self.warm_up_s = warm_up_s
        self.result: dict[str, Any] = {}

    def _snapshot(self, daemon: Daemon) -> dict[str, Any]:
        st = daemon.status()
        frames = [getattr(s, "frames", None) for s in daemon.rig.sources]  # DetectorKeypointSource's capture
        tids = {t for f in frames if isinstance(t := getattr(f, "thread_id", None), int)}
        servers = {f["name"]: _cpu_s(f["pid"]) for f in st["fake_cameras"] if f["pid"]}
        trackers = [t for s in daemon.rig.sources if (t := getattr(s, "tracker", None)) is not None]
        return {"t": time.monotonic(), "status": st, "threads": thread_cpu_by_kind(tids),
                "process_cpu": time.process_time(), "servers": servers, "trackers": trackers,
                "tracker_errors": [t.error_count for t in trackers]}  # fmt: skip

    async def __call__(self, daemon: Daemon) -> None:
        rss: list[tuple[float, float]] = []
        t0 = time.monotonic()
        percentiles: list[dict[str, Any]] = []
        a: dict[str, Any] | None = None
        end = t0 + self.warm_up_s + self.seconds
        while (now := time.monotonic()) < end:
            await asyncio.sleep(min(1.0, end - now))
            now = time.monotonic()
            rss.append((round(now - t0, 1), round(_rss_mb(), 1)))
            if a is None and now - t0 >= self.warm_up_s:
                a = self._snapshot(daemon)
                # The measured window is ``seconds`` from this snapshot: an event loop that stalled past the
                # warm-up's end (a loaded machine) would otherwise leave a window of a few ms, and rates of 0.
                end = a["t"] + self.seconds
            if a is not None and len(rss) % 30 == 0:
                e2e = daemon.status()["latency_ms"]["end_to_end"]
                percentiles.append({"t_s": round(now - t0, 1), "p50": e2e["p50"], "p95": e2e["p95"]})
        assert a is not None
        b = self._snapshot(daemon)
        self.result = summarize(a, b, rss, percentiles, self.warm_up_s)
        self.result["tracked_vs_detected_px"] = tracked_errors(a)
        # Where the tick's budget went (per person job, by stage) and what the governor shed, at the end.
        end = b.get("status", {})
        for key in ("person_cpu_ms", "solve_threads", "governor"):
            self.result[key] = end.get(key)
        self.result["tracking_rate_hz_by_camera"] = [
            c.get("tracking", {}).get("rate_hz") for c in end.get("cameras", [])
        ]
        # [detector] landmarks: what ran at the end (with "auto": the choice, its reason, per-camera rates) and the
        # passes with landmarks per second over the measured window.
        marks = [(s.get("status", {}).get("detector") or {}).get("landmarks") for s in (a, b)]
        if isinstance(marks[1], dict):
            self.result["landmarks"] = marks[1]
            if isinstance(marks[0], dict) and "landmark_passes" in marks[1]:
                done = {v: n - marks[0]["landmark_passes"].get(v, 0) for v, n in marks[1]["landmark_passes"].items()}
                self.result["landmark_passes_per_s"] = {v: round(n / (b["t"] - a["t"]), 2) for v, n in done.items()}


def summarize(
    a: dict[str, Any],
    b: dict[str, Any],
    rss: list[tuple[float, float]],
    percentiles: list[dict[str, Any]],
    warm_up_s: float = WARM_UP_S,
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
            "failures": cb["capture"]["failures"], "detection_delay_ms": cb.get("detection_delay_ms"),
            "tracking": _tracking(ca, cb, wall),
        }  # fmt: skip
    detected = sum((cb["detected"] - ca["detected"]) for ca, cb in zip(sa["cameras"], sb["cameras"], strict=True))
    stage_cpu = {k: round(v - sa["cpu_s"].get(k, 0.0), 2) for k, v in sb["cpu_s"].items()}
    after = [m for t, m in rss if t >= warm_up_s]
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
        "detection_kinds": sorted({str(c.get("kind")) for c in sb["cameras"]}),
        "latency_at_end": sb["output"].get("latency"),
        "detection_group_at_end": sb["cameras"][0].get("packing"),
        "detection_group_window": _group_window(sa["cameras"][0].get("packing"), sb["cameras"][0].get("packing")),
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
                      "warm_up_s": warm_up_s},
        "task_failures": {k: v["failures"] for k, v in sb["tasks"].items()},
    }  # fmt: skip


def tracked_errors(a: dict[str, Any]) -> dict[str, Any] | None:
    """The tracked keypoints' error against each new detection of the same frame, measured since snapshot ``a``,
    pooled over the cameras (:func:`~mocapd.pipeline.keypoint_tracker.error_summary`), with each camera's median."""
    trackers = a.get("trackers")
    if not trackers:
        return None
    parts = [t.errors(since) for t, since in zip(trackers, a["tracker_errors"], strict=True)]
    pooled = [np.concatenate([p[k] for p in parts]) for k in range(3)]
    out = error_summary(pooled[0], pooled[1], pooled[2])
    out["camera_medians"] = [round(float(np.median(p[0])), 2) if p[0].size else None for p in parts]
    out["joint_groups"] = list(JOINT_GROUPS)
    return out


def _tracking(ca: dict[str, Any], cb: dict[str, Any], wall: float) -> dict[str, Any] | None:
    """One camera's keypoints between detections over the window (None: no tracking)."""
    ta, tb = ca.get("tracking"), cb.get("tracking")
    if ta is None or tb is None:
        return None
    sets = tb["keypoint_sets"] - ta["keypoint_sets"]
    person_sets = tb["person_keypoint_sets"] - ta["person_keypoint_sets"]
    frames = tb["frames"] - ta["frames"]
    cpu = tb["cpu_s"] - ta["cpu_s"]
    detections = cb["detected"] - ca["detected"]
    people = (cb["detected_people"] - ca["detected_people"]) / detections if detections else None
    person_hz = person_sets / wall
    return {
        "keypoint_sets_per_s": round(sets / wall, 2), "person_keypoint_sets_per_s": round(person_hz, 2),
        "people_per_detection": round(people, 3) if people is not None else None,
        # Keypoints per second for each person in view: the people the detector sees in this camera, on average.
        "keypoint_hz_per_person": round(person_hz / people, 2) if people else None,
        "tracked_frames_per_s": round(frames / wall, 2), "cpu_cores": round(cpu / wall, 4),
        "cpu_ms_per_frame": round(1e3 * cpu / frames, 3) if frames else None,
        "cpu_ms_per_person_frame": round(1e3 * cpu / person_sets, 3) if person_sets else None,
        "detections_late": tb["tracker"]["detections_late"] - ta["tracker"]["detections_late"],
        "people_dropped_age": tb["tracker"]["people_dropped_age"] - ta["tracker"]["people_dropped_age"],
        "people_dropped_keypoints": (tb["tracker"]["people_dropped_keypoints"]
                                     - ta["tracker"]["people_dropped_keypoints"]),
        "people_kept_missed": tb["tracker"]["people_kept_missed"] - ta["tracker"]["people_kept_missed"],
        # Detections delivered as they are while tracking stepped back (they came later than it can carry).
        "detections_delivered": tb["detections_delivered"] - ta["detections_delivered"],
        "steps_back": tb["steps_back"] - ta["steps_back"], "active_at_end": tb["active"],
        "thread": tb["thread"],
    }  # fmt: skip


def _group_window(a: dict[str, Any] | None, b: dict[str, Any] | None) -> dict[str, Any] | None:
    """The packed detection group over the measured window: passes, and a pass's milliseconds inside onnxruntime
    and outside it (frame conversion, canvases, decoding: what limits a GPU detector)."""
    if not a or not b or "inference_s" not in b:
        return None
    passes = b["passes"] - a["passes"]
    busy = b["detector_busy_s"] - a["detector_busy_s"]
    inference = b["inference_s"] - a["inference_s"]
    per = 1e3 / passes if passes else 0.0
    return {"passes": passes, "busy_s": round(busy, 2), "inference_s": round(inference, 2),
            "pass_ms": round(busy * per, 2), "inference_ms_per_pass": round(inference * per, 2),
            "rest_ms_per_pass": round((busy - inference) * per, 2)}  # fmt: skip


def _mean(values: list[float | None]) -> float | None:
    kept = [v for v in values if v is not None]
    return round(sum(kept) / len(kept), 3) if kept else None


def _mean_of(a: float | None, b: float | None) -> float | None:
    return round((a + b) / 2, 3) if a is not None and b is not None else None


def per_core(camera_frames_per_s: float, cores: float | None) -> float | None:
    """Camera frames per second per core of CPU the detector used (None where it used none measurable)."""
    return round(camera_frames_per_s / cores, 2) if cores else None


def headline(alone: dict[str, Any], live: dict[str, Any], cameras: int) -> dict[str, Any]:
    """The numbers issue 15 asks for, from the detector-alone figures and the live run's report.

    Beside the ratio of the rates, the ratio per core of CPU the detector had: on a machine whose cores the
    detector shares live (the tick, the capture, a simulated rig's camera servers) the first falls with the
    detector's share of the cores, the second only where the live pipeline wastes the cores it gets.
    """
    live_rate = live["detector_camera_frames_per_s"]
    packed, whole = alone["packed_camera_frames_per_s"], alone["whole_camera_frames_per_s"]
    out = live["output"]
    ticks = out["frames"] + out["missed_ticks"]
    threads = live["cpu_fraction_of_one_core"]["threads"]
    e2e = live["end_to_end_ms_last_window"]
    live_per_core = per_core(live_rate, threads.get("detector"))
    alone_per_core = per_core(packed, alone.get("packed_cpu_cores"))
    tracking = [c["tracking"] for c in live["cameras"].values() if c.get("tracking")]
    per_person = [t["keypoint_hz_per_person"] for t in tracking if t["keypoint_hz_per_person"] is not None]
    errors = live.get("tracked_vs_detected_px") or {}
    error_median = (errors.get("all") or {}).get("median")
    missed = round(out["missed_ticks"] / ticks, 4) if ticks else None
    group = live.get("detection_group_at_end") or {}
    return {
        "detector_alone_packed_camera_frames_per_s": packed,
        "detector_alone_whole_camera_frames_per_s": whole,
        "live_detected_camera_frames_per_s": live_rate,
        "live_over_alone_packed": round(live_rate / packed, 3) if packed else None,
        "live_over_alone_whole": round(live_rate / whole, 3) if whole else None,
        "detector_alone_packed_cpu_cores": alone.get("packed_cpu_cores"),
        "detector_alone_packed_camera_frames_per_core_s": alone_per_core,
        "live_detected_camera_frames_per_detector_core_s": live_per_core,
        "live_over_alone_packed_per_core": (
            round(live_per_core / alone_per_core, 3) if live_per_core and alone_per_core else None
        ),
        "live_detection": live["detection_kinds"],
        "end_to_end_ms_p50": e2e["p50"], "end_to_end_ms_p95": e2e["p95"],
        "detector_pass_ms": live.get("detection_group_window"),
        "missed_ticks_after_warm_up": out["missed_ticks"],
        "missed_tick_fraction_after_warm_up": missed,
        # People solved per output frame (2 people in the videos): what the keypoints give the solver.
        "person_solves_per_frame": live["people"]["person_solves_per_frame"],
        "detector_sessions": group.get("sessions"),
        "detection_modes": (group.get("mode") or {}).get("passes"),
        "keypoint_hz_per_person_by_camera": per_person,
        "keypoint_sets_per_s_by_camera": [t["keypoint_sets_per_s"] for t in tracking],
        "tracking_cpu_ms_per_frame": _mean([t["cpu_ms_per_frame"] for t in tracking]),
        "tracking_cpu_ms_per_person_frame": _mean([t["cpu_ms_per_person_frame"] for t in tracking]),
        "tracked_vs_detected_px_median": error_median,
        "tracked_vs_detected_px_by_joint_group": {g: v["median"] for g, v in
                                                  (errors.get("by_joint_group") or {}).items()},
        "targets_issue_31": {
            "keypoint_hz_per_person_min": min(per_person) if per_person else None,
            "keypoints_30hz_per_person": bool(per_person) and min(per_person) >= 30.0,
            "end_to_end_p50_le_150ms": e2e["p50"] is not None and e2e["p50"] <= 150.0,
            "end_to_end_p95_le_200ms": e2e["p95"] is not None and e2e["p95"] <= 200.0,
            "missed_ticks_le_1pct": missed is not None and missed <= 0.01,
            "tracked_error_median_le_5px": error_median is not None and error_median <= 5.0,
        },
        "cpu_cores": {"capture_threads": threads.get("capture", 0.0),
                      "capture_threads_per_camera": round(threads.get("capture", 0.0) / cameras, 4),
                      "aravis_stream_threads": threads.get("aravis", 0.0),
                      "detector_threads": threads.get("detector", 0.0),
                      "event_loop_with_tick": threads.get("event_loop", 0.0),
                      # Tracking: on the capture threads (thread = "capture": part of capture_threads) or its pool.
                      "tracking": round(sum(t["cpu_cores"] for t in tracking), 4) if tracking else None,
                      "tracking_pool_threads": threads.get("tracking", 0.0),
                      "other_threads": threads.get("other", 0.0),
                      "tick_stages": live["cpu_fraction_of_one_core"]["scheduler_stages"],
                      "daemon_process": live["cpu_fraction_of_one_core"]["daemon_process"]},
    }  # fmt: skip


def child_main(argv: list[str] | None = None) -> int:
    """Inside the private network namespace: the detector alone, then the demo run and measured; prints the JSON
    report."""
    p = argparse.ArgumentParser()
    p.add_argument("--seconds", type=float, default=120.0)
    p.add_argument("--warm-up", type=float, default=WARM_UP_S)
    p.add_argument("--alone-passes", type=int, default=ALONE_PASSES)
    p.add_argument("--options", default="{}")
    p.add_argument("--config", type=Path, default=None)
    args = p.parse_args(argv)
    lifecycle.install_stop_signals("mocapd bench latency (in its network namespace)")  # names the stop line
    try:
        load_aravis()  # before a minute of detector passes: no Aravis, no fake cameras, no benchmark
    except MocapdError as exc:
        print(f"error: {exc}", file=sys.stderr, flush=True)
        return 2
    opts = CameraDemoOptions(**json.loads(args.options))
    # The base config's [detector] (providers, precision, threads, packing) and [daemon] rates are the ones run;
    # the demo's cameras and calibration replace its rig.
    config: Config = load_config(args.config)
    # Inside the namespace: any free port (nothing outside it reads them).
    config = config.model_copy(update={"daemon": config.daemon.model_copy(update={"http_port": 0}),
                                       "websocket": config.websocket.model_copy(update={"port": 0})})  # fmt: skip
    m = config.detector.model
    load0 = os.getloadavg()

    def alone_now() -> dict[str, Any]:
        # The frames are decoded again each time rather than kept: 130 MB held through the live run would count
        # in its memory figures. On a thread named like the detector's workers: OpenVINO's TBB pool is
        # process-wide, made by the first thread that infers and named after it (Linux), and the live detector
        # then runs on those same threads; started from the main thread they counted as "other", not "detector".
        frames = served_frames(opts, ALONE_WARM_UP + args.alone_passes)
        with detector_executor() as named:
            return named.submit(detector_alone, config.detector.options(), frames, ALONE_WARM_UP).result()

    # The detector alone before and after the live run, so that a change of load on a shared machine shows as a
    # difference between the two instead of hiding in the ratio.
    measure = Measure(args.seconds, args.warm_up)

    async def live(stop: asyncio.Event) -> int:
        return await run_camera_demo(config, opts, RunOptions(), monitor=measure, stop=stop)

    try:  # the detector alone and the live run both under the budget: the report's ratio compares like with like
        budget = cpu_budget.hold(opts.cpu_budget) if opts.cpu_budget is not None else None
    except MocapdError as exc:
        print(f"error: {exc}", file=sys.stderr, flush=True)
        return 2
    try:
        before = alone_now()
        code = lifecycle.run_until_stopped(live)
        if lifecycle.requested() is not None:
            return 0  # stopped: nothing measured to report
        after = alone_now()
    except MocapdError as exc:  # no Aravis, no model, a camera that did not start: the cause in one line
        print(f"error: {exc}", file=sys.stderr, flush=True)
        return 2
    finally:
        throttling = budget.describe() if budget is not None else None
        cpu_budget.release()
    alone = {"before_live_run": before, "after_live_run": after,
             **{k: round((before[k] + after[k]) / 2, 2) for k in ("whole_camera_frames_per_s",
                                                                   "packed_camera_frames_per_s")},
             "packed_cpu_cores": _mean_of(before["packed_cpu_cores"], after["packed_cpu_cores"])}  # fmt: skip
    report = {
        "rig": {"cameras": len(CAMERAS),
                "source": f"Pose2Sim {opts.demo} videos, fake GigE Vision cameras in a private netns",
                "image": list(opts.size), "pixel_format": opts.pixel_format,
                "camera_fps": 60 * opts.speed, "detector": f"{m.input_width}x{m.input_height} yolo11n-pose, "
                f"{config.detector.workers} worker(s), providers {list(config.detector.providers)}, "
                f"precision {config.detector.precision}",
                "config": str(args.config) if args.config is not None else "shipped config.toml",
                "options": asdict(opts)},
        "summary": headline(alone, measure.result, len(CAMERAS)) if measure.result else None,
        "detector_alone": alone,
        **measure.result,
        "cpu_budget": throttling,
        "machine": {**machine(), "loadavg_at_start": [round(x, 2) for x in load0],
                    "loadavg_at_end": [round(x, 2) for x in os.getloadavg()]},
    }  # fmt: skip
    print(json.dumps(report, indent=2), flush=True)
    return code


def run(
    seconds: float,
    opts: CameraDemoOptions,
    *,
    warm_up_s: float = WARM_UP_S,
    alone_passes: int = ALONE_PASSES,
    config: Path | None = None,
) -> int:
    """``mocapd bench latency --rig cameras``: re-run this module in a private network namespace (``config``: the
    base config whose detector settings are measured; default the shipped one)."""
    extra = [] if config is None else ["--config", str(config.resolve())]
    return in_private_netns(
        "mocapd.service.bench.cameras:child_main",
        ["--seconds", str(seconds), "--warm-up", str(warm_up_s), "--alone-passes", str(alone_passes),
         "--options", json.dumps(asdict(opts)), *extra],
    )  # fmt: skip


if __name__ == "__main__":
    lifecycle.child_main(["mocapd.service.bench.cameras:child_main", *sys.argv[1:]])
