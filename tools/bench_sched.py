"""Detection scheduling policies of the live packed group, compared in one process on the Pose2Sim demo frames.

Developer benchmark, not a ``mocapd bench`` verb (those are the benchmarks a user runs).

The daemon's :class:`~mocapd.pipeline.packed_source.PackedDetectionGroup` runs back-to-back passes over cameras
that always have a new frame (60 fps cameras, a detector far slower). This benchmark drives its pass function
directly (no capture, no event loop) with the four ``Demo_MultiPerson`` cameras at 544x960, interleaving policies
in blocks so that a shared machine's load drifts over all of them alike:

* ``canvas``: what the daemon does: one canvas's worth of cameras per pass, longest-waiting first;
* ``all``: every camera in one pass (what the group did before issue 15);
* ``whole``: one camera per pass, letterboxed whole (``[detector.packing] enabled = false``, or "auto"'s other mode);

each with the model's own input only (``square``) and with ``[detector] fitted_inputs`` (``fitted``: whole frames
at the camera's aspect, canvases cropped to their tiles).

Per policy: camera frames detected per second of detector time, and per camera the *need* (detections in at
``done_k`` for a frame taken at ``take_k``: ``done_k - take_{k-1}``, the delay + interval that ``latency_s =
"auto"`` must cover), its p50/p95, and the pure delay ``done_k - take_k``. Prints one JSON object.

    .venv/bin/python tools/bench_sched.py --blocks 6 --passes 8 --threads 2 [--policies canvas all whole]
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from mocapd.io.pose2sim_demo import CAMERAS, demo_video
from mocapd.pipeline.detector_config import DetectorConfig
from mocapd.pipeline.frame_ring import FrameRef
from mocapd.pipeline.packed_source import PackedDetectionGroup
from mocapd.pipeline.packing import packed_detector_from_config

SIZE = (544, 960)


class LoopingCamera:
    """A camera that always has a new frame: the demo video's frames in turn (RGB, as rings hold them)."""

    def __init__(self, camera: int, frames: list[NDArray[np.uint8]]) -> None:
        self.camera = camera
        self.frames = frames
        self.seq = 0
        self.taken: list[int] = []  # perf_counter_ns of each take

    def has_new_frame(self) -> bool:
        return True

    def take_newest(self) -> tuple[FrameRef, NDArray[np.uint8]]:
        now = time.perf_counter_ns()
        self.taken.append(now)
        ref = FrameRef(f"cam{self.camera}", self.seq, now, now, self.seq)
        image = self.frames[self.seq % len(self.frames)]
        self.seq += 1
        return ref, image


def _no_canvases(_cameras: object) -> int:
    return 0


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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--blocks", type=int, default=6, help="rounds of blocks (one per policy and input)")
    ap.add_argument("--passes", type=int, default=8, help="passes per block")
    ap.add_argument("--threads", type=int, default=2, help="onnxruntime intra-op threads")
    ap.add_argument("--policies", nargs="+", default=["canvas", "whole"], choices=["canvas", "all", "whole"])
    ap.add_argument("--inputs", nargs="+", default=["square", "fitted"], choices=["square", "fitted"],
                    help="square: the model's own input only; fitted: whole frames at the camera's aspect and "
                    "canvases cropped to their tiles ([detector] fitted_inputs)")  # fmt: skip
    args = ap.parse_args()
    frames = demo_frames(30)
    groups: dict[str, PackedDetectionGroup] = {}
    for inp in args.inputs:
        cfg = DetectorConfig(intra_op_threads=args.threads, fitted_inputs="auto" if inp == "fitted" else False)
        groups[inp] = PackedDetectionGroup(
            packed_detector_from_config(cfg, [SIZE] * len(frames)), ThreadPoolExecutor(1)
        )
    runs = [(f"{policy}/{inp}", policy, inp) for inp in args.inputs for policy in args.policies]
    load0 = os.getloadavg()
    stats: dict[str, dict[str, Any]] = {
        name: {"frames": 0, "busy_ns": 0, "needs": [], "delays": []} for name, *_ in runs
    }
    for block in range(args.blocks + 1):  # block 0 warms the sessions and seeds the ROIs, unmeasured
        for name, policy, inp in runs:
            group = groups[inp]
            packer = group.packer
            canvases_for = packer.canvases_for
            cams = [LoopingCamera(i, f) for i, f in enumerate(frames)]
            group.sources = {}
            for c in cams:
                group.add(c)  # type: ignore[arg-type]  # the group only calls take_newest / has_new_frame
            # "all": every camera fits the first one's canvases (a pass over all of them, as before issue 15).
            if policy == "all":
                setattr(packer, "canvases_for", _no_canvases)  # noqa: B010
            done: dict[int, list[tuple[int, int]]] = {c.camera: [] for c in cams}  # (take, done) per camera
            for _ in range(args.passes):
                t0 = time.perf_counter_ns()
                found = group._whole_pass() if policy == "whole" else group._packed_pass()
                t1 = time.perf_counter_ns()
                assert found
                if block == 0:
                    group.passes += 1
                    for cam in found:
                        group._detected_at[cam] = group.passes
                    continue
                stats[name]["frames"] += len(found)
                stats[name]["busy_ns"] += t1 - t0
                group.passes += 1
                for cam in found:
                    done[cam].append((cams[cam].taken[-1], t1))
                    group._detected_at[cam] = group.passes  # what _run_pass records (longest-waiting first)
            setattr(packer, "canvases_for", canvases_for)  # noqa: B010
            for pairs in done.values():
                for (t_prev, _), (t_k, d_k) in itertools.pairwise(pairs):
                    stats[name]["needs"].append(d_k - t_prev)
                    stats[name]["delays"].append(d_k - t_k)
    cropped = {inp: g.packer.canvas_detector.cropped_canvases for inp, g in groups.items()}
    for g in groups.values():
        g.close()

    def ms(values: list[int], q: float) -> float | None:
        return round(float(np.percentile(values, q)) / 1e6, 1) if values else None

    report = {
        "rig": f"4 x Demo_MultiPerson {SIZE[0]}x{SIZE[1]}, yolo11n-pose 640, CPU, {args.threads} intra-op threads",
        "blocks": args.blocks, "passes_per_block": args.passes,
        "policies": {
            name: {"camera_frames_per_detector_s": round(s["frames"] / (s["busy_ns"] / 1e9), 2),
                   "need_p50_ms": ms(s["needs"], 50), "need_p95_ms": ms(s["needs"], 95),
                   "delay_p50_ms": ms(s["delays"], 50), "delay_p95_ms": ms(s["delays"], 95)}
            for name, s in stats.items()
        },
        "cropped_canvases": cropped,
        "loadavg": {"start": [round(x, 2) for x in load0], "end": [round(x, 2) for x in os.getloadavg()]},
        "cpus": os.cpu_count(),
    }  # fmt: skip
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
